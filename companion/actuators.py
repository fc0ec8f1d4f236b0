"""How a companion's commands reach the rotors and servos: the actuator-output seam.

The control loop hands an output rotor speeds [rad/s] and servo angles [rad] (three each) and the
flight-controller time [boot us] of the telemetry they answer; the output turns them into what its flight
controller takes. Adding another way is another class with these two methods; the loop does not
change. (ArduPilot's script reads the same message; PX4's Zenoh link, ``px4_link``, turns it into
PX4's direct actuator setpoints.)
"""

from __future__ import annotations

import math

from triswarm.protocol.mavlink import encode_actuators, mavlink

NO_COMMAND = [math.nan] * 8
"""Controls of an answer that commands nothing (lockstep: the state was seen, nothing to command)."""


class ActuatorControlTarget:
    """SET_ACTUATOR_CONTROL_TARGET, group 0, in the flight controller's custom EXTERNAL mode
    (``protocol.mavlink`` states the mapping): what triswarm's SITL takes. ``time_usec`` is the
    time of the telemetry the command answers (boot time, microseconds), so a simulator in
    lockstep knows which state was answered."""

    def __init__(self, codec, target_system: int, max_rotor_speed_rad_s: float, servo_limit_rad: float) -> None:
        self.codec = codec
        self.target_system = target_system
        self.max_rotor_speed_rad_s = max_rotor_speed_rad_s
        self.servo_limit_rad = servo_limit_rad

    def command(self, boot_us: int, omega_rad_s, alpha_rad) -> bytes:
        controls = encode_actuators(omega_rad_s, alpha_rad, self.max_rotor_speed_rad_s, self.servo_limit_rad)
        return self._frame(boot_us, controls)

    def no_command(self, boot_us: int) -> bytes:
        return self._frame(boot_us, NO_COMMAND)

    def _frame(self, boot_us: int, controls: list[float]) -> bytes:
        return mavlink.MAVLink_set_actuator_control_target_message(
            boot_us & 0xFFFFFFFFFFFFFFFF, 0, self.target_system, 1, controls).pack(self.codec)
