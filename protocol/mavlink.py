"""The MAVLink conventions shared by the SITL flight controllers and the companions.

The dialect is chosen here, once: everything in triswarm that speaks MAVLink imports ``mavlink``
from this module, never through pymavlink's environment variables. It is triswarm's dialect
(``protocol/dialect/triswarm.xml``: common.xml plus the plan and leader commands), generated with
pymavlink's own generator; its messages are common.xml's, byte for byte.

Custom modes (HEARTBEAT.custom_mode, with MAV_MODE_FLAG_CUSTOM_MODE_ENABLED in base_mode):

    EXTERNAL = 1  rotors and servos follow SET_ACTUATOR_CONTROL_TARGET (a companion flies the drone)
    HOLD     = 2  the flight controller's own controller holds position, level
    LAND     = 3  it descends at LAND_SPEED_M_S and disarms once on the ground
    TAKEOFF  = 4  it climbs to the takeoff altitude, then HOLD

Actuator mapping of SET_ACTUATOR_CONTROL_TARGET (group_mlx 0), normalised as MAVLink asks:

    controls[0..2]  rotor i speed / MOT_MAX_RPM         in [0, 1]
    controls[3..5]  servo i angle / SERVO_LIM_DEG       in [-1, 1]
    controls[6..7]  unused (0)

Values outside those ranges are clamped and counted; a message with a non-finite value in
controls[0..5] is dropped and counted.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
from . import frames
from .dialect import load as _load_dialect

mavlink = _load_dialect()  # the dialect, chosen once

ACTUATOR_GROUP = 0
COMP_AUTOPILOT = mavlink.MAV_COMP_ID_AUTOPILOT1
COMP_ONBOARD = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER


class CustomMode(enum.IntEnum):
    EXTERNAL = 1
    HOLD = 2
    LAND = 3
    TAKEOFF = 4


def new_codec(sysid: int, compid: int) -> "mavlink.MAVLink":
    """A MAVLink 2 encoder/parser for one link: robust parsing (bad frames become BAD_DATA)."""
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.robust_parsing = True
    return mav


def reset_parser(mav: "mavlink.MAVLink") -> None:
    """Forget any partial frame (a UDP datagram carries whole frames; leftovers are garbage)."""
    mav.buf = bytearray()
    mav.buf_index = 0
    mav.expected_length = mavlink.HEADER_LEN_V1 + 2
    mav.have_prefix_error = False


@dataclass
class ActuatorDecode:
    omega_rad_s: np.ndarray | None
    alpha_rad: np.ndarray | None
    clamped: int = 0
    dropped_non_finite: bool = False


def encode_actuators(omega_rad_s, alpha_rad, max_rotor_speed_rad_s: float, servo_limit_rad: float) -> list[float]:
    """Rotor speeds [rad/s] and servo angles [rad] (3 each) to controls[8]."""
    w = np.asarray(omega_rad_s, dtype=float) / max_rotor_speed_rad_s
    a = np.asarray(alpha_rad, dtype=float) / servo_limit_rad
    return [float(x) for x in np.concatenate([np.clip(w, 0.0, 1.0), np.clip(a, -1.0, 1.0), [0.0, 0.0]])]


def decode_actuators(controls, max_rotor_speed_rad_s: float, servo_limit_rad: float) -> ActuatorDecode:
    """controls[8] to rotor speeds and servo angles; clamps and counts out-of-range values, drops
    the whole command if any of the six values is not finite."""
    c = np.asarray(list(controls)[:6], dtype=float)
    if c.shape != (6,) or not np.all(np.isfinite(c)):
        return ActuatorDecode(None, None, 0, True)
    w = np.clip(c[0:3], 0.0, 1.0)
    a = np.clip(c[3:6], -1.0, 1.0)
    clamped = int(np.count_nonzero(w != c[0:3]) + np.count_nonzero(a != c[3:6]))
    return ActuatorDecode(w * max_rotor_speed_rad_s, a * servo_limit_rad, clamped, False)


def attitude_to_paper(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """ATTITUDE (FRD in NED) to the paper's Euler angles."""
    return frames.euler_flip([roll, pitch, yaw])


def rates_to_paper(rollspeed: float, pitchspeed: float, yawspeed: float) -> np.ndarray:
    return frames.flip([rollspeed, pitchspeed, yawspeed])


def local_ned_to_paper(x: float, y: float, z: float) -> np.ndarray:
    return frames.flip([x, y, z])

