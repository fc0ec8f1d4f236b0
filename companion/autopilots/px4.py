"""PX4 over its Zenoh bridge (``px4_link``): offboard mode with direct actuator setpoints, the way PX4
(since v1.14, which removed SET_ACTUATOR_CONTROL_TARGET) gives an onboard computer its motors and
servos. Its airframe (``deploy/px4/``) routes actuator_motors 1-3 and actuator_servos 1-3 to the
rotors and tilt servos; in offboard mode with direct_actuator PX4's control allocation is bypassed
and the companion's commands are the outputs.

- The companion's mode is OFFBOARD (PX4's MAVLink custom mode: main mode 6), entered with
  DO_SET_MODE once the offboard signal flows (the link streams it first).
- Idle on the ground the companion commands nothing: outside offboard PX4 ignores direct actuator
  setpoints, and its own controllers hold the motors.
- PX4 takes the vehicle back in any other mode, failsafes included (offboard lost: its
  COM_OBL_RC_ACT), which the companion's commands do not win back.
- Positions are from EKF2's origin (where the vehicle first had a GPS fix), moved by the distance
  from the swarm's home to it (``Autopilot.offset_from``).
- The actuator scaling is the plan's airframe's (the bridge carries no parameters): actuator_motors
  is the rotor speed over the top speed, actuator_servos the tilt over the servo limit, as the
  airframe's outputs map them.

Over MAVLink PX4 is recognised and refused with the reason: it has no output path there.
"""

from __future__ import annotations

from triswarm.protocol import px4_msgs as px4
from triswarm.protocol.frames import geodetic_from_mavlink
from triswarm.protocol.mavlink import mavlink

from .base import Autopilot, AutopilotError, FcRequests, Say


class Px4(Autopilot):
    name = "px4"
    COMMANDS_WHILE_IDLE = False

    def __init__(self, home: tuple[float, float, float] | None = None) -> None:
        super().__init__()
        self.home = home
        self.origin: tuple[float, float, float] | None = None
        """EKF2's origin (where it had its first GPS fix): latitude, longitude [deg], altitude [m]."""

    @classmethod
    def matches(cls, autopilot: int, vehicle_type: int) -> bool:
        return autopilot == mavlink.MAV_AUTOPILOT_PX4

    async def prepare(self, fc: FcRequests, say: Say) -> None:
        from ..px4_link import SCHEME, Px4ZenohLink  # (the link's module reaches this registry through the options)

        if not isinstance(getattr(fc, "link", None), Px4ZenohLink):
            raise AutopilotError("the flight controller is PX4, which takes direct actuator commands only over its "
                                 f"uORB bridge (offboard direct_actuator), not over MAVLink: give --fc "
                                 f"{SCHEME}://ROUTER_HOST:PORT/NAMESPACE (its Zenoh bridge)")

    async def detect_simulator(self, fc: FcRequests) -> None:
        """A simulator if its link says so (``sitl up`` gives the links of its PX4s so); not in
        lockstep with the companion (its clock is its simulator's, which paces itself)."""
        self.simulator = bool(getattr(getattr(fc, "link", None), "simulator", False))

    async def ready(self, fc: FcRequests, say: Say) -> None:
        """EKF2's origin, once its position is global, and the distance from the swarm's home to it
        (PX4 sets the origin where each vehicle first had a fix: every drone's own)."""
        await fc.wait("its EKF origin (vehicle_local_position with a global reference)",
                      lambda: self.origin is not None, None, say)
        self.offset_from(self.home, self.origin, say)

    def take(self, msg) -> None:
        if msg.get_type() == "GPS_GLOBAL_ORIGIN":
            self.origin = geodetic_from_mavlink(msg.latitude, msg.longitude, msg.altitude) or self.origin

    def streams(self, rate_hz: float) -> list[tuple[int, float]]:
        return []  # (the bridge publishes at PX4's own rates: vehicle_odometry at its estimator's)

    def accelerometer_streams(self, rate_hz: float) -> list[tuple[int, float]]:
        return []  # (the bridge publishes no IMU topic: the observer runs without the accelerometer)

    @property
    def control_mode(self) -> int:
        return px4.custom_mode(px4.NAV_STATE_OFFBOARD)

    def mode_name(self, mode: int) -> str:
        return px4.mode_name(mode)

    def take_control(self) -> tuple[int, tuple[float, ...]]:
        return mavlink.MAV_CMD_DO_SET_MODE, (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
                                             float(px4.OFFBOARD_MAIN_MODE), 0.0)

    def released(self, mode: int, critical: bool) -> str | None:
        return None if mode == self.control_mode else f"the flight controller is in {self.mode_name(mode)}"
