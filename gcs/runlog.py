"""A whole-stack run's MAVLink log (pymavlink's .tlog) as telemetry in the paper's frame and plan time.

A .tlog is a sequence of records: an 8-byte big-endian Unix time in microseconds (when the ground
station received the frame), then one MAVLink frame. Garbage and truncated frames are skipped and
counted: after a record that does not check (length, CRC, message id), the reader looks for the next
place where a timestamp is followed by a frame that does.

Each drone (system id i, flight controller component 1) reports ATTITUDE (FRD in NED) and
LOCAL_POSITION_NED stamped with its boot time, not necessarily on the same instants. A sample's Unix
time is its boot time plus the drone's clock offset from SYSTEM_TIME (time_unix - time_boot): the
latest one received before the sample, or the first one for samples before it (the boot clock does
not jump). A drone that never sent SYSTEM_TIME is timed by the tlog's receive times. Both streams are
then interpolated onto one uniform grid in plan time t = unix time - the plan's start time.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from triswarm.protocol.mavlink import COMP_AUTOPILOT, attitude_to_paper, local_ned_to_paper, mavlink
from triswarm.protocol.metrics import wrap_angle

TLOG_TIMESTAMP = struct.Struct(">Q")
_FRAME_START = re.compile(b"[\xfd\xfe]")  # MAVLink 2 and MAVLink 1 start bytes


class RunLogError(ValueError):
    """A log that cannot give every drone's telemetry, with the reason in one sentence."""


@dataclass
class TlogStats:
    frames: int = 0
    """Records read."""
    skipped_bytes: int = 0
    """Bytes that were not part of a record that checks (garbage, truncated or corrupt frames)."""
    skipped_runs: int = 0
    """Separate stretches of skipped bytes."""


def read_tlog(data: bytes, stats: TlogStats) -> Iterator[tuple[float, object]]:
    """(receive time [Unix s], message) for every record that checks, in file order."""
    mav = mavlink.MAVLink(None)
    pos, lost_at = 0, None
    while pos + TLOG_TIMESTAMP.size < len(data):
        msg, frame_len = _frame_at(mav, data, pos + TLOG_TIMESTAMP.size)
        if msg is None:
            if lost_at is None:
                lost_at = pos
                stats.skipped_runs += 1
            found = _FRAME_START.search(data, pos + TLOG_TIMESTAMP.size + 1)
            pos = len(data) if found is None else found.start() - TLOG_TIMESTAMP.size
            continue
        if lost_at is not None:
            stats.skipped_bytes += pos - lost_at
            lost_at = None
        stats.frames += 1
        yield TLOG_TIMESTAMP.unpack_from(data, pos)[0] / 1e6, msg
        pos += TLOG_TIMESTAMP.size + frame_len
    if lost_at is None and pos < len(data):
        lost_at = pos
        stats.skipped_runs += 1
    if lost_at is not None:
        stats.skipped_bytes += len(data) - lost_at


def _frame_at(mav, data: bytes, at: int) -> tuple[object | None, int]:
    """The message whose frame starts at data[at] and its frame length, or (None, 0)."""
    if at + 3 > len(data):
        return None, 0
    magic, payload_len, flags = data[at], data[at + 1], data[at + 2]
    if magic == mavlink.PROTOCOL_MARKER_V2:
        if flags & ~mavlink.MAVLINK_IFLAG_SIGNED:
            return None, 0
        signed = flags & mavlink.MAVLINK_IFLAG_SIGNED
        frame_len = mavlink.HEADER_LEN_V2 + payload_len + 2 + (mavlink.MAVLINK_SIGNATURE_BLOCK_LEN if signed else 0)
    elif magic == mavlink.PROTOCOL_MARKER_V1:
        frame_len = mavlink.HEADER_LEN_V1 + payload_len + 2
    else:
        return None, 0
    if at + frame_len > len(data):
        return None, 0
    try:
        msg = mav.decode(bytearray(data[at:at + frame_len]))
    except mavlink.MAVError:
        return None, 0
    if isinstance(msg, mavlink.MAVLink_unknown):  # no CRC to check it by
        return None, 0
    return msg, frame_len


@dataclass
class _Stream:
    """One drone's samples of one message: boot time, receive time, clock offset then (or NaN), value."""

    boot_s: list[float] = field(default_factory=list)
    received_unix_s: list[float] = field(default_factory=list)
    offset_s: list[float] = field(default_factory=list)
    values: list[np.ndarray] = field(default_factory=list)

    def add(self, boot_ms: int, received_unix_s: float, offset_s: float, value: np.ndarray) -> None:
        self.boot_s.append(boot_ms / 1000.0)
        self.received_unix_s.append(received_unix_s)
        self.offset_s.append(offset_s)
        self.values.append(value)

    def timed(self, first_offset_s: float, start_unix_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(plan times, values), sorted, one sample per instant."""
        offset = np.asarray(self.offset_s)
        offset = np.where(np.isnan(offset), first_offset_s, offset)
        unix = np.where(np.isnan(offset), self.received_unix_s, offset + np.asarray(self.boot_s))
        t, first = np.unique(unix - start_unix_s, return_index=True)
        return t, np.asarray(self.values)[first]


@dataclass(frozen=True)
class DroneLog:
    attitude_samples: int
    position_samples: int
    largest_gap_s: float
    """Longest time without a new sample of either stream, within the grid's span."""
    clock: str
    """What timed its samples: "SYSTEM_TIME" or "tlog" (receive times)."""


@dataclass(frozen=True)
class RunLog:
    t_s: np.ndarray
    """(T,) uniform plan-time grid [s]."""
    position_m: np.ndarray
    """(T, N, 3) paper earth frame (x north, y west, z up), local origin."""
    euler_rad: np.ndarray
    """(T, N, 3) paper ZYX Euler angles (roll, pitch, yaw), wrapped to (-pi, pi]."""
    drones: list[DroneLog]
    tlog: TlogStats


def read_run_log(path: Path, n_drones: int, start_unix_s: float, rate_hz: float = 50.0) -> RunLog:
    """Drones 1..n_drones from a .tlog on a common grid at rate_hz, from plan time 0 (or the first
    instant every drone's streams cover) to the last instant they all cover."""
    stats = TlogStats()
    attitude = [_Stream() for _ in range(n_drones)]
    position = [_Stream() for _ in range(n_drones)]
    offsets: list[list[float]] = [[] for _ in range(n_drones)]
    for received_unix_s, msg in read_tlog(Path(path).read_bytes(), stats):
        drone = msg.get_srcSystem() - 1
        if msg.get_srcComponent() != COMP_AUTOPILOT or not 0 <= drone < n_drones:
            continue
        kind = msg.get_type()
        offset_s = offsets[drone][-1] if offsets[drone] else math.nan
        if kind == "SYSTEM_TIME" and msg.time_unix_usec > 0:
            offsets[drone].append(msg.time_unix_usec / 1e6 - msg.time_boot_ms / 1000.0)
        elif kind == "ATTITUDE":
            attitude[drone].add(msg.time_boot_ms, received_unix_s, offset_s, attitude_to_paper(msg.roll, msg.pitch, msg.yaw))
        elif kind == "LOCAL_POSITION_NED":
            position[drone].add(msg.time_boot_ms, received_unix_s, offset_s, local_ned_to_paper(msg.x, msg.y, msg.z))

    timed = []
    for i in range(n_drones):
        for name, stream in (("ATTITUDE", attitude[i]), ("LOCAL_POSITION_NED", position[i])):
            if not stream.values:
                raise RunLogError(f"{path}: no {name} from drone {i + 1} (system {i + 1}, component {COMP_AUTOPILOT})")
        first_offset_s = offsets[i][0] if offsets[i] else math.nan
        timed.append((attitude[i].timed(first_offset_s, start_unix_s), position[i].timed(first_offset_s, start_unix_s)))

    t_from = max(0.0, *(t[0] for pair in timed for t, _ in pair))
    t_to = min(t[-1] for pair in timed for t, _ in pair)
    t_s = np.arange(math.ceil(t_from * rate_hz - 1e-9), math.floor(t_to * rate_hz + 1e-9) + 1) / rate_hz
    if t_s.size < 2:
        raise RunLogError(f"{path}: the drones' telemetry has no common span of plan time after the start")
    position_m = np.empty((t_s.size, n_drones, 3))
    euler_rad = np.empty((t_s.size, n_drones, 3))
    drones = []
    for i, ((t_att, eta), (t_pos, pos)) in enumerate(timed):
        eta = np.unwrap(eta, axis=0)
        for c in range(3):
            position_m[:, i, c] = np.interp(t_s, t_pos, pos[:, c])
            euler_rad[:, i, c] = wrap_angle(np.interp(t_s, t_att, eta[:, c]))
        gap_s = max(float(np.diff(np.clip(t, t_s[0], t_s[-1]), prepend=t_s[0], append=t_s[-1]).max())
                    for t in (t_att, t_pos))
        drones.append(DroneLog(t_att.size, t_pos.size, gap_s, "SYSTEM_TIME" if offsets[i] else "tlog"))
    return RunLog(t_s, position_m, euler_rad, drones, stats)
