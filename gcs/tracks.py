"""Tracks: every drone's position and attitude as its flight controller reports them (ATTITUDE and
LOCAL_POSITION_NED from system i, component 1), in the paper's frame and on plan time. One piece of
logic for the live recorder (``recorder.py``) and for a run's log read afterwards (``runlog.py``).

Samples are kept as they came: per drone and stream (boot time, receive time, value), and the
SYSTEM_TIME offsets (Unix time - boot time). Each stream is timed and interpolated on its own
stamps, so attitude and position need not share an instant or a rate.

The clock rule is the companions': a track runs on the drone's boot clock with the offset its
SYSTEM_TIME gave last before the plan started on it (the companions take the flight controller's
Unix time as it comes on the ground, and fly on the boot clock once the plan runs: a later step of
the Unix time, someone setting the clock forwards or back, does not move what was flown; an earlier
one, a GPS fix correcting a clock that started from the computer's, does). Every sample of that boot, also those
that came before, is its boot time plus that offset; a boot whose SYSTEM_TIMEs all came after the
start runs on its first. A boot time that goes back by a second or more (``REBOOT_JUMP_US``) is a
new boot. A boot without any SYSTEM_TIME is timed by its receive times.

Positions are from the flight controller's local origin (its EKF origin). Given the swarm's home, a
boot whose GPS_GLOBAL_ORIGIN was heard has its positions moved by the distance from home to that
origin (ArduPilot takes its first GPS fix as origin unless told otherwise), as the companions do; the
last one heard in a boot holds for all of it (an EKF keeps its origin once set).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numpy as np

from triswarm.companion.telemetry import REBOOT_JUMP_US
from triswarm.protocol.frames import geodetic_from_mavlink, origin_offset_e_m
from triswarm.protocol.mavlink import COMP_AUTOPILOT, attitude_to_paper, local_ned_to_paper
from triswarm.protocol.metrics import wrap_angle

from .errors import GcsError

STREAMS = ("ATTITUDE", "LOCAL_POSITION_NED")


class TrackError(GcsError, ValueError):
    """A track that cannot be made, with the reason in one sentence."""


@dataclass
class StreamSamples:
    """One drone's samples of one message, in the order they came."""

    boot_s: list[float] = field(default_factory=list)
    received_unix_s: list[float] = field(default_factory=list)
    boot: list[int] = field(default_factory=list)
    """Which of the drone's boots (an index into DroneSamples.boot_clocks) the sample is of."""
    values: list[np.ndarray] = field(default_factory=list)

    def copy(self) -> "StreamSamples":
        return StreamSamples(list(self.boot_s), list(self.received_unix_s), list(self.boot), list(self.values))


@dataclass
class DroneSamples:
    """One drone's attitude (paper Euler angles [rad]) and position (paper earth frame [m]) samples,
    and per boot its SYSTEM_TIMEs: (Unix time, offset = Unix time - boot time) [s], as they came."""

    attitude: StreamSamples = field(default_factory=StreamSamples)
    position: StreamSamples = field(default_factory=StreamSamples)
    boot_clocks: list[list[tuple[float, float]]] = field(default_factory=list)
    origins: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    """Per boot, its GPS_GLOBAL_ORIGIN as last heard: latitude, longitude [deg], altitude [m]."""
    newest_boot_s: float = -math.inf
    """The newest boot time heard in the current boot."""
    system_times: int = 0
    heard_unix_s: float = math.nan
    """The drone's clock as last heard: its current boot's offset + newest_boot_s, or as it was
    before a boot whose SYSTEM_TIME has not come yet."""

    def needs_origin(self) -> bool:
        """Its current boot has said no GPS_GLOBAL_ORIGIN yet."""
        return max(0, len(self.boot_clocks) - 1) not in self.origins

    def _boot_of(self, boot_s: float) -> int:
        if not self.boot_clocks or boot_s < self.newest_boot_s - REBOOT_JUMP_US / 1e6:
            self.boot_clocks.append([])
            self.newest_boot_s = boot_s
        self.newest_boot_s = max(self.newest_boot_s, boot_s)
        if self.boot_clocks[-1]:
            self.heard_unix_s = self.boot_clocks[-1][-1][1] + self.newest_boot_s
        return len(self.boot_clocks) - 1

    def offsets_at(self, start_unix_s: float) -> list[float]:
        """Each boot's offset [s] for a plan that started at ``start_unix_s`` (the clock rule); NaN
        for a boot without SYSTEM_TIME."""
        out = []
        for clocks in self.boot_clocks:
            offset = math.nan
            for unix_s, new_offset in clocks:
                if not math.isnan(offset) and unix_s - new_offset + offset >= start_unix_s:
                    break  # (it came with the plan running on the clock then in force: in flight)
                offset = new_offset
            out.append(offset)
        return out

    def take(self, received_unix_s: float, msg) -> bool:
        """Keep msg if it is one of the flight controller's ATTITUDE, LOCAL_POSITION_NED,
        GPS_GLOBAL_ORIGIN or SYSTEM_TIME (with a Unix time); the caller has checked its system id."""
        kind = msg.get_type()
        if msg.get_srcComponent() != COMP_AUTOPILOT:
            return False
        if kind == "SYSTEM_TIME":
            if msg.time_unix_usec <= 0:
                return False
            boot = self._boot_of(msg.time_boot_ms / 1000.0)
            offset = msg.time_unix_usec / 1e6 - msg.time_boot_ms / 1000.0
            clocks = self.boot_clocks[boot]
            if not clocks or clocks[-1][1] != offset:  # (a new offset; the same again adds nothing)
                clocks.append((msg.time_unix_usec / 1e6, offset))
            self.heard_unix_s = offset + self.newest_boot_s
            self.system_times += 1
            return True
        if kind == "GPS_GLOBAL_ORIGIN":
            origin = geodetic_from_mavlink(msg.latitude, msg.longitude, msg.altitude)
            if origin is None:
                return False
            self.origins[max(0, len(self.boot_clocks) - 1)] = origin  # (no boot time in it: of the boot heard last)
            return True
        if kind == "ATTITUDE":
            stream, value = self.attitude, attitude_to_paper(msg.roll, msg.pitch, msg.yaw)
        elif kind == "LOCAL_POSITION_NED":
            stream, value = self.position, local_ned_to_paper(msg.x, msg.y, msg.z)
        else:
            return False
        stream.boot.append(self._boot_of(msg.time_boot_ms / 1000.0))
        stream.boot_s.append(msg.time_boot_ms / 1000.0)
        stream.received_unix_s.append(received_unix_s)
        stream.values.append(value)
        return True

    def copy(self) -> "DroneSamples":
        return DroneSamples(self.attitude.copy(), self.position.copy(), [list(c) for c in self.boot_clocks],
                            dict(self.origins), self.newest_boot_s, self.system_times, self.heard_unix_s)


@dataclass(frozen=True)
class Track:
    """One drone's streams on plan time, each sorted with one sample per instant."""

    attitude_t_s: np.ndarray
    euler_rad: np.ndarray
    """(A, 3) unwrapped along the track."""
    position_t_s: np.ndarray
    position_m: np.ndarray
    """(P, 3)."""
    clock: str
    """What timed its samples: "SYSTEM_TIME" or "received" (no SYSTEM_TIME in any boot)."""

    @property
    def span_s(self) -> tuple[float, float]:
        """The plan time both streams cover."""
        return max(self.attitude_t_s[0], self.position_t_s[0]), min(self.attitude_t_s[-1], self.position_t_s[-1])


def _timed(stream: StreamSamples, offsets_s: np.ndarray, start_unix_s: float) -> tuple[np.ndarray, np.ndarray]:
    offset = offsets_s[np.asarray(stream.boot, dtype=int)]
    unix = np.where(np.isnan(offset), stream.received_unix_s, offset + np.asarray(stream.boot_s))
    t, first = np.unique(unix - start_unix_s, return_index=True)
    return t, np.asarray(stream.values).reshape(-1, 3)[first]


def track(drone: DroneSamples, start_unix_s: float, name: str = "drone", home_lla=None) -> Track:
    """A drone's samples on plan time t = unix time - start_unix_s; with the swarm's home (latitude,
    longitude [deg], altitude [m]), positions from it."""
    for kind, stream in zip(STREAMS, (drone.attitude, drone.position)):
        if not stream.values:
            raise TrackError(f"no {kind} from {name}")
    offsets = np.asarray(drone.offsets_at(start_unix_s), dtype=float)
    t_att, eta = _timed(drone.attitude, offsets, start_unix_s)
    position = drone.position
    if home_lla is not None and drone.origins:
        moves = {boot: np.asarray(origin_offset_e_m(home_lla, lla)) for boot, lla in drone.origins.items()}
        position = StreamSamples(position.boot_s, position.received_unix_s, position.boot,
                                 [v + moves[b] if b in moves else v for b, v in zip(position.boot, position.values)])
    t_pos, pos = _timed(position, offsets, start_unix_s)
    return Track(t_att, np.unwrap(eta, axis=0), t_pos, pos,
                 "SYSTEM_TIME" if not np.isnan(offsets).all() else "received")


def common_span_s(tracks: list[Track]) -> tuple[float, float]:
    """The plan time every track covers (empty if the first exceeds the second)."""
    spans = [tr.span_s for tr in tracks]
    return max(lo for lo, _ in spans), min(hi for _, hi in spans)


def on_grid(tracks: list[Track], t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position (T, N, 3) [m], Euler angles (T, N, 3) [rad] wrapped to (-pi, pi]) at plan times t_s,
    each stream interpolated linearly on its own stamps (held at its ends)."""
    position_m = np.empty((t_s.size, len(tracks), 3))
    euler_rad = np.empty((t_s.size, len(tracks), 3))
    for i, tr in enumerate(tracks):
        for c in range(3):
            position_m[:, i, c] = np.interp(t_s, tr.position_t_s, tr.position_m[:, c])
            euler_rad[:, i, c] = wrap_angle(np.interp(t_s, tr.attitude_t_s, tr.euler_rad[:, c]))
    return position_m, euler_rad


class LiveTracks:
    """Samples fed as messages arrive (one thread), read as consistent snapshots (any thread)."""

    def __init__(self, sysids, home_lla=None) -> None:
        self._lock = threading.Lock()
        self._drones = {s: DroneSamples() for s in sysids}
        self.home_lla = home_lla
        """The swarm's home (latitude, longitude [deg], altitude [m]), or None: positions as sent."""

    def take(self, sysid: int, received_unix_s: float, msg) -> bool:
        with self._lock:
            return self._drones[sysid].take(received_unix_s, msg)

    def heard_unix_s(self, sysid: int) -> float:
        """The drone's clock as last heard (Unix time; NaN before its first SYSTEM_TIME)."""
        with self._lock:
            return self._drones[sysid].heard_unix_s

    def snapshot(self) -> dict[int, DroneSamples]:
        with self._lock:
            return {s: d.copy() for s, d in self._drones.items()}

    def tracks(self, start_unix_s: float) -> dict[int, Track]:
        return {s: track(d, start_unix_s, f"vehicle {s}", self.home_lla) for s, d in sorted(self.snapshot().items())}

    def needing_origin(self) -> list[int]:
        """The vehicles whose current boot has said no GPS_GLOBAL_ORIGIN yet."""
        with self._lock:
            return [s for s, d in self._drones.items() if d.needs_origin()]
