"""Record what the flight controllers themselves report (their ground-station links), in the paper's
frame and in plan time: the truth a formation is judged by, not the companions' own reports.

Every record is stamped with the flight controllers' clock (SYSTEM_TIME and the telemetry's boot
time, as Unix time), never the wall's, so a run on a simulator's clock (lockstep) reads the same."""

from __future__ import annotations

import select
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from triswarm.protocol.mavlink import attitude_to_paper, local_ned_to_paper, mavlink, new_codec, reset_parser


@dataclass
class Track:
    t_unix: list = field(default_factory=list)
    position_m: list = field(default_factory=list)
    euler_rad: list = field(default_factory=list)


class Recorder:
    """Listen to every vehicle's gcs link in a background thread at ``rate_hz``."""

    def __init__(self, manifest: dict, rate_hz: float = 25.0) -> None:
        import socket

        self.rate_hz = rate_hz
        self.tracks: dict[int, Track] = {}
        self.statustexts: list[tuple[float, int, str]] = []
        self.heartbeats: dict[int, object] = {}
        self.modes: dict[int, list[tuple[float, int, bool]]] = {}
        """Per vehicle, every change of (custom mode, armed) with the flight controller's time it was
        heard at (Unix time; NaN before its clock was heard)."""
        self._fc_now: dict[int, float] = {}
        self._socks = {}
        self._codec = new_codec(254, 190)
        for v in manifest["vehicles"]:
            link = v["links"]["gcs"]
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.connect((link["host"], link["port"]))
            s.setblocking(False)
            self._socks[s] = v["sysid"]
            self.tracks[v["sysid"]] = Track()
        self._offset: dict[int, float] = {}
        self._boot_ms: dict[int, int] = {}
        self._att: dict[int, tuple] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> "Recorder":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for s in self._socks:
            s.close()

    def _send(self, s, msg) -> None:
        try:
            s.send(msg.pack(self._codec))
        except OSError:
            pass

    def _hello(self) -> None:
        interval = 1e6 / self.rate_hz
        for s, sysid in self._socks.items():
            self._send(s, mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))
            for msg_id in (mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED):
                self._send(s, mavlink.MAVLink_command_long_message(sysid, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                                   msg_id, interval, 0, 0, 0, 0, 0))

    def _run(self) -> None:
        parser = new_codec(254, 190)
        next_hello = 0.0
        while not self._stop.is_set():
            if time.monotonic() >= next_hello:
                self._hello()
                next_hello = time.monotonic() + 1.0
            ready, _, _ = select.select(list(self._socks), [], [], 0.1)
            for s in ready:
                sysid = self._socks[s]
                while True:
                    try:
                        data = s.recv(65535)
                    except (BlockingIOError, OSError):
                        break
                    reset_parser(parser)
                    for m in parser.parse_buffer(data) or []:
                        self._take(sysid, m)

    def _take(self, sysid: int, m) -> None:
        t = m.get_type()
        if m.get_srcSystem() != sysid:
            return
        if t == "SYSTEM_TIME" and m.time_unix_usec > 0:
            # (a track runs on the vehicle's boot clock from the first SYSTEM_TIME of each boot: a
            # step of its Unix time, someone setting its clock, does not move what it flew)
            boot = self._boot_ms.get(sysid)
            if sysid not in self._offset or boot is None or m.time_boot_ms < boot:
                self._offset[sysid] = m.time_unix_usec / 1e6 - m.time_boot_ms / 1000.0
            self._boot_ms[sysid] = m.time_boot_ms
            self._fc_now[sysid] = self._offset[sysid] + m.time_boot_ms / 1000.0
        elif t == "ATTITUDE":
            self._att[sysid] = (m.time_boot_ms, attitude_to_paper(m.roll, m.pitch, m.yaw))
        elif t == "LOCAL_POSITION_NED":
            att = self._att.get(sysid)
            off = self._offset.get(sysid)
            if att is not None and off is not None and att[0] == m.time_boot_ms:
                tr = self.tracks[sysid]
                tr.t_unix.append(off + m.time_boot_ms / 1000.0)
                self._fc_now[sysid] = tr.t_unix[-1]
                tr.position_m.append(local_ned_to_paper(m.x, m.y, m.z))
                tr.euler_rad.append(att[1])
        elif t == "STATUSTEXT":
            self.statustexts.append((self._fc_now.get(sysid, float("nan")), sysid, m.text))
        elif t == "HEARTBEAT" and m.get_srcComponent() == 1:
            self.heartbeats[sysid] = m
            state = (m.custom_mode, bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED))
            history = self.modes.setdefault(sysid, [])
            if not history or history[-1][1:] != state:
                history.append((self._fc_now.get(sysid, float("nan")), *state))

    def now(self) -> float:
        """The flight controllers' clock as last heard, as Unix time: the slowest vehicle's (NaN
        before every vehicle was heard)."""
        times = [self._fc_now.get(s) for s in self.tracks]
        return float("nan") if None in times else min(times)

    def arrays(self, start_unix: float, dt_s: float = 0.05, t_from: float | None = None, t_to: float | None = None):
        """Every vehicle resampled on a common plan-time grid: (t (T,), position (T, N, 3), euler
        (T, N, 3)), plan time t = unix - start_unix. Each vehicle's samples are interpolated."""
        sysids = sorted(self.tracks)
        # the recording may go on meanwhile: take each track as far as all three lists reach now
        counts = [min(len(tr.t_unix), len(tr.position_m), len(tr.euler_rad)) for tr in map(self.tracks.get, sysids)]
        spans = [np.asarray(self.tracks[s].t_unix[:n]) - start_unix for s, n in zip(sysids, counts)]
        lo = max(sp[0] for sp in spans) if t_from is None else t_from
        hi = min(sp[-1] for sp in spans) if t_to is None else t_to
        t = np.arange(lo, hi, dt_s)
        pos = np.zeros((t.size, len(sysids), 3))
        eta = np.zeros((t.size, len(sysids), 3))
        for k, (s, n) in enumerate(zip(sysids, counts)):
            tr = self.tracks[s]
            ts = spans[k]
            p = np.asarray(tr.position_m[:n])
            e = np.unwrap(np.asarray(tr.euler_rad[:n]), axis=0)
            for c in range(3):
                pos[:, k, c] = np.interp(t, ts, p[:, c])
                eta[:, k, c] = np.interp(t, ts, e[:, c])
        return t, pos, eta
