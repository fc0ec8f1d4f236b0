"""What the ground station and the companion both know of the autopilots a swarm flies: which the
HEARTBEAT's autopilot field names, their mode numbers, and how each is asked to take off.
No I/O: commands as (MAV_CMD, params) for whoever sends them."""

from __future__ import annotations

import math

from .mavlink import mavlink

ARDUCOPTER_GUIDED, ARDUCOPTER_LAND, ARDUCOPTER_BRAKE = 4, 9, 17
"""ArduCopter's custom modes (ArduCopter/mode.h)."""
DEFAULT_TAKEOFF_HEIGHT_M = 2.5
"""A takeoff's height above home when none is given (triswarm's simulated TKO_ALT_M's default)."""


COMPANION_MODES = {0: "idle", 1: "scheduled", 2: "flying", 3: "holding", 4: "fc lost", 5: "landing"}
"""The companion's HEARTBEAT custom_mode: its flight's phase (``companion.flight.Phase``), by name."""


def is_ardupilot(autopilot: int) -> bool:
    return autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA


def flies_itself(autopilot: int) -> bool:
    """Whether a flight controller's own controllers take the tri-rotor off and land it. PX4's do
    not with the shipped airframe (deploy/px4/: its multicopter controllers are not tuned for
    tilting rotors): there the companion's entry takes off from the ground, and the companion
    lands it (MAV_CMD_NAV_LAND to the companion)."""
    return autopilot != mavlink.MAV_AUTOPILOT_PX4


def launch_mode_command(autopilot: int) -> tuple[int, tuple[float, ...]] | None:
    """The mode a flight controller takes off in, set before it arms (None: it has none to set).
    ArduCopter takes off in GUIDED, which it enters only once it has a position estimate."""
    if is_ardupilot(autopilot):
        return mavlink.MAV_CMD_DO_SET_MODE, (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(ARDUCOPTER_GUIDED))
    return None


def takeoff_commands(autopilot: int, height_m: float | None = None) -> list[tuple[int, tuple[float, ...]]]:
    """The commands that make a flight controller (its HEARTBEAT's autopilot field) take off by itself
    and hover ``height_m`` above home (None: its own default). ArduCopter takes off in GUIDED, to a
    height above home (param7); triswarm's simulated flight controllers take param7 as an altitude
    above mean sea level, and NaN as their TKO_ALT_M."""
    nan = math.nan
    mode = launch_mode_command(autopilot)
    if is_ardupilot(autopilot):
        height = DEFAULT_TAKEOFF_HEIGHT_M if height_m is None else height_m
        return [mode, (mavlink.MAV_CMD_NAV_TAKEOFF, (0.0, 0.0, 0.0, nan, nan, nan, float(height)))]
    return [(mavlink.MAV_CMD_NAV_TAKEOFF, (0.0, 0.0, 0.0, nan, nan, nan, nan))]
