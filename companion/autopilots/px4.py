"""PX4 over MAVLink: recognised, not flown. PX4 removed SET_ACTUATOR_CONTROL_TARGET in v1.14; it
gives an onboard computer its motors and servos only through offboard mode with direct actuator
setpoints over its uORB bridge (uXRCE-DDS, or Zenoh on builds that have it), which the companion
does not speak yet. (triswarm's simulated flight controllers streaming as PX4 does,
``sitl up --fc-profile px4``, say they are generic autopilots: ``triswarm.py`` flies them.)"""

from __future__ import annotations

from triswarm.protocol.mavlink import mavlink

from .base import Autopilot, AutopilotError, FcRequests, Say


class Px4(Autopilot):
    name = "px4"

    @classmethod
    def matches(cls, autopilot: int, vehicle_type: int) -> bool:
        return autopilot == mavlink.MAV_AUTOPILOT_PX4

    async def prepare(self, fc: FcRequests, say: Say) -> None:
        raise AutopilotError("the flight controller is PX4, which takes direct actuator commands only over its "
                             "uORB bridge (offboard direct_actuator), not over MAVLink: not supported yet")

    @property
    def control_mode(self) -> int:
        return 0

    def mode_name(self, mode: int) -> str:
        return f"mode {mode}"
