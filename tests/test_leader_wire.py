"""`triswarm leader goto` on the wire, read by an independent listener: positions in local NED and
yaw clockwise from north, as every MAVLink tool expects, whatever frame the command line speaks.

The listener is a bare UDP socket with pymavlink's parser standing where a companion would be: it
answers the plan-time parameter and acknowledges the command, and records what arrived.
"""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import threading
import time

import pytest

from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink, new_codec

PLAN_T_S = 12.5


def _listen(sock: socket.socket, seen: list, stop: threading.Event) -> None:
    """Beat like a companion, answer PLAN_T_S and ACK every command, for at most 60 s; record the
    COMMAND_LONGs."""
    codec = new_codec(1, COMP_ONBOARD)
    heartbeat = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                                                  0, 0, mavlink.MAV_STATE_ACTIVE, 3)
    deadline = time.monotonic() + 60.0
    peer = None
    sock.settimeout(0.1)
    while not stop.is_set() and time.monotonic() < deadline:
        if peer is not None:
            sock.sendto(heartbeat.pack(codec), peer)
        try:
            data, peer = sock.recvfrom(4096)
        except TimeoutError:
            continue
        for msg in codec.parse_buffer(data) or []:
            kind = msg.get_type()
            if kind == "PARAM_REQUEST_READ" and msg.target_system == 1:
                reply = mavlink.MAVLink_param_value_message(b"PLAN_T_S", PLAN_T_S,
                                                            mavlink.MAV_PARAM_TYPE_REAL32, 1, 0)
            elif kind == "COMMAND_LONG" and msg.target_system == 1:
                seen.append(msg)
                reply = mavlink.MAVLink_command_ack_message(msg.command, mavlink.MAV_RESULT_ACCEPTED)
            else:
                continue
            sock.sendto(reply.pack(codec), peer)


@pytest.mark.parametrize("args, ned_m, yaw_ned_deg", [
    (["8", "-5", "2", "--yaw", "30"], (8.0, 5.0, -2.0), -30.0),     # 5 m west is 5 m east negative
    (["-3", "4", "-1"], (-3.0, -4.0, 1.0), None),                    # no --yaw: NaN, the yaw is kept
])
def test_leader_goto_sends_ned(tmp_path, args, ned_m, yaw_ned_deg):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    manifest = tmp_path / "swarm.json"
    manifest.write_text(json.dumps({"swarm": "wire", "drones": [{"id": 1, "mavlink": f"udpout:127.0.0.1:{port}"}]}))
    seen: list = []
    stop = threading.Event()
    listener = threading.Thread(target=_listen, args=(sock, seen, stop), daemon=True)
    listener.start()
    try:
        r = subprocess.run([sys.executable, "-m", "triswarm.gcs.cli", "leader", "goto", *args, "--speed", "3",
                            "--manifest", str(manifest), "--tlog", str(tmp_path / "g.tlog")],
                           capture_output=True, text=True, timeout=60)
    finally:
        stop.set()
        listener.join(timeout=5)
        sock.close()
    assert r.returncode == 0, r.stdout + r.stderr
    goto = [m for m in seen if m.command == mavlink.MAV_CMD_TRISWARM_LEADER_GOTO]
    assert goto, [m.command for m in seen]
    m = goto[0]
    assert (m.param5, m.param6, m.param7) == pytest.approx(ned_m)
    assert m.param1 == pytest.approx(3.0)
    assert m.param3 == pytest.approx(PLAN_T_S + 1.0)  # the default lead of 1 s
    if yaw_ned_deg is None:
        assert math.isnan(m.param2)
    else:
        assert m.param2 == pytest.approx(math.radians(yaw_ned_deg))
