"""Bad input on the wire: >= 100,000 malformed or hostile frames at a running vehicle, in bursts
that it answers a probe after. It keeps its telemetry rate, answers a command afterwards, and counts
every frame it dropped."""

from __future__ import annotations

import json
import socket
import time

import numpy as np
import pytest
from pymavlink import mavutil

from triswarm.protocol.mavlink import new_codec

from .fuzz.mav import recrc
from .sitl_helpers import command, connect, sitl_process

M = mavutil.mavlink
PER_KIND = 21000
KINDS = ("random_bytes", "mutated_payload", "wrong_crc", "foreign_sysid", "nan_actuator")
BURST = 100
"""Frames between two probes: a burst fits a socket's default receive buffer (~200 datagrams)."""
PROBE_TS1 = 7 << 50


def templates(codec):
    """Valid frames of messages a vehicle handles, addressed to vehicle 1."""
    return [
        codec.command_long_encode(1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, 30, 0, 0, 0, 0, 0, 0),
        codec.command_int_encode(1, 1, 0, M.MAV_CMD_DO_SET_MODE, 0, 0, 1, 2, 0, 0, 0, 0, 0),
        codec.param_set_encode(1, 1, b"NOISE_POS_M", 0.0, M.MAV_PARAM_TYPE_REAL32),
        codec.param_request_read_encode(1, 1, b"MASS_KG", -1),
        codec.set_actuator_control_target_encode(0, 0, 1, 1, [0.2, 0.2, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0]),
        codec.timesync_encode(0, 42),
        codec.heartbeat_encode(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0),
    ]


def make_frames(rng: np.random.Generator) -> list[tuple[str, bytes]]:
    codec = new_codec(255, 190)
    base = templates(codec)
    frames: list[tuple[str, bytes]] = []
    for _ in range(PER_KIND):
        frames.append(("random_bytes", rng.integers(0, 256, int(rng.integers(1, 280)), dtype=np.uint8).tobytes()))
        msg = base[int(rng.integers(len(base)))]
        packed = bytearray(msg.pack(codec))
        plen = packed[1]
        for _ in range(int(rng.integers(1, 4))):
            packed[10 + int(rng.integers(plen))] = int(rng.integers(256))
        frames.append(("mutated_payload", recrc(packed, msg.crc_extra)))
        bad = bytearray(msg.pack(codec))
        bad[-1] ^= 0x5A
        frames.append(("wrong_crc", bytes(bad)))
        frames.append(("foreign_sysid", codec.command_long_encode(42, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 21196,
                                                                  0, 0, 0, 0, 0).pack(codec)))
        controls = [float(v) for v in rng.uniform(-1, 1, 8)]
        controls[int(rng.integers(6))] = float(rng.choice([np.nan, np.inf, -np.inf]))
        frames.append(("nan_actuator", codec.set_actuator_control_target_encode(0, 0, 1, 1, controls).pack(codec)))
    order = rng.permutation(len(frames))
    return [frames[k] for k in order]


@pytest.mark.realtime
def test_vehicle_survives_a_flood_of_bad_frames(tmp_path):
    frames = make_frames(np.random.default_rng(2024))
    assert len(frames) >= 100_000
    with sitl_process(tmp_path, 1) as (manifest, proc):
        link = manifest["vehicles"][0]["links"]["companion"]
        monitor = connect(link["pymavlink"])
        sent = {k: 0 for k in KINDS}
        stamps, walls = set(), []

        def probe(k: int) -> None:
            """Until the vehicle answers a TIMESYNC sent after burst k: it has then taken every frame
            sent before it (one socket, one queue), so the next burst never overflows its socket
            buffer, however slow the machine. ATTITUDE on the way is recorded."""
            ts1 = PROBE_TS1 + k
            monitor.mav.timesync_send(0, ts1)
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                msg = monitor.recv_match(type=["ATTITUDE", "TIMESYNC"], blocking=True, timeout=0.5)
                if msg is None:
                    continue
                if msg.get_type() == "TIMESYNC":
                    if msg.ts1 == ts1 and msg.tc1 != 0:
                        return
                    continue
                walls.append((time.monotonic(), msg.time_boot_ms))
                if msg.time_boot_ms % 10 == 0:  # the 100 Hz stream's grid (one-off replies land anywhere)
                    stamps.add(msg.time_boot_ms)
            raise AssertionError(f"the vehicle answered no TIMESYNC within 10 s after {k * BURST} frames")

        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            for k in range(0, len(frames), BURST):
                for kind, data in frames[k:k + BURST]:
                    sock.sendto(data, (link["host"], link["port"]))
                    sent[kind] += 1
                probe(k // BURST)
        finally:
            sock.close()
        (w0, t0), (w1, t1) = walls[0], walls[-1]
        assert w1 - w0 > 2.0
        rate = len(stamps) / ((t1 - t0) / 1000.0)
        assert rate >= 95.0, f"ATTITUDE stream at {rate:.1f} Hz of simulated time during the flood"
        realtime = (t1 - t0) / 1000.0 / (w1 - w0)
        assert realtime > 0.9, f"the simulation ran at {realtime:.2f} x real time during the flood"

        # afterwards it answers a heartbeat-triggered command
        monitor.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        ack = command(monitor, 1, M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        assert ack.result == M.MAV_RESULT_ACCEPTED
        # (1 Hz streams; the bound is generous for a loaded machine, a verdict only on what they say)
        status = monitor.recv_match(type="SYS_STATUS", blocking=True, timeout=15)
        assert status is not None, "no SYS_STATUS within 15 s after the flood"
        assert status.errors_comm > 0 and status.drop_rate_comm > 0
        hb = monitor.recv_match(type="HEARTBEAT", blocking=True, timeout=15)
        assert hb is not None, "no HEARTBEAT within 15 s after the flood"
        assert not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED  # the foreign arm commands were not ours
    assert proc.returncode == 0
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert stats["handler_exceptions"] == 0
    counters = stats["vehicles"][0]["counters"]
    print("sent", sent, "\ncounted", counters,
          f"\nATTITUDE stream during the flood: {rate:.1f} Hz, simulation at {realtime:.2f} x real time")
    # (every frame was taken, the probes say: each kind is counted at least as often as it was sent;
    # a mutated payload may add to a count)
    assert counters["drop_foreign_system"] >= sent["foreign_sysid"]
    assert counters["drop_actuator_non_finite"] >= sent["nan_actuator"]
    assert counters["drop_bad_crc"] >= sent["wrong_crc"]
    assert counters.get("drop_bad_frame", 0) > 0 and stats["vehicles"][0]["drops"] >= (
        sent["foreign_sysid"] + sent["nan_actuator"] + sent["wrong_crc"])
