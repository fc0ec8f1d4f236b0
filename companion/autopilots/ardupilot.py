"""ArduCopter with triswarm's script (``deploy/ardupilot/``): the companion's commands reach the
motors and tilt servos through ``triswarm.lua``, which drives the outputs only in the companion's
mode (TSW_MODE: GUIDED) and lets ArduPilot's own controllers take over otherwise. Idle on the
ground the companion commands nothing: ArduPilot's own GUIDED holds its motors there.

Set-up reads the script's parameters (TSW_MODE, TSW_FS_MODE, and the actuator scaling TSW_MAX_RPM,
TSW_SRV_DEG): without them the script is not running, and the companion says so and does not fly.
The EKF origin: ArduPilot's local positions are from its EKF origin, which it sets where it first
has a GPS fix; a swarm needs one frame, so with the swarm's home given (``--home``) the companion
sets the origin there (SET_GPS_GLOBAL_ORIGIN) while the flight controller has none, and adds the
distance between the two to every position, read once the positions flow (an EKF that initialises
after the origin was set forgets it and takes its first fix instead). Home (where RTL returns) is
left alone: each drone's own.

ArduCopter takes off by itself (GUIDED, NAV_TAKEOFF) before it hands the vehicle over: a vehicle it
has not seen take off is landed to it, and it disarms one landed with its motors at rest.

When the commands stop the script switches to TSW_FS_MODE (BRAKE) and reports TSW_STATE 2: a
failsafe that fresh commands win back within TSW_FS_LAND_S, so the flight is not over yet.
A firmware built for SITL (it has SIM_SPEEDUP) is a simulator: its clock is its physics'.
"""

from __future__ import annotations

import time

from pymavlink import mavutil

from triswarm.protocol.autopilots import ARDUCOPTER_GUIDED, takeoff_commands
from triswarm.protocol.frames import geodetic_from_mavlink
from triswarm.protocol.mavlink import mavlink

from .base import Autopilot, AutopilotError, FcRequests, Say

SCRIPT_STATE_FAILSAFE = 2
TAKEOFF_TIMEOUT_S = 30.0
"""ArduPilot's own takeoff reaches its height within this long [s, wall] or the launch failed."""
ORIGIN_ASK_S = 1.0
"""Asked for the EKF origin this long without an answer: it has none (yet)."""


class ArduCopter(Autopilot):
    name = "ardupilot"
    SCALING_PARAMS = ("TSW_MAX_RPM", "TSW_SRV_DEG")
    COMMANDS_WHILE_IDLE = False

    def __init__(self, home: tuple[float, float, float] | None = None) -> None:
        super().__init__()
        self.home = home
        self._control_mode = ARDUCOPTER_GUIDED
        self.fs_mode = 17
        self.script_state: int | None = None
        """The script's TSW_STATE (2: it switched to TSW_FS_MODE because the commands stopped); None
        before it said (it says once a second, and at once when it changes)."""
        self.origin: tuple[float, float, float] | None = None
        """The EKF origin: latitude, longitude [deg], altitude [m]."""
        self.ahrs_started = False
        """SYS_STATUS says its AHRS enabled: its EKF started (10 s ago: AP_AHRS::initialised), so an
        origin set now is kept."""

    @classmethod
    def matches(cls, autopilot: int, vehicle_type: int) -> bool:
        return autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA

    async def detect_simulator(self, fc: FcRequests) -> None:
        try:
            await fc.param("SIM_SPEEDUP")
            self.simulator = True
        except TimeoutError:
            self.simulator = False

    async def prepare(self, fc: FcRequests, say: Say) -> None:
        try:
            self._control_mode = round(await fc.param("TSW_MODE"))
            self.fs_mode = round(await fc.param("TSW_FS_MODE"))
        except TimeoutError:
            raise AutopilotError("the flight controller has no TSW_MODE parameter: triswarm.lua is not running "
                                 "(copy deploy/ardupilot/triswarm.lua to its scripts folder, set SCR_ENABLE 1, "
                                 "reboot)") from None
        await self._origin(fc, say)

    async def _origin(self, fc: FcRequests, say: Say) -> None:
        """With the swarm's home: the EKF origin set there if the flight controller has none yet, once
        its EKF has started (one that initialises afterwards forgets it; ``ready`` reads what holds)."""
        if self.home is None:
            return
        asked = time.monotonic()
        await fc.wait("its EKF origin", lambda: self.origin is not None or time.monotonic() - asked > ORIGIN_ASK_S,
                      lambda: self._ask_origin(fc), None)
        if self.origin is None:  # none yet: the swarm's home is the origin, once the EKF has started
            lat, lon, alt = self.home

            def set_origin() -> None:
                if self.ahrs_started:
                    fc.send(mavlink.MAVLink_set_gps_global_origin_message(
                        fc.sysid, round(lat * 1e7), round(lon * 1e7), round(alt * 1000), 0))
                    self._ask_origin(fc)
                else:
                    fc.send(mavlink.MAVLink_command_long_message(fc.sysid, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                                                 mavlink.MAVLINK_MSG_ID_SYS_STATUS, 0, 0, 0, 0, 0, 0))

            await fc.wait("its EKF origin (set to the swarm's home)", lambda: self.origin is not None, set_origin, say)

    async def ready(self, fc: FcRequests, say: Say) -> None:
        """The EKF origin as it holds once the position flows (EKF3 keeps it for the boot from then
        on), and the distance from the swarm's home to it."""
        self.origin = None
        await fc.wait("its EKF origin", lambda: self.origin is not None, lambda: self._ask_origin(fc), say)
        self.offset_from(self.home, self.origin, say)

    @staticmethod
    def _ask_origin(fc: FcRequests) -> None:
        fc.send(mavlink.MAVLink_command_long_message(fc.sysid, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                                     mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, 0, 0, 0, 0, 0, 0))

    def streams(self, rate_hz: float) -> list[tuple[int, float]]:
        # (ArduCopter has no ODOMETRY stream to turn off)
        interval = 1e6 / rate_hz
        return [(mavlink.MAVLINK_MSG_ID_ATTITUDE, interval), (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, interval),
                (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, 1e6), (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2e5)]

    def accelerometer_streams(self, rate_hz: float) -> list[tuple[int, float]]:
        # (ArduCopter has no HIGHRES_IMU stream. Its SCALED_IMU is the accelerometer as its INS
        # filters it (INS_ACCEL_FILTER), stamped when sent: not the instant's specific force the
        # observer relates to the input; three drones in the loop flew 0.46 m with it against 0.25
        # without. Not asked for: the observer runs without the accelerometer)
        return []

    async def launch(self, fc, height_m: float, say: Say) -> None:
        (set_mode, mode_params), (takeoff, takeoff_params) = takeoff_commands(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, height_m)
        await _accepted(fc, "GUIDED", set_mode, *mode_params)
        if not fc.armed:
            await _accepted(fc, "arming", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        z0 = fc.last_sample.position_e_m[2] if fc.last_sample is not None else 0.0
        await _accepted(fc, "takeoff", takeoff, *takeoff_params)
        say(f"taking off to {height_m:g} m (ArduPilot's GUIDED takeoff)")
        t0 = time.monotonic()

        def up() -> bool:
            s = fc.last_sample
            if time.monotonic() - t0 > TAKEOFF_TIMEOUT_S:
                raise RuntimeError(f"ArduPilot's takeoff did not reach {height_m:g} m in {TAKEOFF_TIMEOUT_S:g} s")
            return not fc.landed and s is not None and s.position_e_m[2] - z0 >= 0.9 * height_m

        await fc.wait(f"the takeoff to {height_m:g} m", up, None, say)

    @property
    def control_mode(self) -> int:
        return self._control_mode

    def mode_name(self, mode: int) -> str:
        return mavutil.mode_mapping_acm.get(mode, f"mode {mode}")

    def released(self, mode: int, critical: bool) -> str | None:
        if mode == self._control_mode or (mode == self.fs_mode and self.script_state in (None, SCRIPT_STATE_FAILSAFE)):
            return None  # (in its failsafe mode before the script said why: its next word decides)
        return f"the flight controller is in {self.mode_name(mode)}"

    def take(self, msg) -> None:
        t = msg.get_type()
        if t == "NAMED_VALUE_FLOAT" and msg.name.rstrip("\x00") == "TSW_STATE":
            self.script_state = round(msg.value)
        elif t == "SYS_STATUS":
            self.ahrs_started = bool(msg.onboard_control_sensors_enabled & mavlink.MAV_SYS_STATUS_AHRS)
        elif t == "GPS_GLOBAL_ORIGIN":
            self.origin = geodetic_from_mavlink(msg.latitude, msg.longitude, msg.altitude) or self.origin


async def _accepted(fc, what: str, command: int, *params: float) -> None:
    result = await fc.command(command, *params)
    if result != mavlink.MAV_RESULT_ACCEPTED:
        raise RuntimeError(f"the flight controller refused {what} ({result})")
