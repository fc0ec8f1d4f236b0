"""A whole-stack run's MAVLink log (pymavlink's .tlog) as telemetry in the paper's frame and plan time.

A .tlog is a sequence of records: an 8-byte big-endian Unix time in microseconds (when the ground
station received the frame), then one MAVLink frame. Garbage and truncated frames are skipped and
counted: after a record that does not check (length, CRC, message id), the reader looks for the next
place where a timestamp is followed by a frame that does.

Each drone (system id i, flight controller component 1) reports ATTITUDE (FRD in NED) and
LOCAL_POSITION_NED stamped with its boot time, not necessarily on the same instants. They are timed
as the live recorder times them (``tracks.py``: the boot clock as the companions flew it, from
the SYSTEM_TIMEs of each boot; the tlog's receive times for a drone that never sent SYSTEM_TIME)
and interpolated onto one uniform grid in plan time t = unix time - the plan's start time.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from triswarm.protocol.mavlink import COMP_AUTOPILOT, mavlink

from .errors import GcsError
from .tracks import DroneSamples, TrackError, common_span_s, on_grid, track

TLOG_TIMESTAMP = struct.Struct(">Q")
_FRAME_START = re.compile(b"[\xfd\xfe]")  # MAVLink 2 and MAVLink 1 start bytes


class RunLogError(GcsError, ValueError):
    """A log that cannot give every drone's telemetry, with the reason in one sentence."""


@dataclass
class TlogStats:
    frames: int = 0
    """Records read."""
    skipped_bytes: int = 0
    """Bytes that were not part of a record that checks (garbage, truncated or corrupt frames)."""
    skipped_runs: int = 0
    """Separate stretches of skipped bytes."""
    unknown: int = 0
    """Whole records of messages this dialect does not know (an autopilot's own), passed over."""


def read_tlog(data: bytes, stats: TlogStats) -> Iterator[tuple[float, object]]:
    """(receive time [Unix s], message) for every record that checks, in file order."""
    mav = mavlink.MAVLink(None)
    pos, lost_at = 0, None
    while pos + TLOG_TIMESTAMP.size < len(data):
        msg, frame_len = _frame_at(mav, data, pos + TLOG_TIMESTAMP.size)
        if isinstance(msg, mavlink.MAVLink_unknown):
            end = pos + TLOG_TIMESTAMP.size + frame_len
            if end == len(data) or _FRAME_START.match(data, end + TLOG_TIMESTAMP.size):
                stats.unknown += 1  # (a whole record, the next one right after it: not garbage)
                if lost_at is not None:
                    stats.skipped_bytes += pos - lost_at
                    lost_at = None
                pos = end
                continue
            msg = None  # (no CRC to check it by, and nothing after it that says it was whole)
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
    """The message whose frame starts at data[at] and its frame length, or (None, 0); a message
    the dialect does not know is a ``MAVLink_unknown``, unchecked."""
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
    return msg, frame_len


@dataclass(frozen=True)
class DroneLog:
    attitude_samples: int
    position_samples: int
    largest_gap_s: float
    """Longest time without a new sample of either stream, within the grid's span."""
    clock: str
    """What timed its samples: "SYSTEM_TIME" or "tlog" (receive times)."""
    boot_offset_s: float
    """Unix time minus boot time by its SYSTEM_TIME, as the tracks' clock rule took it (NaN: none came):
    its first boot's clock."""


@dataclass(frozen=True)
class RunLog:
    t_s: np.ndarray
    """(T,) uniform plan-time grid [s]."""
    position_m: np.ndarray
    """(T, N, 3) paper earth frame (x north, y west, z up), from the swarm's home if given, else each
    flight controller's local origin."""
    euler_rad: np.ndarray
    """(T, N, 3) paper ZYX Euler angles (roll, pitch, yaw), wrapped to (-pi, pi]."""
    drones: list[DroneLog]
    tlog: TlogStats


def read_run_log(path: Path, n_drones: int, start_unix_s: float, rate_hz: float = 50.0, home_lla=None) -> RunLog:
    """Drones 1..n_drones from a .tlog on a common grid at rate_hz, from plan time 0 (or the first
    instant every drone's streams cover) to the last instant they all cover; with the swarm's home
    (latitude, longitude [deg], altitude [m]), positions from it (``tracks.py``)."""
    stats = TlogStats()
    samples = [DroneSamples() for _ in range(n_drones)]
    for received_unix_s, msg in read_tlog(Path(path).read_bytes(), stats):
        if 1 <= msg.get_srcSystem() <= n_drones:
            samples[msg.get_srcSystem() - 1].take(received_unix_s, msg)
    tracks = []
    for i, drone in enumerate(samples):
        try:
            tracks.append(track(drone, start_unix_s, f"drone {i + 1} (system {i + 1}, component {COMP_AUTOPILOT})",
                                home_lla))
        except TrackError as exc:
            raise RunLogError(f"{path}: {exc}") from None
    t_from, t_to = common_span_s(tracks)
    t_from = max(0.0, t_from)
    t_s = np.arange(math.ceil(t_from * rate_hz - 1e-9), math.floor(t_to * rate_hz + 1e-9) + 1) / rate_hz
    if t_s.size < 2:
        raise RunLogError(f"{path}: the drones' telemetry has no common span of plan time after the start")
    position_m, euler_rad = on_grid(tracks, t_s)
    drones = []
    for tr in tracks:
        gap_s = max(float(np.diff(np.clip(t, t_s[0], t_s[-1]), prepend=t_s[0], append=t_s[-1]).max())
                    for t in (tr.attitude_t_s, tr.position_t_s))
        offsets = [o for o in samples[len(drones)].offsets_at(start_unix_s) if not math.isnan(o)]
        drones.append(DroneLog(tr.attitude_t_s.size, tr.position_t_s.size, gap_s,
                               "SYSTEM_TIME" if tr.clock == "SYSTEM_TIME" else "tlog",
                               offsets[0] if offsets else math.nan))
    return RunLog(t_s, position_m, euler_rad, drones, stats)
