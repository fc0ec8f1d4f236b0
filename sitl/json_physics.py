"""triswarm's plant as the physics of ArduPilot's own firmware, over its JSON interface.

ArduPilot's SITL (``libraries/SITL/SIM_JSON.cpp``) sends its outputs to a physics backend, one UDP
packet per frame, and waits for the state that answers it: the backend's ``timestamp`` is the
firmware's clock. So the loop is lockstep by construction: the firmware's time moves only when the
plant has stepped. Here one plant flies N firmwares on one clock: every vehicle's frame k is in
before the plant steps (all vehicles at once, ``Plant.advance``) and answers each, so every
firmware's clock reads the same simulated time (and, started with one ``--start-time``, the same
Unix time: their GPS time is that plus the clock).

What a firmware sends (little-endian): ``uint16 magic 18458, uint16 frame_rate, uint32 frame_count,
uint16 pwm[16]`` (40 bytes), or with 32 channels magic 29569 and ``pwm[32]``. What it gets: one JSON
object between newlines, the truth in its frames: ``timestamp`` [s], ``imu.gyro`` (FRD body rates
[rad/s]), ``imu.accel_body`` (FRD specific force [m/s^2]), ``position`` (NED from home [m]),
``velocity`` (NED [m/s]), ``quaternion`` (FRD to NED, scalar first), and ``rc`` (a radio at rest,
throttle low). The firmware makes its own IMU, compass, barometer and GPS readings from that truth,
with its own noise, and what it streams is its EKF's estimate of it.

The outputs are the hardware of ``deploy/ardupilot/triswarm.parm``: PWM 1..3 the motors of rotors
1..3, the speed proportional to the PWM from 1000 us (stopped) to 2000 us (the airframe's top
speed); PWM 4..6 their tilt servos, the angle proportional to the PWM about 1500 us (untilted),
+-500 us the airframe's servo limit. A frame of zeros (the firmware's outputs not yet live) stops
every motor.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from .physics import SENSOR_COLUMNS

SERVO_MAGIC_16, SERVO_MAGIC_32 = 18458, 29569
_HEAD = struct.Struct("<HHI")
_PWM = {SERVO_MAGIC_16: struct.Struct("<16H"), SERVO_MAGIC_32: struct.Struct("<32H")}
PWM_CHANNELS = 16
"""Channels the plant reads (the 32-channel packet's first 16)."""


@dataclass(frozen=True)
class ServoFrame:
    frame_rate_hz: int
    frame_count: int
    pwm: tuple[int, ...]
    """The first PWM_CHANNELS outputs [us]."""


def decode_servo_packet(data: bytes) -> ServoFrame | None:
    """A firmware's output packet, or None if it is not one (wrong magic or length)."""
    if len(data) < _HEAD.size:
        return None
    magic, rate, count = _HEAD.unpack_from(data)
    pwm = _PWM.get(magic)
    if pwm is None or len(data) != _HEAD.size + pwm.size:
        return None
    return ServoFrame(rate, count, pwm.unpack_from(data, _HEAD.size)[:PWM_CHANNELS])


@dataclass(frozen=True)
class OutputMap:
    """Which outputs drive what, and how PWM maps to rotor speed and tilt (the hardware that
    ``deploy/ardupilot/triswarm.parm`` describes)."""

    motor_channels: tuple[int, int, int] = (0, 1, 2)
    tilt_channels: tuple[int, int, int] = (3, 4, 5)
    motor_pwm_us: tuple[float, float] = (1000.0, 2000.0)
    """PWM of a stopped rotor and of one at the airframe's top speed."""
    tilt_trim_us: float = 1500.0
    tilt_span_us: float = 500.0
    """PWM of an untilted rotor, and from there to the airframe's servo limit."""

    def commands(self, pwm: np.ndarray, max_omega_rad_s: np.ndarray, servo_limit_rad: np.ndarray):
        """PWM (N, channels) [us] to rotor speeds [rad/s] and tilt angles [rad], (N, 3) each, for
        airframes with these limits (N,). A motor output of 0 (not live) is a stopped rotor, a servo
        output of 0 an untilted one."""
        pwm = np.asarray(pwm, dtype=float)
        lo, hi = self.motor_pwm_us
        motor = pwm[:, list(self.motor_channels)]
        tilt = pwm[:, list(self.tilt_channels)]
        speed = np.clip((motor - lo) / (hi - lo), 0.0, 1.0)
        angle = np.where(tilt > 0, np.clip((tilt - self.tilt_trim_us) / self.tilt_span_us, -1.0, 1.0), 0.0)
        return speed * max_omega_rad_s[:, None], angle * servo_limit_rad[:, None]


RC_AT_REST = '"rc":{"rc_1":1500,"rc_2":1500,"rc_3":1000,"rc_4":1500,"rc_5":1000,"rc_6":1000,"rc_7":1000,"rc_8":1000}'
"""A radio transmitter switched on, its sticks centred and its throttle low: what the firmware's
pre-arm checks and its radio failsafe want to see (a pilot at the sticks does nothing)."""
_FLIP = np.array([1.0, -1.0, -1.0])
_QFLIP = np.array([1.0, 1.0, -1.0, -1.0])


def state_json(t_s: float, sensors_row: np.ndarray) -> bytes:
    """The answer to a frame: one vehicle's ``Plant.sensors`` row (paper frames) at time ``t_s``
    [s], in the firmware's frames, framed by newlines."""
    col = SENSOR_COLUMNS
    pos = sensors_row[col["position_m"]] * _FLIP
    vel = sensors_row[col["velocity_e_m_s"]] * _FLIP
    q = sensors_row[col["quaternion"]] * _QFLIP
    gyro = sensors_row[col["rate_b_rad_s"]] * _FLIP
    acc = sensors_row[col["specific_force_b"]] * _FLIP
    text = ('\n{"timestamp":%.6f,"imu":{"gyro":[%.9g,%.9g,%.9g],"accel_body":[%.9g,%.9g,%.9g]},'
            '"position":[%.9g,%.9g,%.9g],"velocity":[%.9g,%.9g,%.9g],"quaternion":[%.9g,%.9g,%.9g,%.9g],%s}\n'
            % (t_s, *gyro, *acc, *pos, *vel, *q, RC_AT_REST))
    return text.encode()


def frame_period_s(physics_hz: float) -> float:
    """The clock's step [s]: whole microseconds (the firmware keeps its clock in them)."""
    us = round(1e6 / physics_hz)
    if us < 1 or not math.isfinite(physics_hz):
        raise ValueError(f"physics rate must be a positive number of hertz up to 1 MHz, got {physics_hz!r}")
    return us / 1e6
