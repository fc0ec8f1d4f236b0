"""The per-drone controller between the protocol (72) and the actuators, for N agents at once.

One tick of an agent, at time t with measured output y = (eta, lambda):

    xhat  = controller.observe(y)            # estimate of x_r at t + lead_s   -> publish xi = xhat - h
    v     = protocol_input(...)              # (72), from own and neighbours' xi at t + lead_s
    act   = controller.actuate(v)            # rotor speeds and servo angles to send now

What this adds to the paper's law, and why (see docs/control-design.md):

* Servo delay. The servos act d = servo_delay_s after their command, the motors at once. The motor
  command is held back by the same d in software, which turns the mixed delay into a pure input
  delay of the whole u; an exact predictor (the discrete model over the inputs already committed)
  then gives the state at t + d, and the protocol and the RFL act on that prediction. For the
  nominal plant the loop is the delay-free loop shifted by d (a Smith predictor).
* Latency. Where the command that answers a measurement reaches the flight controller
  ``latency_s`` after the instant the measurement is stamped with (the link, the companion's work,
  the flight controller's own step), the whole input acts that much later again: the predictor runs
  over d + latency, the motors are still held back by d alone.
* Observer. (73) is discretised with a zero-order hold on v and a first-order hold on y, updated
  when y arrives, so the estimate used at tick k has seen y_k. With ``Design.F_aug`` it also
  estimates an acceleration disturbance on x_r rows 1-6, which the command cancels.
* Drag. In air (``air_density_kg_m3`` > 0) the RFL also cancels the body's drag in still air,
  -(k/m) |v| v at the estimated velocity (``rfl`` module docstring); the observer's disturbance is
  then the wind's share alone.
* Body rates. Measured body rates can be three more outputs of the observer (``measured_rates``);
  off by default: they cost half the servo-delay margin (docs/control-design.md).
* Accelerometer. With ``measured_accel`` (a plan's default in air) the measured specific force,
  turned to the earth frame, less the acceleration the model's input explains, is three more
  outputs of the observer with the disturbance in them, and the accelerometer's bias three more
  states (``design.accel_model``): the disturbance is measured. A tick without it runs without.
* Servo range. A drone with a rotor held at the servo range's edge commits the v its rotors then
  deliver (``kernels.input_shortfall_v``), so the observer's disturbance estimate does not wind up
  on the actuators' shortfall; with no rotor at the edge, v itself, to the bit.
* Servo speed. Where the airframe states how fast a servo turns, no servo command is further from
  the last than it turns in a period, and the rotors' forces are the best within that reach
  (``kernels.allocate_within_reach``), so the servos follow the commands and the predictor stays
  exact.
* Thrust effectiveness. A scalar kappa ~ (k_f/m)_plant / (k_f/m)_model, adapted from the
  translational disturbance along the specific thrust asked before the disturbance is cancelled
  (the idea of PX4's hover-thrust estimator) and divided out of u, so a heavier drone or a weaker
  propeller is flown as designed.

Everything here is arrays in, arrays out; time and measurements come in as arguments.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg

from .design import Design, accel_model, zoh
from . import kernels
from .model import actuator_inverse
from .rfl import MAX_PITCH_RAD, RFL

if TYPE_CHECKING:
    from .plan import Plan
    from .wind import Wind


WIND_ESTIMATE_FLOOR_M_S = 1.0
"""Airspeed [m/s] below which the wind estimate's step is taken as at this speed: the drag's
sensitivity to the wind, 2 k |r| / m, vanishes with the airspeed |r|."""


def _zoh_foh(A: np.ndarray, B_hold: np.ndarray, B_ramp: np.ndarray, T: float):
    """x(T) = Phi x0 + G_hold u + G0 y0 + G1 y1 for x' = A x + B_hold u + B_ramp y(t), u held and
    y linear from y0 (t = 0) to y1 (t = T)."""
    n, m, p = A.shape[0], B_hold.shape[1], B_ramp.shape[1]
    M = np.zeros((n + m + 2 * p, n + m + 2 * p))
    M[:n, :n] = A * T
    M[:n, n:n + m] = B_hold * T
    M[:n, n + m:n + m + p] = B_ramp * T
    M[n + m:n + m + p, n + m + p:] = np.eye(p)  # y(s) = y0 + s (y1 - y0), s = t / T
    E = scipy.linalg.expm(M)
    Phi = E[:n, :n]
    G_hold = E[:n, n:n + m]
    G_level = E[:n, n + m:n + m + p]
    G_slope = E[:n, n + m + p:]
    return Phi, G_hold, G_level - G_slope, G_slope


@dataclass(frozen=True)
class Actuation:
    """Commands to send now, (N, 3) each: rotor speeds [rad/s] and servo angles [rad]."""

    omega_rad_s: np.ndarray
    alpha_rad: np.ndarray


def lead_ticks(servo_delay_s: float, latency_s: float, dt_s: float) -> tuple[int, int]:
    """The servo delay and the lead (the servo delay and the latency) in whole control periods."""
    servo = int(round(servo_delay_s / dt_s))
    return servo, max(int(round((servo_delay_s + latency_s) / dt_s)), servo)


class FormationController:
    """Observer, delay predictor, thrust adaptation, RFL and actuator inverse for N agents."""

    @staticmethod
    def warm_up(design: Design, rate_hz: float) -> None:
        """Compile the kernels (or load them from numba's cache) now, on a scratch controller, not
        at the first tick in the air: a first compile takes seconds, a cache load some 300 ms."""
        from .agent import protocol_rows

        scratch = FormationController(design, 1, rate_hz, measured_rates=True)
        scratch.reset(np.r_[np.zeros(11), 1.0][None, :])
        y = np.r_[np.zeros(5), 1.0][None, :]
        scratch.observe(y, [0], np.zeros((1, 3)))
        scratch.actuate(np.zeros((1, 6)), [0])
        scratch.hold_tick(y, [0])
        z = np.zeros((1, 12))
        protocol_rows(design, z, z, np.zeros(1), np.ones(1), z, design.gamma(z, z))

    @classmethod
    def for_plan(cls, plan: "Plan", n_agents: int, rate_hz: float, wind: "Wind | None",
                 delay_s: float | None = None, measured_rates: bool = False) -> "FormationController":
        """The controller of ``plan`` flown in ``wind`` (None: no air), with the plan's design,
        thrust adaptation, wind estimate, and the air density and accelerometer that
        ``Plan.controller_air_density_kg_m3`` and ``Plan.controller_accelerometer`` give: the one
        way a simulation and the companions make theirs."""
        return cls(plan.design, n_agents, rate_hz, delay_s, measured_accel=plan.controller_accelerometer(wind),
                   thrust_adaptation_rate_1_s=plan.controller.thrust_adaptation_rate_1_s,
                   air_density_kg_m3=plan.controller_air_density_kg_m3(wind), measured_rates=measured_rates,
                   wind_estimate_rate_1_s=plan.controller.wind_estimate_rate_1_s, latency_s=plan.controller.latency_s)

    def __init__(self, design: Design, n_agents: int, rate_hz: float = 200.0, delay_s: float | None = None,
                 thrust_adaptation_rate_1_s: float = 3.0, thrust_scale_limits: tuple[float, float] = (0.3, 3.0),
                 air_density_kg_m3: float = 0.0, measured_rates: bool = False,
                 wind_estimate_rate_1_s: float = 0.0, measured_accel: bool = False, latency_s: float = 0.0) -> None:
        """latency_s: the time [s] from the instant a measurement is stamped with to the flight
        controller taking the command that answers it (the link, the companion's own work), which
        the predictor runs ahead by on top of the servo delay (0: none). air_density_kg_m3: the air
        the drones fly in, as the controller assumes it [kg/m^3], for the drag the RFL cancels; 0 is
        no air (the paper's law, to the bit). wind_estimate_rate_1_s: the rate [1/s] at which the
        wind estimate takes up the translational disturbance that its drag explains (``kernels.update_wind_estimate``; 0: still air assumed, no wind estimate)."""
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"controller rate must be a positive number of hertz, got {rate_hz!r}")
        self.design = design
        self.rfl: RFL = design.rfl
        self.n = int(n_agents)
        self.dt_s = 1.0 / float(rate_hz)
        delay = self.rfl.airframe.servo_delay_s if delay_s is None else float(delay_s)
        if not (np.isfinite(delay) and delay >= 0):
            raise ValueError(f"compensated servo delay must be a non-negative number of seconds, got {delay!r}")
        if not (np.isfinite(latency_s) and latency_s >= 0):
            raise ValueError(f"compensated latency must be a non-negative number of seconds, got {latency_s!r}")
        self.servo_ticks, self.lead_ticks = lead_ticks(delay, latency_s, self.dt_s)
        """The servo delay in whole ticks (the motor commands are held back by it), and the lead."""
        self.lead_s = self.lead_ticks * self.dt_s
        """Estimates and protocol inputs refer to t + lead_s: the servo delay and the latency, in whole ticks."""
        if not (np.isfinite(air_density_kg_m3) and air_density_kg_m3 >= 0):
            raise ValueError(f"air density must be a non-negative number of kg/m^3, got {air_density_kg_m3!r}")
        self.air_density_kg_m3 = float(air_density_kg_m3)
        self.drag_1_m = self.rfl.drag_per_mass_1_m(self.air_density_kg_m3)
        """k / m of the drag the RFL cancels [1/m] (0: none)."""
        self.measured_rates = bool(measured_rates)
        """Take the body rates given to ``observe`` (the observer with the Euler rates as three more
        outputs); off: the observer alone estimates them (docs/control-design.md says why it is
        the default)."""
        self.measured_accel = bool(measured_accel)
        """Take the specific force given to ``observe`` (the observer, with a disturbance estimate,
        with the earth-frame acceleration as three more outputs: an accelerometer measures the
        disturbance)."""
        self.adaptation_rate = float(thrust_adaptation_rate_1_s)
        if not (np.isfinite(wind_estimate_rate_1_s) and wind_estimate_rate_1_s >= 0):
            raise ValueError(f"wind estimate rate must be a non-negative number of 1/s, got {wind_estimate_rate_1_s!r}")
        self.wind_estimate_rate_1_s = float(wind_estimate_rate_1_s)
        self.kappa_limits = thrust_scale_limits

        A, B, C, _ = design.observer_model()
        if self.measured_accel and design.estimates_disturbance:  # (the accelerometer's bias: three more states)
            A, B, _ = accel_model(A, B, C)
        self.n_z = A.shape[0]
        # contiguous copies: the compiled loops index them row by row
        Phi1, G1 = map(np.ascontiguousarray, zoh(A, B, self.dt_s))
        self._Phi1, self._G1 = Phi1, G1
        # Prediction over the pipe: z(t + D dt) = Phi1^D z + sum_j Phi1^(D-1-j) G1 v_j.
        self._pred_Phi = np.linalg.matrix_power(Phi1, self.lead_ticks)
        self._pred_G = np.array([np.linalg.matrix_power(Phi1, self.lead_ticks - 1 - j) @ G1
                                 for j in range(self.lead_ticks)]).reshape(self.lead_ticks, self.n_z, 6)
        # One discretisation per set of outputs measured (design.RATES | design.ACCEL), each over the
        # 12 outputs of design.full_output (zero columns for those not measured). One whose model has
        # fewer states (no accelerometer's bias) holds the others as they are.
        n = self.n_z
        self._Phi_m = np.tile(np.eye(n), (4, 1, 1))
        self._Gv_m, self._Gy0_m, self._Gy1_m = np.zeros((4, n, 6)), np.zeros((4, n, 12)), np.zeros((4, n, 12))
        for measured in range(4):
            Am, Bm, Cm, Fm = design.measured_observer_model(measured)
            m = Am.shape[0]
            if m > n:  # (an accelerometer's gains in a controller that does not take it)
                continue
            idx = design.outputs_measured(measured)
            Phi, Gv, Gy0, Gy1 = _zoh_foh(Am - design.c * Fm @ Cm, Bm, design.c * Fm, self.dt_s)
            self._Phi_m[measured][:m, :m], self._Gv_m[measured][:m] = Phi, Gv
            self._Gy0_m[measured][:m, idx], self._Gy1_m[measured][:m, idx] = Gy0, Gy1
        self._B_accel = np.ascontiguousarray(design.B_r[0:3])
        self._half_Phi, self._half_G = map(np.ascontiguousarray, zoh(A, B, 0.5 * self.dt_s))
        self._Einv = np.linalg.inv(design.B_r[0:6]) if design.estimates_disturbance else None
        self._Einv_or_zero = self._Einv if self._Einv is not None else np.zeros((6, 6))
        self._adapt_k = self.adaptation_rate * self.dt_s if self._Einv is not None else 0.0
        self._wind_gain = self.wind_estimate_rate_1_s * self.dt_s if self._Einv is not None else 0.0
        self._G = np.ascontiguousarray(np.linalg.inv(self.rfl.G_inv))
        self._M0_inv = np.ascontiguousarray(np.linalg.inv(self.rfl.M0))
        """G and M(0)^-1: what the observer is told a rotor held at the servo range's edge delivered,
        as a protocol input (``kernels.input_shortfall_v``)."""
        self.wind_estimate_e_m_s = np.zeros((self.n, 3))
        """The wind each agent's controller has estimated, earth frame [m/s] (N, 3): the RFL cancels
        the drag of the drone's velocity relative to it."""
        step = self.rfl.airframe.servo_rate_rad_s * self.dt_s
        self._servo_step_rad = step if step < 0.5 * np.pi else 0.0
        """How far a servo turns in one period [rad]; 0: at once (also a servo that turns a quarter of a
        turn or more in a period: its reach is then no convex cone, and no limit)."""
        self.servo_command_rad: np.ndarray | None = None
        """The servo angles each agent last commanded [rad] (N, 3): its servos turn from there."""
        self.z: np.ndarray | None = None
        self._y_prev: np.ndarray | None = None
        self.thrust_scale = np.ones(self.n)
        self._all_rows = np.arange(self.n, dtype=np.int64)

    # -- state ---------------------------------------------------------------------------------

    def reset(self, x: np.ndarray, rows: np.ndarray | None = None) -> None:
        """Start from the measured state x of (28), e.g. at rest on the ground: (N, 12), or
        (len(rows), 12) to restart only those agents (the others keep their state)."""
        if self.z is None:
            self.z = np.zeros((self.n, self.n_z))
            self._y_prev = np.full((self.n, 12), np.nan)
            self._fresh = np.ones(self.n, dtype=np.bool_)
            self._v_pipe = np.zeros((self.lead_ticks, self.n, 6))
            self._motor_pipe = np.zeros((self.servo_ticks, self.n, 3))
            self._v_applied = np.zeros((self.n, 6))
            self._z_pred = np.zeros((self.n, self.n_z))
            self.initial_actuation = Actuation(np.zeros((self.n, 3)), np.zeros((self.n, 3)))
            self.servo_command_rad = np.zeros((self.n, 3))
        rows = self._rows(rows)
        x = np.asarray(x, dtype=float).reshape(rows.size, 12)
        self.z[rows] = 0.0
        self.z[rows, :12] = self.rfl.phi_r(x)
        self._z_pred[rows] = self.z[rows]
        self._y_prev[rows] = np.nan
        self._y_prev[rows, :6] = x[:, 6:12]
        self._fresh[rows] = True  # the first measurement after a reset is taken, not integrated
        hold = self.rfl.control(x, np.zeros((rows.size, 6)), self.air_density_kg_m3)
        omega, alpha = actuator_inverse(hold)
        self.initial_actuation.omega_rad_s[rows] = omega
        self.initial_actuation.alpha_rad[rows] = alpha
        self.servo_command_rad[rows] = alpha
        self._v_pipe[:, rows] = 0.0
        self._motor_pipe[:, rows] = omega
        self._v_applied[rows] = 0.0
        self.thrust_scale[rows] = 1.0
        self.wind_estimate_e_m_s[rows] = 0.0

    @property
    def disturbance_estimate(self) -> np.ndarray:
        """Estimated acceleration disturbance (N, 6): earth-frame translation [m/s^2] then Euler
        accelerations [rad/s^2]; zeros without disturbance estimation."""
        if self.z is None or self.n_z == 12:
            return np.zeros((self.n, 6))
        return self.z[:, 12:18].copy()

    @property
    def estimate(self) -> np.ndarray:
        """Current (not predicted) estimate of x_r, (N, 12)."""
        return self.z[:, :12].copy()

    # -- one tick ------------------------------------------------------------------------------
    #
    # Each call takes the agents it acts on as ``rows`` (indices, default: every agent), so one
    # controller serves agents whose samples come at different moments (a companion process's
    # agents); the other rows are left exactly as they were.

    def _rows(self, rows) -> np.ndarray:
        if rows is None:
            return self._all_rows
        return np.asarray(rows, dtype=np.int64).reshape(-1)

    def observe(self, y: np.ndarray, rows=None, rate_b_rad_s: np.ndarray | None = None,
                accel_b_m_s2: np.ndarray | None = None) -> np.ndarray:
        """Take y = (eta [rad], lambda [m]) (len(rows), 6) at t, and the body rates measured at t
        (len(rows), 3) [rad/s] where a gyro gives them; return the estimate of x_r at t + lead_s of
        those rows.

        Rows of y that are not finite are treated as missing: the estimate runs on the model. With
        ``measured_rates``, a row with finite rates (and y) runs the observer with the Euler rates
        Psi(eta) omega as three more outputs (``Design.F_rates``); the other rows, and every row
        without ``measured_rates``, run the observer alone, bit for bit."""
        if self.z is None:
            raise RuntimeError("FormationController.observe before reset")
        rows = self._rows(rows)
        y = np.ascontiguousarray(y, dtype=float).reshape(rows.size, 6)
        rates = self._measured(rate_b_rad_s, self.measured_rates, rows.size)
        accel = self._measured(accel_b_m_s2, self.measured_accel and self.design.estimates_disturbance, rows.size)
        kernels.observe(rows, self.z, self._v_applied, self._y_prev, y, self._fresh, self._Phi_m, self._Gv_m,
                        self._Gy0_m, self._Gy1_m, self._Phi1, self._G1, self._pred_Phi, self._pred_G, self._v_pipe,
                        self._z_pred, rates, accel, self._B_accel, self.rfl.airframe.gravity_m_s2, MAX_PITCH_RAD)
        return self._z_pred[rows, :12]

    @staticmethod
    def _measured(values: np.ndarray | None, taken: bool, n_rows: int) -> np.ndarray:
        if values is None or not taken:
            return np.full((n_rows, 3), np.nan)
        return np.ascontiguousarray(values, dtype=float).reshape(n_rows, 3)

    def actuate(self, v: np.ndarray, rows=None) -> Actuation:
        """Turn the protocol input v (len(rows), 6) for t + lead_s into the commands to send now."""
        rows = self._rows(rows)
        v = np.ascontiguousarray(v, dtype=float).reshape(rows.size, 6)
        v_out = np.empty((rows.size, 6))
        omega = np.empty((rows.size, 3))
        alpha = np.empty((rows.size, 3))
        omega_now = np.empty((rows.size, 3))
        r = self.rfl
        kernels.actuate(rows, self._z_pred, self.z, v, self._Einv_or_zero, self._Einv is not None, self._half_Phi,
                        self._half_G, r.L, r.M0, r.inertia, r.inertia_inv, r.G_inv, r.airframe.gravity_m_s2, self.drag_1_m,
                        MAX_PITCH_RAD, self.thrust_scale, self._adapt_k, self.kappa_limits[0], self.kappa_limits[1],
                        self.wind_estimate_e_m_s, self._wind_gain, WIND_ESTIMATE_FLOOR_M_S, r.airframe.servo_limit_rad,
                        self._servo_step_rad, self.servo_command_rad, self._v_pipe, self._motor_pipe,
                        self._v_applied, v_out, omega, alpha, omega_now, self._G, self._M0_inv)
        return Actuation(omega_now, alpha)

    def hold_tick(self, y: np.ndarray, rows=None, rate_b_rad_s: np.ndarray | None = None,
                  accel_b_m_s2: np.ndarray | None = None) -> None:
        """A control period in which no new command went out (the loop fell behind): take the
        measurement, and record that the actuators kept the last command."""
        rows = self._rows(rows)
        self.observe(y, rows, rate_b_rad_s, accel_b_m_s2)
        last_v = self._v_pipe[-1, rows] if self.lead_ticks else self._v_applied[rows]
        kept = np.empty((rows.size, 3))  # (the rotor speeds: the pipe keeps its last ones)
        kernels.push(rows, last_v, kept, True, self._v_pipe, self._motor_pipe, self._v_applied, kept)
