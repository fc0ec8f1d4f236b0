"""The plant's truth of a run whose flight controllers were a real firmware (``sitl up --autopilot
ardupilot --truth``): every vehicle's true position and attitude, stamped with the firmware's clock
(its boot time), read back on the same plan-time grid as the firmwares' own telemetry.

A truth sample is put on plan time with its drone's own clock, the offset its SYSTEM_TIME gave
(Unix time minus boot time): the clock the companions flew the plan on, and the one its telemetry
is timed by. So truth and telemetry are judged against the same formation at the same instants,
and what separates them is the firmware's estimation error (and the control's), not a clock.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .errors import GcsError
from .tracks import Track

COLUMNS = ("sysid", "boot_s", "x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad")


class TruthError(GcsError, ValueError):
    """A truth log that cannot be read (one sentence naming it)."""


def read_truth(path: Path, boot_offsets_s: list[float], start_unix_s: float) -> list[Track]:
    """Drones 1..len(boot_offsets_s) of a truth log as tracks on plan time (unix - start_unix_s)."""
    try:
        data = np.atleast_1d(np.genfromtxt(path, delimiter=",", names=True, dtype=float))
    except (OSError, ValueError) as exc:
        raise TruthError(f"{path}: cannot read the truth log ({exc})") from None
    if data.size == 0 or data.dtype.names is None or tuple(data.dtype.names) != COLUMNS:
        raise TruthError(f"{path}: not a truth log (columns {', '.join(COLUMNS)})")
    tracks = []
    for i, offset in enumerate(boot_offsets_s):
        rows = data[data["sysid"] == i + 1]
        if rows.size < 2:
            raise TruthError(f"{path}: no truth of drone {i + 1}")
        if math.isnan(offset):
            raise TruthError(f"drone {i + 1} sent no SYSTEM_TIME: its truth cannot be put on its clock")
        t = offset + rows["boot_s"] - start_unix_s
        pos = np.stack([rows["x_m"], rows["y_m"], rows["z_m"]], axis=1)
        eta = np.unwrap(np.stack([rows["roll_rad"], rows["pitch_rad"], rows["yaw_rad"]], axis=1), axis=0)
        tracks.append(Track(t, eta, t, pos, "SYSTEM_TIME"))
    return tracks
