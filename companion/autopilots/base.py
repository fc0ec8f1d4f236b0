"""What the companion needs of a kind of flight controller, beyond the MAVLink every one speaks.

The flight-controller face (``flight_controller.FlightController``) reads the link, turns telemetry
into samples, keeps the clock and sends requests; at set-up, once the flight controller's HEARTBEAT
has said what it is (``registry``), it asks its ``Autopilot``:

- the actuator scaling: what a control of 1 means (top rotor speed, servo limit);
- whether it is a simulator, and one in lockstep (then its clock is no wall clock to hold against);
- any set-up of its own, before the streams and once they flow (ArduPilot: its script's mode, the
  EKF origin);
- which streams to ask for, at which intervals;
- the output path: what carries the rotor speeds and tilts (``actuators.py``);
- its modes: the one that hands control to the companion, how to enter it, their names, and when
  the flight controller has taken the vehicle back (a failsafe it can be won back from is not);
- the launch: whether the flight controller must take the vehicle off itself before it hands it
  over (ArduCopter believes a vehicle it did not take off is on the ground, and disarms it);
- the position frame: what to add to its local positions to have the swarm's frame.

An ``Autopilot`` keeps no link: it acts through the face's narrow interface (``FcRequests``).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import ClassVar, Protocol

from triswarm.protocol.frames import origin_offset_e_m
from triswarm.protocol.mavlink import mavlink

from ..actuators import ActuatorControlTarget
from ..errors import CompanionError

Say = Callable[[str], None]


class AutopilotError(CompanionError):
    """The flight controller cannot be flown as it is (its script missing, an output path it has
    not): one sentence for the operator."""


class FcRequests(Protocol):
    """What an ``Autopilot`` may ask of the face during set-up."""

    sysid: int

    async def param(self, name: str) -> float: ...  # TimeoutError: no answer

    async def command(self, command: int, *params: float) -> int: ...  # the MAV_RESULT

    def send(self, msg) -> None: ...

    async def wait(self, what: str, done: Callable[[], bool], poke: Callable[[], None] | None, say: Say | None) -> None: ...


class Autopilot(ABC):
    """One kind of flight controller, as the companion flies it."""

    name: ClassVar[str]
    SCALING_PARAMS: ClassVar[tuple[str, str] | None] = None
    """The flight controller's parameters that give the top rotor speed [RPM] and the servo limit [deg]."""
    COMMANDS_WHILE_IDLE: ClassVar[bool] = True
    """Armed on the ground in ``control_mode`` with no plan flying, the companion idles the rotors
    (triswarm's flight controllers fail safe without commands); False: it commands nothing there."""

    def __init__(self) -> None:
        self.simulator = False
        """A simulator, whose clock is its host's: no wall-clock checks against it."""
        self.lockstep = False
        """A simulator in lockstep: it steps when the companion has answered its newest state."""
        self.position_offset_e_m = (0.0, 0.0, 0.0)
        """Added to the flight controller's local positions to have the swarm's frame [m, paper earth frame]."""

    @classmethod
    @abstractmethod
    def matches(cls, autopilot: int, vehicle_type: int) -> bool:
        """Whether a HEARTBEAT's autopilot and type fields say this kind."""

    # -- set-up ------------------------------------------------------------------------------------

    async def scaling(self, fc: FcRequests, fallback: tuple[float, float], say: Say) -> tuple[float, float]:
        """(top rotor speed [RPM], servo limit [deg]): the flight controller's SCALING_PARAMS, else
        ``fallback`` (the plan's airframe), said."""
        if self.SCALING_PARAMS is not None:
            try:
                values = (await fc.param(self.SCALING_PARAMS[0]), await fc.param(self.SCALING_PARAMS[1]))
                if all(math.isfinite(v) and v > 0 for v in values):
                    return values
            except TimeoutError:
                pass
        say(f"the flight controller has no {' / '.join(self.SCALING_PARAMS or ('actuator scaling',))}: actuator "
            f"commands scaled to the plan's airframe ({fallback[0]:g} RPM, {fallback[1]:g} deg)")
        return fallback

    async def detect_simulator(self, fc: FcRequests) -> None:
        """Set ``simulator`` and ``lockstep`` (neither, unless the kind knows how to tell)."""

    async def prepare(self, fc: FcRequests, say: Say) -> None:
        """Set-up of the kind's own, after the scaling and before the streams (AutopilotError: it
        cannot be flown)."""

    async def ready(self, fc: FcRequests, say: Say) -> None:
        """Set-up of the kind's own once its telemetry flows (AutopilotError: it cannot be flown)."""

    def offset_from(self, home: tuple[float, float, float] | None, origin: tuple[float, float, float], say: Say) -> None:
        """``position_offset_e_m`` for a flight controller whose local positions are from ``origin``
        (its EKF origin: latitude, longitude [deg], altitude [m]): the distance from the swarm's
        ``home`` to it, said when it is more than a centimetre."""
        if home is None:
            say("no swarm home (--home): positions are the flight controller's, from its own EKF origin")
            return
        self.position_offset_e_m = origin_offset_e_m(home, origin)
        north, west, up = self.position_offset_e_m
        if max(map(abs, self.position_offset_e_m)) > 0.01:
            say(f"its EKF origin is {abs(north):.2f} m {'north' if north >= 0 else 'south'}, {abs(west):.2f} m "
                f"{'west' if west >= 0 else 'east'} and {abs(up):.2f} m {'above' if up >= 0 else 'below'} the swarm's "
                "home: positions are moved by that")

    def streams(self, rate_hz: float) -> list[tuple[int, float]]:
        """(message id, interval [us]; -1: off) to ask for: the attitude and position at the control
        rate, the clock, the landed state; the alternatives off."""
        interval = 1e6 / rate_hz
        return [(mavlink.MAVLINK_MSG_ID_ATTITUDE, interval), (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, interval),
                (mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, -1), (mavlink.MAVLINK_MSG_ID_ODOMETRY, -1),
                (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, 1e6), (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2e5)]

    def accelerometer_streams(self, rate_hz: float) -> list[tuple[int, float]]:
        """What to ask for besides when the plan's controllers take the accelerometer: HIGHRES_IMU at
        the control rate (74 bytes a frame: on a slow serial line it is asked only when used)."""
        return [(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 1e6 / rate_hz)]

    def output(self, codec, sysid: int, max_rotor_speed_rad_s: float, servo_limit_rad: float) -> ActuatorControlTarget:
        """The output path: SET_ACTUATOR_CONTROL_TARGET, unless the kind has another."""
        return ActuatorControlTarget(codec, sysid, max_rotor_speed_rad_s, servo_limit_rad)

    # -- modes -------------------------------------------------------------------------------------

    @property
    @abstractmethod
    def control_mode(self) -> int:
        """The HEARTBEAT custom mode in which the companion flies the vehicle."""

    @abstractmethod
    def mode_name(self, mode: int) -> str:
        """A custom mode's name, for the operator."""

    def take_control(self) -> tuple[int, tuple[float, ...]]:
        """The command (and its parameters) that puts the flight controller in ``control_mode``."""
        return mavlink.MAV_CMD_DO_SET_MODE, (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(self.control_mode))

    async def launch(self, fc, height_m: float, say: Say) -> None:
        """Off the ground before the companion takes control, by the flight controller's own
        controllers, to ``height_m`` above where it rests (RuntimeError: it would not); by default
        nothing: the companion's entry takes off."""

    def released(self, mode: int, critical: bool) -> str | None:
        """Why the flight controller has taken the vehicle back (in flight, armed), or None: in
        ``control_mode``, or in a failsafe the companion's commands win back (its heartbeat's
        MAV_STATE_CRITICAL)."""
        if mode == self.control_mode or critical:
            return None
        return f"the flight controller is in {self.mode_name(mode)}"

    # -- messages ----------------------------------------------------------------------------------

    def take(self, msg) -> None:
        """A message of the flight controller the face does not read itself."""
