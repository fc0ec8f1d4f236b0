"""What a flight controller's estimator reports, made from the plant's truth: the state of a moment
ago (the estimator's lag), plus a bias that wanders (a first-order Gauss-Markov process: a random
walk pulled back towards zero, as a GNSS receiver's error or an AHRS's heading drift is, seen through
the estimator's smoothing: a first-order lag of ``smoothing_s``), plus white noise. Named profiles for the positioning users fly with (``PROFILES``); the numbers are an
EKF's output with that positioning, per axis, 1 sigma.

Pure: arrays in, arrays out; the random numbers come from the generator it is given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from triswarm.protocol.metrics import wrap_angle


@dataclass(frozen=True)
class EstimatorProfile:
    name: str
    position_noise_m: float
    """White noise on each position axis [m]."""
    attitude_noise_rad: float
    """White noise on each Euler angle [rad]."""
    gyro_noise_rad_s: float
    """White noise on each body rate [rad/s]."""
    position_bias_m: float
    """Standard deviation of the wandering bias of each horizontal position axis [m] (the vertical's
    is ``vertical_bias_factor`` times it, and starts at zero)."""
    attitude_bias_rad: float
    """Standard deviation of the wandering bias of each Euler angle [rad]."""
    bias_time_s: float
    """How long the biases take to wander (their correlation time) [s]."""
    lag_s: float
    """How old the reported state is [s]."""
    accel_noise_m_s2: float = 0.1
    """White noise on each accelerometer axis [m/s^2] (the raw specific force an autopilot streams:
    the airframe's vibration, not the estimator's lag)."""
    accel_bias_m_s2: float = 0.05
    """Standard deviation of each accelerometer axis's bias [m/s^2], drawn once per vehicle: what
    calibration leaves."""
    vertical_bias_factor: float = 1.5
    smoothing_s: float = 1.0
    """The estimator's smoothing of the wandering (its time constant [s]): an EKF's position error
    moves smoothly, not in white steps at the control rate; 0: none."""
    summary: str = ""


PROFILES = {p.name: p for p in (
    EstimatorProfile("truth", position_noise_m=0.0, attitude_noise_rad=0.0, gyro_noise_rad_s=0.0, position_bias_m=0.0,
                     attitude_bias_rad=0.0, bias_time_s=60.0, lag_s=0.0, accel_noise_m_s2=0.0, accel_bias_m_s2=0.0,
                     summary="the plant's state, exactly"),
    EstimatorProfile("mocap", position_noise_m=0.0005, attitude_noise_rad=0.001, gyro_noise_rad_s=0.003,
                     position_bias_m=0.0005, attitude_bias_rad=0.0005, bias_time_s=30.0, lag_s=0.002,
                     summary="motion capture indoors: millimetres, a few milliseconds late"),
    EstimatorProfile("rtk", position_noise_m=0.005, attitude_noise_rad=0.002, gyro_noise_rad_s=0.005,
                     position_bias_m=0.01, attitude_bias_rad=0.002, bias_time_s=60.0, lag_s=0.004,
                     summary="RTK-fixed GNSS with an EKF: a centimetre of noise and a centimetre of wandering bias"),
    EstimatorProfile("gps", position_noise_m=0.01, attitude_noise_rad=0.003, gyro_noise_rad_s=0.005,
                     position_bias_m=0.5, attitude_bias_rad=0.005, bias_time_s=60.0, lag_s=0.01,
                     summary="plain GNSS (no corrections) with an EKF: half a metre of wandering bias"),
)}
"""The named estimator profiles (``triswarm sim --estimator NAME``)."""


def profile(name: str) -> EstimatorProfile:
    """The profile called ``name`` (ValueError: none is)."""
    try:
        return PROFILES[name]
    except KeyError:
        raise ValueError(f"no estimator profile {name!r}: one of {', '.join(PROFILES)}") from None


class Estimator:
    """The estimates of N vehicles, reported at any instants (``report``), in order."""

    def __init__(self, prof: EstimatorProfile, n: int, rng: np.random.Generator) -> None:
        self.profile, self.n, self.rng = prof, n, rng
        self._past: list[tuple[float, np.ndarray, np.ndarray, np.ndarray | None]] = []
        self._t_s: float | None = None
        # the biases start in their steady distribution, but the height's at zero: an estimator's
        # height is referenced to where it starts (its barometer, its origin's altitude), and
        # wanders from there
        self._pos_sigma = prof.position_bias_m * np.array([1.0, 1.0, prof.vertical_bias_factor])
        self._att_sigma = np.full(3, prof.attitude_bias_rad)
        self._pos_raw = rng.standard_normal((n, 3)) * self._pos_sigma
        self._pos_raw[:, 2] = 0.0
        self._att_raw = rng.standard_normal((n, 3)) * self._att_sigma
        self.position_bias_m = self._pos_raw.copy()
        self.attitude_bias_rad = self._att_raw.copy()
        self.accel_bias_m_s2 = rng.standard_normal((n, 3)) * prof.accel_bias_m_s2

    def accelerometer(self, specific_force_b: np.ndarray) -> np.ndarray:
        """What the accelerometers read (N, 3) [m/s^2, body frame] when they feel ``specific_force_b``:
        the raw sensor, not lagged, with its bias and noise."""
        return specific_force_b + self.accel_bias_m_s2 + self.profile.accel_noise_m_s2 * self.rng.standard_normal((self.n, 3))

    def report(self, t_s: float, y: np.ndarray, rates_b: np.ndarray, velocity: np.ndarray | None = None):
        """From the truth at time t_s [s] (y: (N, 6) Euler angles [rad] and position [m]; body rates
        (N, 3) [rad/s]; optionally a velocity (N, 3), lagged alone): what the estimator reports then,
        (y, rates, velocity or None): the truth ``lag_s`` earlier with its biases and noise."""
        if self._t_s is not None and t_s > self._t_s:
            self._wander(t_s - self._t_s)
        self._t_s = t_s
        self._past.append((t_s, np.array(y, dtype=float), np.array(rates_b, dtype=float),
                           None if velocity is None else np.array(velocity, dtype=float)))
        then = t_s - self.profile.lag_s
        while len(self._past) >= 2 and self._past[1][0] <= then:
            del self._past[0]
        y_then, rates_then, velocity_then = self._at(then)
        p, rng = self.profile, self.rng
        y_then[:, 0:3] += self.attitude_bias_rad + p.attitude_noise_rad * rng.standard_normal((self.n, 3))
        y_then[:, 3:6] += self.position_bias_m + p.position_noise_m * rng.standard_normal((self.n, 3))
        return y_then, rates_then + p.gyro_noise_rad_s * rng.standard_normal((self.n, 3)), velocity_then

    def _wander(self, dt_s: float) -> None:
        """The biases dt_s on: a = exp(-dt / tau), the step's noise keeping the variance sigma^2
        (1 - a^2); the estimator's smoothing follows them by 1 - exp(-dt / T)."""
        p, rng = self.profile, self.rng
        a = math.exp(-dt_s / p.bias_time_s)
        k = math.sqrt(1.0 - a * a)
        self._pos_raw = a * self._pos_raw + k * self._pos_sigma * rng.standard_normal((self.n, 3))
        self._att_raw = a * self._att_raw + k * self._att_sigma * rng.standard_normal((self.n, 3))
        follow = 1.0 - math.exp(-dt_s / p.smoothing_s) if p.smoothing_s > 0 else 1.0
        self.position_bias_m += follow * (self._pos_raw - self.position_bias_m)
        self.attitude_bias_rad += follow * (self._att_raw - self.attitude_bias_rad)

    def _at(self, t_s: float):
        """The truth at t_s, linear between the two reports around it (angles the short way round);
        the oldest kept if the flight is younger than the lag. Copies."""
        t0, y0, r0, v0 = self._past[0]
        if len(self._past) < 2 or t_s <= t0:
            return y0.copy(), r0.copy(), None if v0 is None else v0.copy()
        t1, y1, r1, v1 = self._past[1]
        f = (t_s - t0) / (t1 - t0)
        step = y1 - y0
        step[:, 0:3] = wrap_angle(step[:, 0:3])
        return y0 + f * step, r0 + f * (r1 - r0), None if v0 is None else v0 + f * (v1 - v0)
