"""The flight controller's telemetry, as autopilots send it, turned into the samples a tick needs.

Autopilots do not send the state as one message. PX4 stamps ATTITUDE and LOCAL_POSITION_NED with
the publication times of two estimator topics, at different rates (attitude with every IMU
sample, position with every filter update); ArduPilot stamps each message with the time it sends
it; ODOMETRY, where it exists, carries one sample time for the whole state (docs/flight-controllers.md).
So the companion takes each stream as it comes:

- attitude (ATTITUDE, ATTITUDE_QUATERNION or ODOMETRY, each with its body rates): every new
  attitude instant is a tick, the stream the loop runs on;
- position and velocity (LOCAL_POSITION_NED or ODOMETRY): the newest one is brought to the tick's
  instant with its own velocity, p(t) = p_k + v_k (t - t_k), forwards or backwards;
- gyro rates (HIGHRES_IMU) when the attitude message carries none;
- the accelerometer's specific force (HIGHRES_IMU, SCALED_IMU), taken at a tick when it is within
  ``MAX_ACCEL_AGE_US`` of the attitude's instant (the observer relates it to the input of that
  instant).

A sample whose newest position is older than ``MAX_POSITION_AGE_US`` has no position (NaN): the
observer then runs on its model, and the companion says that the stream stopped. Messages older
than the newest of their stream (out of order) are dropped and counted; the same instant again
(a simulator offering its state again) makes no new tick. A stamp REBOOT_JUMP_US or more back, or
ahead by more than the wall clock ran (``AHEAD_US``), is held until the stream's next message
decides: running on from it, it is a new clock (a flight controller that restarted: every stream
starts again) or a jump; else it was out of place, and is dropped and counted.

Times are the flight controller's boot clock in microseconds (ms-stamped messages times 1000).
No I/O: the flight-controller face (``flight_controller.py``) feeds it parsed messages, read here into the paper's
frames (``attitude_of``, ``position_of``, ``gyro_of``, ``accel_of``).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

from triswarm.protocol.frames import attitude_from_mavlink, body_velocity_to_earth
from triswarm.protocol.mavlink import mavlink

REBOOT_JUMP_US = 1_000_000
"""A stamp this much older than the newest of its stream is a restarted flight controller."""
AHEAD_US = 100_000
"""A stamp that does not run on from its stream's newest (REBOOT_JUMP_US or more behind it, or
ahead of it by this much [us] more than the wall clock ran since) is held until the stream's next
message: taken if that one runs on from it (behind: a restarted flight controller's new clock;
ahead: a jump), dropped and counted (``<stream>_stamp_out_of_place``) if not (a hostile message, a
frame corrupted past its checksum). Taken at its word, one stamp ahead would have made the true
ones out of order until the clock caught up with it, and one behind would have restarted every
stream."""
MAX_POSITION_AGE_US = 250_000
"""A position older than this at a tick is not used: the observer runs on its model meanwhile."""
MAX_ACCEL_AGE_US = 10_000
"""A specific force further than this from a tick's attitude instant is not used at that tick."""
NAN3 = (math.nan, math.nan, math.nan)
STANDARD_GRAVITY_M_S2 = 9.80665
"""What SCALED_IMU's milli-g are thousandths of."""


def attitude_of(msg) -> tuple[tuple, tuple]:
    """ATTITUDE, ATTITUDE_QUATERNION or ODOMETRY (FRD body in NED) as the paper's Euler angles [rad]
    and body rates [rad/s]."""
    kind = msg.get_type()
    if kind == "ATTITUDE":
        eta = (msg.roll, -msg.pitch, -msg.yaw)
    elif kind == "ATTITUDE_QUATERNION":
        eta = attitude_from_mavlink((msg.q1, msg.q2, msg.q3, msg.q4))
    else:
        eta = attitude_from_mavlink(msg.q)
    return eta, (msg.rollspeed, -msg.pitchspeed, -msg.yawspeed)


def position_of(msg) -> tuple[tuple, tuple] | None:
    """LOCAL_POSITION_NED or ODOMETRY as the paper's earth-frame position [m] and velocity [m/s];
    None for an ODOMETRY in frames the companion does not fly on (not local NED, or its velocity
    neither in the body's FRD nor in local NED)."""
    position = (msg.x, -msg.y, -msg.z)
    if msg.get_type() == "LOCAL_POSITION_NED":
        return position, (msg.vx, -msg.vy, -msg.vz)
    if msg.frame_id != mavlink.MAV_FRAME_LOCAL_NED:
        return None
    if msg.child_frame_id == mavlink.MAV_FRAME_BODY_FRD:
        return position, body_velocity_to_earth(msg.q, (msg.vx, msg.vy, msg.vz))
    if msg.child_frame_id == mavlink.MAV_FRAME_LOCAL_NED:
        return position, (msg.vx, -msg.vy, -msg.vz)
    return None


def gyro_of(msg) -> tuple:
    """HIGHRES_IMU's gyro (FRD) as the paper's body rates [rad/s]."""
    return msg.xgyro, -msg.ygyro, -msg.zgyro


def accel_of(msg) -> tuple:
    """HIGHRES_IMU's [m/s^2] or SCALED_IMU's [mG] accelerometer (FRD) as the paper's body-frame
    specific force [m/s^2] (FLU)."""
    scale = 1.0 if msg.get_type() == "HIGHRES_IMU" else STANDARD_GRAVITY_M_S2 * 1e-3
    return msg.xacc * scale, -msg.yacc * scale, -msg.zacc * scale


@dataclass(slots=True)
class Sample:
    """One tick's measurements, in the paper's frames (earth: x north, y west, z up; body FLU)."""
    t_rx: float                      # Unix time the datagram arrived (kernel receive time on UDP) [s]
    boot_us: int                     # the flight controller's time of the attitude [us since its boot]
    eta_rad: tuple                   # roll, pitch, yaw
    rate_b_rad_s: tuple              # body rates p, q, r (NaN if none came)
    position_e_m: tuple              # brought to boot_us (NaN: no recent position)
    velocity_e_m_s: tuple
    position_lag_us: int             # how far the position was brought (boot_us - its stamp)
    accel_b_m_s2: tuple = NAN3       # the accelerometer's specific force, body frame (NaN if none near)

    @property
    def boot_ms(self) -> int:
        return self.boot_us // 1000

    @property
    def y(self) -> tuple:
        """The measured output y = (eta, lambda) of the observer (73)."""
        return self.eta_rad + self.position_e_m


NOTHING, NEWER, NEW_CLOCK = 0, 1, 2
"""What a stream's ``take`` did."""


def _runs_on(t0_us: int, t0_rx: float, t_us: int, t_rx: float) -> bool:
    """Whether a stamp ``t_us`` received at ``t_rx`` [s] runs no more than AHEAD_US further than the
    wall clock since the stamp ``t0_us`` received at ``t0_rx``."""
    return t_us - t0_us <= 1e6 * (t_rx - t0_rx) + AHEAD_US


class _Stream:
    __slots__ = ("t_us", "value", "count", "first_us", "t_rx", "held")

    def __init__(self) -> None:
        self.t_us = -1
        self.value = None
        self.count = 0
        self.first_us = -1
        self.t_rx = 0.0
        self.held: tuple | None = None  # (t_us, value, t_rx) of a stamp that did not run on, until the next decides

    def take(self, t_us: int, value, counters: Counter, name: str, t_rx: float) -> int:
        """Take (t_us, value) received at ``t_rx`` [s]: kept if it is the newest, dropped (and
        counted) if it is out of order, held if it does not run on (``AHEAD_US``). Returns NOTHING,
        NEWER (a newer value kept) or NEW_CLOCK (the stream started again on a new clock)."""
        result = NOTHING
        held, self.held = self.held, None
        if held is not None:
            if t_us == held[0]:  # (the same instant again: still undecided)
                self.held = held
                return NOTHING
            if t_us > held[0] and _runs_on(held[0], held[2], t_us, t_rx):
                if held[0] < self.t_us:
                    self.count, self.first_us = 0, -1
                    result = NEW_CLOCK
                else:
                    result = NEWER
                self._keep(*held)
            else:
                counters[f"{name}_stamp_out_of_place"] += 1
        if self.t_us >= 0:
            if t_us < self.t_us - REBOOT_JUMP_US or not _runs_on(self.t_us, self.t_rx, t_us, t_rx):
                self.held = (t_us, value, t_rx)
                return result
            if t_us < self.t_us:
                counters[f"{name}_out_of_order"] += 1
                return result
            if t_us == self.t_us:
                return result
        self._keep(t_us, value, t_rx)
        return result or NEWER

    def _keep(self, t_us: int, value, t_rx: float) -> None:
        self.t_us, self.value, self.t_rx = t_us, value, t_rx
        if self.first_us < 0:
            self.first_us = t_us
        self.count += 1

    def rate_hz(self) -> float:
        """Messages per second of the flight controller's clock since the first (NaN: too few)."""
        if self.count < 3 or self.t_us <= self.first_us:
            return math.nan
        return (self.count - 1) * 1e6 / (self.t_us - self.first_us)


class Assembler:
    """The newest of each stream, and a sample at each new attitude instant."""

    def __init__(self) -> None:
        self.counters: Counter[str] = Counter()
        self.attitude = _Stream()   # (eta, rates)
        self.position = _Stream()   # (p, v)
        self.gyro = _Stream()       # rates
        self.accel = _Stream()      # specific force
        self._sampled_us = -1

    def take_attitude(self, t_us: int, eta_rad: tuple, rate_b_rad_s: tuple | None, t_rx: float) -> None:
        if self.attitude.take(t_us, (eta_rad, rate_b_rad_s), self.counters, "attitude", t_rx) == NEW_CLOCK:
            self.restart()

    def take_position(self, t_us: int, position_e_m: tuple, velocity_e_m_s: tuple, t_rx: float) -> None:
        self.position.take(t_us, (position_e_m, velocity_e_m_s), self.counters, "position", t_rx)

    def take_gyro(self, t_us: int, rate_b_rad_s: tuple, t_rx: float) -> None:
        self.gyro.take(t_us, rate_b_rad_s, self.counters, "gyro", t_rx)

    def take_accel(self, t_us: int, accel_b_m_s2: tuple, t_rx: float) -> None:
        self.accel.take(t_us, accel_b_m_s2, self.counters, "accel", t_rx)

    def restart(self) -> None:
        """A restarted flight controller (its attitudes run on a new clock): the other streams
        start again too."""
        self.counters["fc_clock_restarted"] += 1
        self.position, self.gyro, self.accel = _Stream(), _Stream(), _Stream()
        self._sampled_us = -1

    def sample(self, t_rx: float) -> Sample | None:
        """A sample at the newest attitude instant, if it is new and a position has come."""
        att = self.attitude
        if att.t_us < 0 or att.t_us == self._sampled_us or self.position.t_us < 0:
            return None
        t = att.t_us
        self._sampled_us = t
        eta, rates = att.value
        if rates is None:
            rates = self.gyro.value if self.gyro.t_us >= 0 and abs(self.gyro.t_us - t) <= MAX_POSITION_AGE_US else NAN3
        accel = self.accel.value if self.accel.t_us >= 0 and abs(self.accel.t_us - t) <= MAX_ACCEL_AGE_US else NAN3
        p, v = self.position.value
        lag = t - self.position.t_us
        if abs(lag) > MAX_POSITION_AGE_US:
            self.counters["samples_without_position"] += 1
            return Sample(t_rx, t, eta, rates, NAN3, NAN3, lag, accel)
        dt = lag * 1e-6
        return Sample(t_rx, t, eta, rates, (p[0] + v[0] * dt, p[1] + v[1] * dt, p[2] + v[2] * dt), v, lag, accel)
