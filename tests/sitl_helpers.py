"""Start `triswarm sitl up` as a real process and talk to it: shared by the SITL tests."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time
from pathlib import Path

from pymavlink import mavutil

from triswarm.gcs.stack import stop_in_turn

_OPEN: list = []  # connections made while a SITL runs; closed when it stops


@contextlib.contextmanager
def sitl_process(tmp_path: Path, n: int = 1, *extra: str, startup_timeout_s: float = 120.0):
    """Yield (manifest dict, Popen); SIGTERM on exit and check the process ended by itself."""
    manifest = tmp_path / "manifest.json"
    stats = tmp_path / "stats.json"
    cmd = [sys.executable, "-m", "triswarm.gcs.cli", "sitl", "up", "-n", str(n), "--manifest", str(manifest),
           "--base-port", "0", "--stats", str(stats), "--quiet", *extra]
    out = (tmp_path / "sitl.out").open("w")
    err = (tmp_path / "sitl.err").open("w")
    proc = subprocess.Popen(cmd, stdout=out, stderr=err, text=True)
    try:
        deadline = time.monotonic() + startup_timeout_s
        while not manifest.exists():
            if proc.poll() is not None:
                raise RuntimeError(f"sitl exited with {proc.returncode}: {(tmp_path / 'sitl.err').read_text()}")
            if time.monotonic() > deadline:
                raise TimeoutError("sitl did not write its manifest in time")
            time.sleep(0.05)
        yield json.loads(manifest.read_text()), proc
    finally:
        while _OPEN:
            _OPEN.pop().close()
        stop_in_turn([[proc]])
        out.close()
        err.close()


def connect(url: str, sysid: int = 255, compid: int = 190):
    """A pymavlink connection that has introduced itself (the vehicle streams to whoever spoke)."""
    conn = mavutil.mavlink_connection(url, source_system=sysid, source_component=compid)
    _OPEN.append(conn)
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        hb = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=1.0)
        if hb is not None:
            return conn
    raise TimeoutError(f"no heartbeat from {url}")


def command(conn, target: int, cmd: int, *params: float, timeout: float = 3.0):
    p = list(params) + [0.0] * (7 - len(params))
    conn.mav.command_long_send(target, 1, cmd, 0, *p)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.5)
        if ack is not None and ack.command == cmd:
            return ack
    raise TimeoutError(f"no COMMAND_ACK for command {cmd}")


def _param_reply(conn, name: str, timeout: float) -> float:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        m = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5)
        if m is not None and m.param_id == name:
            return m.param_value
    raise TimeoutError(f"no PARAM_VALUE for {name}")


def read_param(conn, target: int, name: str, timeout: float = 3.0) -> float:
    conn.mav.param_request_read_send(target, 1, name.encode(), -1)
    return _param_reply(conn, name, timeout)


def set_param(conn, target: int, name: str, value: float, timeout: float = 3.0) -> float:
    """Set a parameter; returns the value the vehicle then reports (unchanged if it refused)."""
    conn.mav.param_set_send(target, 1, name.encode(), value, mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
    return _param_reply(conn, name, timeout)


def ports_free(manifest: dict) -> bool:
    import socket

    for v in manifest["vehicles"]:
        for link in v["links"].values():
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                s.bind((link["host"], link["port"]))
            except OSError:
                return False
            finally:
                s.close()
    return True
