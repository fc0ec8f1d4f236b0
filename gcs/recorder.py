"""Record what the flight controllers themselves report (their ground-station links), in the paper's
frame and in plan time: the truth a formation is judged by, not the companions' own reports.

Every record is stamped with the flight controllers' clock (SYSTEM_TIME and the telemetry's boot
time, as Unix time), never the wall's, so a run on a simulator's clock (lockstep) reads the same."""

from __future__ import annotations

import math
import select
import threading
import time

import numpy as np

from triswarm.protocol.mavlink import mavlink, new_codec, reset_parser

from .tracks import LiveTracks, Track, common_span_s, on_grid


class Recorder:
    """Listen to every vehicle's gcs link in a background thread at ``rate_hz``."""

    def __init__(self, manifest: dict, rate_hz: float = 25.0) -> None:
        import socket

        self.rate_hz = rate_hz
        self.statustexts: list[tuple[float, int, str]] = []
        self.heartbeats: dict[int, object] = {}
        self.modes: dict[int, list[tuple[float, int, bool]]] = {}
        """Per vehicle, every change of (custom mode, armed) with the flight controller's time it was
        heard at (Unix time; NaN before its clock was heard)."""
        self._socks = {}
        self._streams: dict = {}
        """The sockets of TCP links (a firmware's own ports), each with its parser: a byte stream."""
        self._codec = new_codec(254, 190)
        for v in manifest["vehicles"]:
            link = v["links"]["gcs"]
            if link.get("transport") == "tcp":
                s = socket.create_connection((link["host"], link["port"]), timeout=5.0)
                self._streams[s] = new_codec(254, 190)
            else:
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                s.connect((link["host"], link["port"]))
            s.setblocking(False)
            self._socks[s] = v["sysid"]
        home = manifest.get("home")
        self.samples = LiveTracks(sorted(self._socks.values()),
                                  None if home is None else (home["lat_deg"], home["lon_deg"], home["alt_m"]))
        """Every vehicle's samples as they came (``tracks.py``), positions from the swarm's home."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> "Recorder":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for s in set(self._socks) | set(self._streams):
            s.close()

    def _send(self, s, msg) -> None:
        try:
            s.send(msg.pack(self._codec))
        except OSError:
            pass

    def _hello(self) -> None:
        interval = 1e6 / self.rate_hz
        unknown_origin = set(self.samples.needing_origin())
        for s, sysid in self._socks.items():
            if sysid in unknown_origin:
                self._send(s, mavlink.MAVLink_command_long_message(sysid, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                                                   mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, 0, 0, 0, 0, 0, 0))
            self._send(s, mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))
            for msg_id, us in ((mavlink.MAVLINK_MSG_ID_ATTITUDE, interval), (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, interval),
                               (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, 1e6)):  # (ArduPilot streams none of them unasked)
                self._send(s, mavlink.MAVLink_command_long_message(sysid, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                                   msg_id, us, 0, 0, 0, 0, 0))

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
                    if not data:  # (the peer closed the connection: nothing more to hear on it)
                        self._socks.pop(s, None)
                        break
                    stream = self._streams.get(s)
                    if stream is None:
                        reset_parser(parser)  # (a datagram holds whole frames)
                    for m in (stream or parser).parse_buffer(data) or []:
                        self._take(sysid, m)

    def _take(self, sysid: int, m) -> None:
        t = m.get_type()
        if m.get_srcSystem() != sysid or self.samples.take(sysid, time.time(), m):
            return
        if t == "STATUSTEXT":
            self.statustexts.append((self.samples.heard_unix_s(sysid), sysid, m.text))
        elif t == "HEARTBEAT" and m.get_srcComponent() == 1:
            self.heartbeats[sysid] = m
            state = (m.custom_mode, bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED))
            history = self.modes.setdefault(sysid, [])
            if not history or history[-1][1:] != state:
                history.append((self.samples.heard_unix_s(sysid), *state))

    def now(self) -> float:
        """The flight controllers' clock as last heard, as Unix time: the slowest vehicle's (NaN
        before every vehicle was heard)."""
        times = [self.samples.heard_unix_s(s) for s in sorted(set(self._socks.values()))]
        return math.nan if any(map(math.isnan, times)) else min(times)

    def tracks(self, start_unix: float) -> dict[int, Track]:
        """Every vehicle's streams on plan time t = unix - start_unix, as recorded so far."""
        return self.samples.tracks(start_unix)

    def arrays(self, start_unix: float, dt_s: float = 0.05, t_from: float | None = None, t_to: float | None = None):
        """Every vehicle resampled on a common plan-time grid: (t (T,), position (T, N, 3), euler
        (T, N, 3)), plan time t = unix - start_unix; t_from and t_to default to the span every
        vehicle's streams cover (t_to is not on the grid)."""
        tracks = list(self.tracks(start_unix).values())
        lo, hi = common_span_s(tracks)
        t = np.arange(lo if t_from is None else t_from, hi if t_to is None else t_to, dt_s)
        pos, eta = on_grid(tracks, t)
        return t, pos, eta
