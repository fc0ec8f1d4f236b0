"""triswarm's own simulated flight controllers (`triswarm sitl up`): the custom mode EXTERNAL, the
actuator scaling in MOT_MAX_RPM and SERVO_LIM_DEG, a simulator that says whether it runs in lockstep
(SIM_LOCKSTEP), and a failsafe hold (MAV_STATE_CRITICAL) that the companion's commands win back.
Whatever streams as it does (``sitl up --fc-profile``) is flown the same."""

from __future__ import annotations

from triswarm.protocol.mavlink import CustomMode, mavlink, mode_name

from .base import Autopilot, FcRequests


class TriswarmSitl(Autopilot):
    name = "triswarm"
    SCALING_PARAMS = ("MOT_MAX_RPM", "SERVO_LIM_DEG")

    @classmethod
    def matches(cls, autopilot: int, vehicle_type: int) -> bool:
        return autopilot == mavlink.MAV_AUTOPILOT_GENERIC

    async def detect_simulator(self, fc: FcRequests) -> None:
        try:
            self.lockstep = await fc.param("SIM_LOCKSTEP") == 1.0
            self.simulator = True
        except TimeoutError:  # a generic autopilot, not triswarm's simulator
            self.simulator = self.lockstep = False

    @property
    def control_mode(self) -> int:
        return CustomMode.EXTERNAL

    def mode_name(self, mode: int) -> str:
        return mode_name(mode)
