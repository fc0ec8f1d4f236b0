"""The tri-rotor plant: rigid-body physics of N drones, no I/O.

Dynamics are the paper's (24)-(25) for body velocity and body rates, with the attitude carried as a
unit quaternion (scalar first) instead of Euler angles so the plant never meets the pitch = +-90 deg
singularity of (26), whatever a flight-controller client commands. Position follows (27).

Forces and torques, and what they do to the body's velocity and rates, are the protocol's
``dynamics.rigid_body`` (one copy, also behind ``model.state_derivative``); this module adds the
quaternion kinematics, the integrator, the actuators, the ground and the wind.

Wind (``protocol.wind``): with a ``Wind`` the body feels drag against its velocity relative to the
air: the steady wind, every gust and each drone's own Dryden turbulence, whose noise comes from a
Generator seeded by ``wind_seed`` and drawn a step at a time (the same seed gives the same wind
however the steps are grouped into ``advance`` calls). The wind is taken at the start of each
physics step and held through it. Without a Wind there is no air at all: the paper's model, exactly.

Actuators, per rotor: motor speed omega in [0, max_rotor_speed] applied at once; servo angle alpha
clamped to +-servo_limit and applied after a pure transport delay (servo_delay_s, rounded to whole
physics steps), the servo then turning towards it at servo_rate_rad_s at most (0: at once). Ground
contact: z never goes below 0; a drone on the ground stays at rest, level, until its thrust lifts
more than its weight.

State per drone (13): position_e [m] (0:3), velocity_b [m/s] (3:6), quaternion_b2e (6:10),
rate_b [rad/s] (10:13), in the paper's frames (earth z up, body z along the untilted thrust).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from triswarm.protocol.airframe import Airframe
from triswarm.protocol.frames import euler_from_quaternion, quaternion_from_euler, rotation_from_quaternion  # noqa: F401 (also for callers)
from triswarm.protocol.dynamics import GRAVITY, KF, MASS, MAX_OMEGA, SERVO_LIMIT, SERVO_RATE, airframe_vector, \
    drag, propulsive_force, rigid_body
from triswarm.protocol.wind import TURBULENCE_STATES, Dryden, Wind, gusts_at, turbulence_step

POS, VEL_B, QUAT, RATE_B = slice(0, 3), slice(3, 6), slice(6, 10), slice(10, 13)
PLANT_DIM = 13


@numba.njit(cache=True, fastmath=False)
def _derivative(s, rho, P, wind_now, i, out):
    """d/dt of one drone's plant state s (13) under input rho and parameters P, in the wind
    wind_now[i] [m/s], or with wind_now None in no air (numba compiles that case without the drag)."""
    qw, qx, qy, qz = s[6], s[7], s[8], s[9]
    # Body-to-earth rotation of the (normalised) quaternion.
    n2 = qw * qw + qx * qx + qy * qy + qz * qz
    k = 2.0 / n2
    R = (1.0 - k * (qy * qy + qz * qz), k * (qx * qy - qz * qw), k * (qx * qz + qy * qw),
         k * (qx * qy + qz * qw), 1.0 - k * (qx * qx + qz * qz), k * (qy * qz - qx * qw),
         k * (qx * qz - qy * qw), k * (qy * qz + qx * qw), 1.0 - k * (qx * qx + qy * qy))
    p, q, r = s[10], s[11], s[12]
    d = rigid_body(s[3], s[4], s[5], p, q, r, R, rho, P)
    out[3], out[4], out[5], out[10], out[11], out[12], out[0], out[1], out[2] = d
    if wind_now is not None:
        a = drag((d[6], d[7], d[8]), R, P, (wind_now[i, 0], wind_now[i, 1], wind_now[i, 2]))
        out[3] += a[0]
        out[4] += a[1]
        out[5] += a[2]
    # Quaternion kinematics q_dot = 1/2 q (x) [0, w].
    out[6] = 0.5 * (-qx * p - qy * q - qz * r)
    out[7] = 0.5 * (qw * p + qy * r - qz * q)
    out[8] = 0.5 * (qw * q - qx * r + qz * p)
    out[9] = 0.5 * (qw * r + qx * q - qy * p)


@numba.njit(cache=True)
def _wind_at(air, step, i, dt, wind_now, scratch):
    """Drone i's wind for this step (steady, gusts, its turbulence), earth frame [m/s], into
    wind_now[i]; its Dryden state moves on a step."""
    step0, steady, gusts, turb_x, Phi, L, C, noise = air
    gx, gy, gz = gusts_at((step0 + step) * dt, gusts)
    wind = wind_now[i]
    wind[0], wind[1], wind[2] = steady[0] + gx, steady[1] + gy, steady[2] + gz
    if noise.shape[0] > 0:
        tx, ty, tz = turbulence_step(turb_x[i], noise[step, i], Phi, L, C, scratch)
        wind[0] += tx
        wind[1] += ty
        wind[2] += tz


@numba.njit(cache=True)
def _advance(state, landed, omega_cmd, alpha_cmd, alpha_hist, hist_pos, delay_steps, servo, params, dt, n_steps,
             rho_out, applied, air, wind_now):
    """Advance every drone n_steps physics steps of dt with the commands held. params (N,
    ``dynamics.PARAM_DIM``) and delay_steps (N,) are per drone; servo (N, 3) holds the angle each
    servo is at (updated). ``applied`` (N, 6) holds the rotor speeds and servo angles
    rho_out was last computed from (the sines and cosines are reused while they hold). ``air`` is
    ``_Air.kernel_args`` and wind_now (N, 3) the wind each drone feels, both None in no air (numba
    compiles that case without any of the wind). Returns hist_pos."""
    n = state.shape[0]
    H = alpha_hist.shape[1]
    k1 = np.empty(13)
    k2 = np.empty(13)
    k3 = np.empty(13)
    k4 = np.empty(13)
    tmp = np.empty(13)
    rho = np.empty(6)
    scratch = np.empty(TURBULENCE_STATES)
    for step in range(n_steps):
        for i in range(n):
            if air is not None:
                _wind_at(air, step, i, dt, wind_now, scratch)
            P = params[i]
            wmax, amax, turn = P[MAX_OMEGA], P[SERVO_LIMIT], P[SERVO_RATE] * dt
            # Servo transport delay through a ring buffer; commands are clamped to the servo range.
            for j in range(3):
                a = alpha_cmd[i, j]
                if a > amax:
                    a = amax
                elif a < -amax:
                    a = -amax
                alpha_hist[i, hist_pos, j] = a
            lag = (hist_pos - delay_steps[i]) % H
            for j in range(3):
                wj = omega_cmd[i, j]
                if wj > wmax:
                    wj = wmax
                elif wj < 0.0:
                    wj = 0.0
                a = alpha_hist[i, lag, j]
                if turn > 0.0:  # the servo turns towards the delayed command at its rate
                    now = servo[i, j]
                    a = min(max(a, now - turn), now + turn)
                servo[i, j] = a
                if wj != applied[i, j] or a != applied[i, j + 3]:
                    w2 = wj * wj
                    rho_out[i, j] = w2 * math.sin(a)
                    rho_out[i, j + 3] = w2 * math.cos(a)
                    applied[i, j] = wj
                    applied[i, j + 3] = a
            for j in range(6):
                rho[j] = rho_out[i, j]
            s = state[i]
            if landed[i]:
                # Resting on the ground: lift off only when thrust exceeds weight.
                qw, qx, qy, qz = s[6], s[7], s[8], s[9]
                n2 = qw * qw + qx * qx + qy * qy + qz * qz
                k = 2.0 / n2
                r20 = k * (qx * qz - qy * qw)
                r21 = k * (qy * qz + qx * qw)
                r22 = 1.0 - k * (qx * qx + qy * qy)
                hf0, hf1, hf2 = propulsive_force(rho)
                lift = P[KF] * (r20 * hf0 + r21 * hf1 + r22 * hf2)
                if lift <= P[MASS] * P[GRAVITY]:
                    continue
                landed[i] = False
            _derivative(s, rho, P, wind_now, i, k1)
            for j in range(13):
                tmp[j] = s[j] + 0.5 * dt * k1[j]
            _derivative(tmp, rho, P, wind_now, i, k2)
            for j in range(13):
                tmp[j] = s[j] + 0.5 * dt * k2[j]
            _derivative(tmp, rho, P, wind_now, i, k3)
            for j in range(13):
                tmp[j] = s[j] + dt * k3[j]
            _derivative(tmp, rho, P, wind_now, i, k4)
            for j in range(13):
                s[j] += dt / 6.0 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])
            qn = math.sqrt(s[6] * s[6] + s[7] * s[7] + s[8] * s[8] + s[9] * s[9])
            for j in range(6, 10):
                s[j] /= qn
            if s[2] < 0.0:
                # Touch down: stop on the ground, level, keeping the heading.
                s[2] = 0.0
                qw, qx, qy, qz = s[6], s[7], s[8], s[9]
                yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
                s[6] = math.cos(0.5 * yaw)
                s[7] = 0.0
                s[8] = 0.0
                s[9] = math.sin(0.5 * yaw)
                for j in range(3, 6):
                    s[j] = 0.0
                for j in range(10, 13):
                    s[j] = 0.0
                landed[i] = True
        hist_pos = (hist_pos + 1) % H
    return hist_pos


SENSOR_COLUMNS = {"position_m": slice(0, 3), "velocity_e_m_s": slice(3, 6), "velocity_b_m_s": slice(6, 9),
                  "euler_rad": slice(9, 12), "quaternion": slice(12, 16), "rate_b_rad_s": slice(16, 19),
                  "specific_force_b": slice(19, 22)}
"""Where each quantity of ``Plant.sensors`` is, paper frames."""


@numba.njit(cache=True)
def _sensors(state, rho, params, landed, wind_now, out):
    """What ideal sensors read on every drone: out (N, 22), columns as ``SENSOR_COLUMNS``. The
    specific force is what an accelerometer feels (body frame): thrust and drag in flight; at rest
    on the ground, the push that holds it against gravity, whatever the rotors do (the ground takes
    the thrust's share: a drone spinning up is not accelerating)."""
    for i in range(state.shape[0]):
        s, P = state[i], params[i]
        qw, qx, qy, qz = s[6], s[7], s[8], s[9]
        n2 = qw * qw + qx * qx + qy * qy + qz * qz
        k = 2.0 / n2
        R = (1.0 - k * (qy * qy + qz * qz), k * (qx * qy - qz * qw), k * (qx * qz + qy * qw),
             k * (qx * qy + qz * qw), 1.0 - k * (qx * qx + qz * qz), k * (qy * qz - qx * qw),
             k * (qx * qz - qy * qw), k * (qy * qz + qx * qw), 1.0 - k * (qx * qx + qy * qy))
        u, v, w = s[3], s[4], s[5]
        ve = (R[0] * u + R[1] * v + R[2] * w, R[3] * u + R[4] * v + R[5] * w, R[6] * u + R[7] * v + R[8] * w)
        for c in range(3):
            out[i, c] = s[c]
            out[i, 3 + c] = ve[c]
            out[i, 6 + c] = s[3 + c]
            out[i, 16 + c] = s[10 + c]
        out[i, 9] = math.atan2(2.0 * (qw * qx + qy * qz), 1.0 - 2.0 * (qx * qx + qy * qy))
        out[i, 10] = math.asin(min(max(2.0 * (qw * qy - qz * qx), -1.0), 1.0))
        out[i, 11] = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
        out[i, 12], out[i, 13], out[i, 14], out[i, 15] = qw, qx, qy, qz
        f = propulsive_force(rho[i])
        kf_m = P[KF] / P[MASS]
        sf = [kf_m * f[0], kf_m * f[1], kf_m * f[2]]
        if wind_now is not None:
            a = drag(ve, R, P, (wind_now[i, 0], wind_now[i, 1], wind_now[i, 2]))
            for c in range(3):
                sf[c] += a[c]
        if landed[i]:  # at rest: the ground takes whatever the thrust does not, so the reading is gravity's
            g = P[GRAVITY]
            sf[0] = g * R[6]
            sf[1] = g * R[7]
            sf[2] = g * R[8]
        for c in range(3):
            out[i, 19 + c] = sf[c]


@numba.njit(cache=True)
def _output(state, y):
    """y = (roll, pitch, yaw, position) per drone, (N, 6): ``euler_from_quaternion`` and the
    position, compiled for the control loop."""
    for i in range(state.shape[0]):
        qw, qx, qy, qz = state[i, 6], state[i, 7], state[i, 8], state[i, 9]
        y[i, 0] = math.atan2(2.0 * (qw * qx + qy * qz), 1.0 - 2.0 * (qx * qx + qy * qy))
        y[i, 1] = math.asin(min(max(2.0 * (qw * qy - qz * qx), -1.0), 1.0))
        y[i, 2] = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
        y[i, 3] = state[i, 0]
        y[i, 4] = state[i, 1]
        y[i, 5] = state[i, 2]


@dataclass
class PlantState:
    """What the sensors of each drone would see, noise-free, in the paper's frames."""

    position_m: np.ndarray       # (N, 3) earth
    velocity_e_m_s: np.ndarray   # (N, 3) earth
    velocity_b_m_s: np.ndarray   # (N, 3) body
    euler_rad: np.ndarray        # (N, 3) roll, pitch, yaw
    rate_b_rad_s: np.ndarray     # (N, 3) body rates p, q, r
    landed: np.ndarray           # (N,) bool

    def paper_state(self) -> np.ndarray:
        """x of (28): [v_b, omega_b, eta, lambda], (N, 12)."""
        return np.concatenate([self.velocity_b_m_s, self.rate_b_rad_s, self.euler_rad, self.position_m], axis=1)


class _Air:
    """The wind's state for the kernel: the steady wind, the gusts, each drone's Dryden state and
    the noise that drives it, drawn from ``rng`` a step at a time."""

    WIND_STREAM = 0x57494E44
    """Mixed into the seed, so the wind's numbers are not those of another user of the same seed."""

    def __init__(self, wind: Wind | None, n: int, dt_s: float, seed: int) -> None:
        self.wind = wind
        self.wind_now = np.zeros((n, 3))
        self.turbulent = wind is not None and wind.turbulence_sigma_w_m_s > 0
        self.noise = np.zeros((0, n, TURBULENCE_STATES))
        self.turb_x = np.zeros((n, TURBULENCE_STATES))
        Phi = L = np.zeros((TURBULENCE_STATES, TURBULENCE_STATES))
        C = np.zeros((3, TURBULENCE_STATES))
        if self.turbulent:
            self.rng = np.random.default_rng([seed, self.WIND_STREAM])
            dryden = Dryden.of(wind, dt_s)
            Phi, L, C = dryden.Phi, dryden.L, dryden.C
            # every drone starts in the stationary distribution of its filters
            w, V = np.linalg.eigh(dryden.P)
            self.turb_x[:] = self.rng.standard_normal((n, TURBULENCE_STATES)) @ (V * np.sqrt(np.clip(w, 0, None))).T
        if wind is not None:
            self.wind_now[:] = wind.steady_e_m_s
            self._fixed = (wind.steady_e_m_s, wind.gust_table(), self.turb_x, Phi, L, C)

    def sensor_wind(self) -> np.ndarray | None:
        """The wind each drone felt during the last step (N, 3) [m/s], or None in no air."""
        return None if self.wind is None else self.wind_now

    def kernel_args(self, step0: int, n_steps: int) -> tuple | None:
        """The kernel's ``air`` for n_steps from step0: None in no air."""
        if self.wind is None:
            return None
        if self.turbulent:
            self.noise = self.rng.standard_normal((n_steps, self.turb_x.shape[0], TURBULENCE_STATES))
        steady, gusts, turb_x, Phi, L, C = self._fixed
        return (step0, steady, gusts, turb_x, Phi, L, C, self.noise)


class Plant:
    """N tri-rotors integrated with RK4 at a fixed physics step, in a wind or in no air at all."""

    def __init__(self, airframe: Airframe, n_drones: int, dt_s: float = 1e-3,
                 servo_delay_s: float | None = None, wind: Wind | None = None, wind_seed: int = 0) -> None:
        if not (dt_s > 0 and math.isfinite(dt_s)):
            raise ValueError(f"physics step must be a positive number of seconds, got {dt_s!r}")
        self.dt_s = float(dt_s)
        self.n = int(n_drones)
        if servo_delay_s is not None:
            airframe = airframe.replace(servo_delay_s=servo_delay_s)
        self.airframes = [airframe] * self.n
        self.air_density_kg_m3 = 0.0 if wind is None else wind.air_density_kg_m3
        """0 without a wind: no drag."""
        self.params = np.tile(airframe_vector(airframe, self.air_density_kg_m3), (self.n, 1))
        self._air = _Air(wind, self.n, self.dt_s, wind_seed)
        self.delay_steps = np.full(self.n, self._steps_of(airframe.servo_delay_s), dtype=np.int64)
        self.state = np.zeros((self.n, PLANT_DIM))
        self.state[:, 6] = 1.0
        self.landed = np.ones(self.n, dtype=np.bool_)
        self.omega_cmd = np.zeros((self.n, 3))
        self.alpha_cmd = np.zeros((self.n, 3))
        self.alpha_hist = np.zeros((self.n, int(self.delay_steps.max()) + 1, 3))
        self.hist_pos = 0
        self.servo_rad = np.zeros((self.n, 3))
        """The angle each servo is at [rad] (behind its delayed command while it turns)."""
        self.rho = np.zeros((self.n, 6))
        """rho (29) actually applied during the last physics step (after limits and delay)."""
        self._applied = np.full((self.n, 6), np.nan)  # what self.rho was computed from
        self.time_s = 0.0
        self.steps = 0

    def _steps_of(self, delay_s: float) -> int:
        if not (math.isfinite(delay_s) and delay_s >= 0):
            raise ValueError(f"servo delay must be a non-negative number of seconds, got {delay_s!r}")
        return int(round(delay_s / self.dt_s))

    def set_airframe(self, i: int, af: Airframe) -> None:
        """Change drone i's physical parameters (e.g. a parameter set over MAVLink)."""
        self.airframes[i] = af
        self.params[i] = airframe_vector(af, self.air_density_kg_m3)
        steps = self._steps_of(af.servo_delay_s)
        if steps + 1 > self.alpha_hist.shape[1]:
            # a longer history: every drone keeps the angle its servos hold now
            current = self.alpha_hist[np.arange(self.n), (self.hist_pos - self.delay_steps) % self.alpha_hist.shape[1]]
            self.alpha_hist = np.repeat(current[:, None, :], steps + 1, axis=1)
            self.hist_pos = 0
        self.delay_steps[i] = steps

    def reset(self, position_m: np.ndarray, euler_rad: np.ndarray | None = None,
              velocity_b_m_s: np.ndarray | None = None, rate_b_rad_s: np.ndarray | None = None,
              servo_rad: np.ndarray | None = None) -> None:
        """Place the drones; a drone at z <= 0 with no velocity starts landed."""
        pos = np.array(position_m, dtype=float).reshape(self.n, 3)
        eta = np.zeros((self.n, 3)) if euler_rad is None else np.array(euler_rad, dtype=float).reshape(self.n, 3)
        self.state[:, POS] = pos
        self.state[:, QUAT] = quaternion_from_euler(eta)
        self.state[:, VEL_B] = 0.0 if velocity_b_m_s is None else velocity_b_m_s
        self.state[:, RATE_B] = 0.0 if rate_b_rad_s is None else rate_b_rad_s
        self.landed[:] = (pos[:, 2] <= 0.0) & (np.abs(self.state[:, VEL_B]).sum(axis=1) == 0.0)
        self.state[self.landed, 2] = 0.0
        servo = np.zeros((self.n, 3)) if servo_rad is None else np.broadcast_to(servo_rad, (self.n, 3))
        self.alpha_hist[:] = servo[:, None, :]
        self.alpha_cmd[:] = servo
        self.servo_rad[:] = servo
        self.time_s = 0.0
        self.steps = 0

    def command(self, omega_rad_s: np.ndarray, alpha_rad: np.ndarray) -> None:
        """Motor speeds [rad/s] and servo angles [rad], (N, 3) each; held until the next command.
        Non-finite values are replaced by 0 (motor stop / servo centred) rather than integrated."""
        w = np.asarray(omega_rad_s, dtype=float)
        a = np.asarray(alpha_rad, dtype=float)
        self.omega_cmd[:] = np.where(np.isfinite(w), w, 0.0)
        self.alpha_cmd[:] = np.where(np.isfinite(a), a, 0.0)

    def advance(self, n_steps: int) -> None:
        self.hist_pos = _advance(self.state, self.landed, self.omega_cmd, self.alpha_cmd, self.alpha_hist,
                                 self.hist_pos, self.delay_steps, self.servo_rad, self.params, self.dt_s, int(n_steps),
                                 self.rho,
                                 self._applied, self._air.kernel_args(self.steps, int(n_steps)),
                                 None if self._air.wind is None else self._air.wind_now)
        self.steps += int(n_steps)
        self.time_s = self.steps * self.dt_s

    @property
    def wind(self) -> Wind | None:
        return self._air.wind

    @property
    def wind_e_m_s(self) -> np.ndarray:
        """The wind each drone felt during the last physics step, earth frame [m/s], (N, 3)."""
        return self._air.wind_now

    def output(self) -> np.ndarray:
        """What the controller measures, noise-free: y = (eta [rad], lambda [m]) per drone, (N, 6)."""
        y = np.empty((self.n, 6))
        _output(self.state, y)
        return y

    def sensors(self) -> np.ndarray:
        """What ideal sensors read on every drone now (N, 22), columns as ``SENSOR_COLUMNS``."""
        out = np.empty((self.n, 22))
        _sensors(self.state, self.rho, self.params, self.landed, self._air.sensor_wind(), out)
        return out

    def observe(self) -> PlantState:
        s = self.state
        q = s[:, QUAT]
        R = rotation_from_quaternion(q)
        vel_b = s[:, VEL_B].copy()
        return PlantState(
            position_m=s[:, POS].copy(),
            velocity_e_m_s=(R @ vel_b[:, :, None])[:, :, 0],
            velocity_b_m_s=vel_b,
            euler_rad=euler_from_quaternion(q),
            rate_b_rad_s=s[:, RATE_B].copy(),
            landed=self.landed.copy(),
        )
