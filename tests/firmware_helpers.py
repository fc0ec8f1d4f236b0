"""Real flight-controller firmware in the tests: where to find it, and a MAVLink peer of its own ports.

The firmware is never part of the project. A test finds ArduPilot's ArduCopter SITL binary through
TRISWARM_ARDUCOPTER, or else at ../shared/ardupilot/bin/arducopter beside the checkout (where CI
has it). Without it the test skips with one line saying how to get it; under CI it fails.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

from pymavlink import mavutil

from .needs import missing

ROOT = Path(__file__).resolve().parents[1]
SHARED_ARDUCOPTER = ROOT.parent / "shared" / "ardupilot" / "bin" / "arducopter"
SHARED_PX4 = ROOT.parent / "shared" / "px4" / "px4_sitl_zenoh.tar.gz"


def arducopter() -> Path:
    """The ArduCopter SITL binary (the test stops, skipped or failed, without one)."""
    given = os.environ.get("TRISWARM_ARDUCOPTER")
    path = Path(given) if given else SHARED_ARDUCOPTER
    if not (path.is_file() and os.access(path, os.X_OK)):
        missing(f"no ArduCopter SITL binary at {path}: set TRISWARM_ARDUCOPTER to one (build it: "
                "docs/flight-controllers.md, ArduPilot)")
    return path


def px4_package() -> Path:
    """The px4_sitl_zenoh build, its folder or its .tar.gz (the test stops, skipped or failed, without one)."""
    given = os.environ.get("TRISWARM_PX4")
    path = Path(given) if given else SHARED_PX4
    if not path.exists():
        missing(f"no PX4 firmware at {path}: set TRISWARM_PX4 to a px4_sitl_zenoh build (its folder or its .tar.gz; "
                "docs/flight-controllers.md, PX4)")
    return path


class Peer:
    """A MAVLink peer (system ``sysid``, component ``compid``) on a firmware's TCP port: it keeps
    every message it hears (a reader thread) and says hello once a second, as ground stations and
    companions do (a firmware sends its status texts only to links that have spoken)."""

    def __init__(self, url: str, sysid: int, compid: int) -> None:
        self.conn = mavutil.mavlink_connection(url, source_system=sysid, source_component=compid)
        self.messages: list = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> "Peer":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.conn.close()

    def _run(self) -> None:
        hello = 0.0
        while not self._stop.is_set():
            if time.monotonic() - hello > 1.0:
                hello = time.monotonic()
                self.send(self.conn.mav.heartbeat_encode(mavutil.mavlink.MAV_TYPE_GCS,
                                                         mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
            msg = self.conn.recv_match(blocking=True, timeout=0.1)
            if msg is not None and msg.get_type() != "BAD_DATA":
                with self._lock:
                    self.messages.append(msg)

    def send(self, msg) -> None:
        with self._lock:
            self.conn.mav.send(msg)

    def heard(self, type_: str) -> list:
        with self._lock:
            return [m for m in self.messages if m.get_type() == type_]

    def newest(self, type_: str):
        found = self.heard(type_)
        return found[-1] if found else None

    def texts(self) -> list[str]:
        return [m.text for m in self.heard("STATUSTEXT")]

    def command(self, command: int, *params: float, target: int = 1, timeout_s: float = 3.0) -> int | None:
        """COMMAND_LONG to the flight controller; its MAV_RESULT (None: no answer)."""
        p = list(params) + [0.0] * (7 - len(params))
        start = len(self.heard("COMMAND_ACK"))
        self.send(self.conn.mav.command_long_encode(target, 1, command, 0, *p))
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            acks = [a for a in self.heard("COMMAND_ACK")[start:] if a.command == command]
            if acks:
                return acks[-1].result
            time.sleep(0.02)
        return None

    def interval(self, msg_id: int, rate_hz: float, target: int = 1) -> None:
        self.command(mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / rate_hz, target=target)

    def set_mode(self, mode: int, timeout_s: float) -> None:
        """Into ArduPilot custom mode ``mode``, asked again every 2 s until its heartbeat says so (a
        firmware can accept GUIDED before it has a position, and fall back to its mode before)."""
        deadline = time.monotonic() + timeout_s
        while True:
            mark = len(self.heard("HEARTBEAT"))
            self.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)
            time.sleep(2.0)
            beats = [h for h in self.heard("HEARTBEAT")[mark:] if h.get_srcComponent() == 1]
            if beats and all(h.custom_mode == mode for h in beats):
                return
            assert time.monotonic() < deadline, f"not in mode {mode} after {timeout_s} s: {self.texts()[-3:]}"

    def until_accepted(self, command: int, *params: float, timeout_s: float) -> None:
        """Ask again every 2 s until accepted (a firmware refuses while its pre-arm checks fail)."""
        deadline = time.monotonic() + timeout_s
        while (result := self.command(command, *params)) != mavutil.mavlink.MAV_RESULT_ACCEPTED:
            assert time.monotonic() < deadline, f"command {command} refused for {timeout_s} s ({result}): " \
                                                f"{self.texts()[-3:]}"
            time.sleep(2.0)
