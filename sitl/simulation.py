"""In-process swarm simulation: N plants and N agents in one process, no I/O.

The agents run exactly what a companion runs (``FormationController`` and ``protocol_input`` of
``triswarm.protocol``), over a leading agent axis; only the neighbour sum is formed here as
``adjacency @ xi`` instead of from estimates received over Zenoh.
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse

from triswarm.protocol.agent import protocol_input, reference_at
from triswarm.protocol.airframe import RPM_TO_RAD_S, Airframe
from triswarm.protocol.controller import FormationController
from triswarm.protocol.plan import MAX_LATENCY_S, Plan
from triswarm.protocol.wind import Wind

from .estimator import Estimator, EstimatorProfile
from .physics import RATE_B, SENSOR_COLUMNS, Plant


MAX_DISTANCE_M = 1e4
"""A drone farther than this from the origin (in any axis) has diverged: the run stops."""


@dataclass(frozen=True)
class SensorNoise:
    """Zero-mean Gaussian noise on what the controller measures (standard deviations), drawn anew
    at every control tick."""

    position_m: float = 0.02
    attitude_rad: float = 0.005
    gyro_rad_s: float = 0.01
    """Per body axis: a MEMS gyro's noise at 200 Hz."""
    accel_m_s2: float = 0.1
    """Per body axis: an accelerometer's noise at 200 Hz, the airframe's vibration in it."""


@dataclass(frozen=True)
class SimConfig:
    duration_s: float = 50.0
    physics_hz: float = 1000.0
    log_hz: float = 50.0
    servo_delay_s: float | None = None
    """Plant servo delay; None keeps the plan airframe's. The controller keeps the plan's value."""
    max_rpm: float | None = None
    """Plant motor limit; None keeps the plan airframe's."""
    servo_rate_deg_s: float | None = None
    """Plant servo speed [deg/s] (0: at once); None keeps the plan airframe's."""
    controller_delay_s: float | None = None
    """Servo delay the controller compensates; None: the plan airframe's (0 switches it off)."""
    noise: SensorNoise | None = None
    measured_rates: bool = False
    """The controller takes the body rates the gyro measures as three more outputs of its observer;
    False (the default, docs/control-design.md): the observer alone estimates them."""
    mismatch_pct: float = 0.0
    """Plant mass and inertias (1 + pct/100) times, k_f (1 - pct/200) times the controller's."""
    seed: int = 0
    start_position_m: np.ndarray | None = None
    """(N, 3) start positions; default: resting on the ground within 3 m of the origin."""
    estimator: EstimatorProfile | None = None
    """What the controllers measure, as an autopilot's estimator reports it (``sitl.estimator``: lag,
    wandering bias, noise); None: the truth (with ``noise``'s white noise if set; not both)."""
    wind: Wind | None = None
    """The air the plant flies in (its turbulence seeded by ``seed``); None: the plan's ``[wind]``,
    and no air at all (the paper's model) when the plan has none."""
    latency_s: float | None = None
    """How long after a measurement's stamp the command that answers it reaches the plant [s]
    (whole physics steps); None: the plan's ``[controller] latency_s``, which its controllers
    compensate."""

    def __post_init__(self) -> None:
        for name in ("duration_s", "physics_hz", "log_hz"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name.replace('_', ' ')} must be a positive number, got {value!r}")
        if self.servo_delay_s is not None and not (math.isfinite(self.servo_delay_s) and self.servo_delay_s >= 0):
            raise ValueError(f"servo delay must be a non-negative number of seconds, got {self.servo_delay_s!r}")
        if self.max_rpm is not None and not (math.isfinite(self.max_rpm) and self.max_rpm > 0):
            raise ValueError(f"max rpm must be a positive number, got {self.max_rpm!r}")
        if self.servo_rate_deg_s is not None and not (math.isfinite(self.servo_rate_deg_s) and self.servo_rate_deg_s >= 0):
            raise ValueError(f"servo rate must be a non-negative number of degrees a second, got {self.servo_rate_deg_s!r}")
        if not (math.isfinite(self.mismatch_pct) and -50.0 < self.mismatch_pct < 100.0):
            raise ValueError(f"mismatch must be a percentage between -50 and 100, got {self.mismatch_pct!r}")
        if self.latency_s is not None and not (math.isfinite(self.latency_s) and 0 <= self.latency_s <= MAX_LATENCY_S):
            raise ValueError(f"latency must be between 0 and {MAX_LATENCY_S:g} s, got {self.latency_s!r}")
        if self.noise is not None and self.estimator is not None:
            raise ValueError("sensor noise and an estimator profile are two ways of saying what is measured: give one")


@dataclass
class SimResult:
    plan: Plan
    config: SimConfig
    plant_airframe: Airframe
    t_s: np.ndarray            # (T,)
    position_m: np.ndarray     # (T, N, 3) earth frame, z up
    euler_rad: np.ndarray      # (T, N, 3) roll, pitch, yaw
    omega_rad_s: np.ndarray    # (T, N, 3) rotor speeds applied
    alpha_rad: np.ndarray      # (T, N, 3) servo angles applied
    start_position_m: np.ndarray
    wall_s: float = 0.0
    diverged_at_s: float | None = None
    diverged_drone: int | None = None
    """The first drone (numbered from 1) whose state left the valid range, when one did."""
    thrust_scale: np.ndarray = field(default_factory=lambda: np.zeros(0))
    wind_estimate_e_m_s: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """The wind each drone's controller had estimated at the end, earth frame [m/s] (N, 3)."""


def default_start_positions(n: int, seed: int = 0, radius_m: float = 3.0) -> np.ndarray:
    """Drones resting on the ground in a sunflower pattern (even spacing), rotated and jittered by
    the seed, all within ``radius_m`` of the origin for up to about 30 drones (wider beyond)."""
    rng = np.random.default_rng(seed)
    outer = max(radius_m - 0.5, 0.45 * math.sqrt(n))
    k = np.arange(n) + 0.5
    r = outer * np.sqrt(k / n)
    ang = k * math.pi * (3.0 - math.sqrt(5.0)) + rng.uniform(0, 2 * math.pi)
    pos = np.stack([r * np.cos(ang), r * np.sin(ang), np.zeros(n)], axis=1)
    pos[:, :2] += rng.uniform(-0.2, 0.2, size=(n, 2))
    return pos


def plant_airframe(plan: Plan, config: SimConfig) -> Airframe:
    af = plan.airframe
    if config.mismatch_pct:
        af = af.with_mismatch(1.0 + config.mismatch_pct / 100.0, 1.0 - config.mismatch_pct / 200.0)
    changes = {}
    if config.servo_delay_s is not None:
        changes["servo_delay_s"] = config.servo_delay_s
    if config.max_rpm is not None:
        changes["max_rotor_speed_rad_s"] = config.max_rpm * RPM_TO_RAD_S
    if config.servo_rate_deg_s is not None:
        changes["servo_rate_rad_s"] = math.radians(config.servo_rate_deg_s)
    return af.replace(**changes) if changes else af


def flown_wind(plan: Plan, config: SimConfig) -> Wind | None:
    """The wind a simulation flies in: the config's, else the plan's."""
    return config.wind if config.wind is not None else plan.wind


def command_latency_s(plan: Plan, config: SimConfig) -> float:
    """How late [s] after a measurement's stamp a simulation's commands reach the plant: the
    config's latency, else the plan's."""
    return plan.controller.latency_s if config.latency_s is None else config.latency_s


def simulate(plan: Plan, config: SimConfig, progress: Callable[[float], None] | None = None) -> SimResult:
    """Fly the plan from rest on the ground for ``config.duration_s``."""
    design = plan.check_formation(horizon_s=config.duration_s)
    n = plan.n_agents
    rate = plan.controller.rate_hz
    sub = int(round(config.physics_hz / rate))
    if sub < 1 or abs(sub * rate - config.physics_hz) > 1e-6 * config.physics_hz:
        raise ValueError(f"physics rate {config.physics_hz:g} Hz must be a whole multiple of the control rate {rate:g} Hz")
    dt = 1.0 / rate
    start = default_start_positions(n, config.seed) if config.start_position_m is None else \
        np.asarray(config.start_position_m, dtype=float).reshape(n, 3)
    rng = np.random.default_rng(config.seed + 1)

    af_plant = plant_airframe(plan, config)
    wind = flown_wind(plan, config)
    plant = Plant(af_plant, n, dt_s=1.0 / config.physics_hz, wind=wind, wind_seed=config.seed)
    ctrl = FormationController.for_plan(plan, n, rate, wind, delay_s=config.controller_delay_s,
                                       measured_rates=config.measured_rates)
    plant.reset(start)
    x0 = plant.observe().paper_state()
    estimator = None if config.estimator is None else Estimator(config.estimator, n, np.random.default_rng(config.seed + 2))
    if estimator is not None:  # (a companion starts from what its flight controller says, as the entry does)
        x0[:, 6:12] = estimator.report(0.0, plant.output(), x0[:, 3:6])[0]
    ctrl.reset(x0)
    plant.reset(start, servo_rad=ctrl.initial_actuation.alpha_rad)
    offsets = plan.entry_formation(x0[:, 9:12], 0.0)
    adjacency = {t.name: scipy.sparse.csr_matrix(t.adjacency) for t in plan.schedule.topologies}

    steps = int(round(config.duration_s * rate))
    log_every = max(1, int(round(rate / config.log_hz)))
    n_log = steps // log_every + 1
    t_log = np.zeros(n_log)
    pos_log = np.zeros((n_log, n, 3))
    eta_log = np.zeros((n_log, n, 3))
    omega_log = np.zeros((n_log, n, 3))
    alpha_log = np.zeros((n_log, n, 3))
    row = 0
    diverged = diverged_drone = None
    wall0 = time.perf_counter()
    lead = ctrl.lead_s
    latency_steps = int(round(command_latency_s(plan, config) * config.physics_hz))
    pending: collections.deque = collections.deque()  # (physics step due, rotor speeds, servo angles)
    for k in range(steps + 1):
        t = k * dt
        y = plant.output()
        if k % log_every == 0 and row < n_log:
            t_log[row] = t
            pos_log[row] = y[:, 3:6]
            eta_log[row] = y[:, 0:3]
            w2 = np.hypot(plant.rho[:, 0:3], plant.rho[:, 3:6])
            omega_log[row] = np.sqrt(w2)
            alpha_log[row] = np.arctan2(plant.rho[:, 0:3], plant.rho[:, 3:6])
            row += 1
            if progress is not None:
                progress(t)
        if k == steps:
            break
        if not (np.all(np.isfinite(plant.state)) and np.abs(y[:, 3:6]).max() < MAX_DISTANCE_M):
            diverged = t
            bad = ~np.isfinite(plant.state).all(axis=1) | ~(np.abs(y[:, 3:6]).max(axis=1) < MAX_DISTANCE_M)
            diverged_drone = int(np.flatnonzero(bad)[0]) + 1
            break
        rates = plant.state[:, RATE_B].copy()
        accel = plant.sensors()[:, SENSOR_COLUMNS["specific_force_b"]] if ctrl.measured_accel else None
        if estimator is not None:
            y, rates, _ = estimator.report(t, y, rates)
            if accel is not None:
                accel = estimator.accelerometer(accel)
        if config.noise is not None:
            y[:, 0:3] += rng.normal(0.0, config.noise.attitude_rad, (n, 3))
            y[:, 3:6] += rng.normal(0.0, config.noise.position_m, (n, 3))
            rates += rng.normal(0.0, config.noise.gyro_rad_s, (n, 3))
            if accel is not None:
                accel += rng.normal(0.0, config.noise.accel_m_s2, (n, 3))
        # One tick of every agent, as a companion runs it (estimates refer to t + lead).
        xhat = ctrl.observe(y, None, rates, accel)
        ref = reference_at(design, offsets.offsets, plan.leader_state, t, lead, dt)
        xi = xhat - ref.h
        topo = plan.schedule.at(ref.t_p)
        v = protocol_input(design, xi, adjacency[topo.name] @ xi, topo.in_degree, topo.pinning, ref.x0, ref.gamma)
        act = ctrl.actuate(v)
        pending.append((k * sub + latency_steps, act.omega_rad_s, act.alpha_rad))
        step, end = k * sub, (k + 1) * sub
        while step < end:  # the plant, with each command taken when due
            while pending and pending[0][0] <= step:
                plant.command(*pending.popleft()[1:])
            due = min(end, pending[0][0]) if pending else end
            plant.advance(due - step)
            step = due
    wall = time.perf_counter() - wall0
    return SimResult(plan, config, af_plant, t_log[:row], pos_log[:row], eta_log[:row], omega_log[:row],
                     alpha_log[:row], start, wall, diverged, diverged_drone, ctrl.thrust_scale.copy(),
                     ctrl.wind_estimate_e_m_s.copy())


def delay_margin(plan: Plan, config: SimConfig, assess_run: Callable[[SimResult], bool],
                 lo_s: float | None = None, hi_s: float = 0.05, resolution_s: float = 0.001) -> float:
    """The largest plant servo delay in [lo_s, hi_s] for which ``assess_run`` still accepts the
    run, by bisection (the controller keeps compensating the plan's delay). Assumes acceptance is
    monotone in the delay above the nominal one; returns lo_s - resolution_s if lo_s already fails."""
    import dataclasses

    lo = plan.airframe.servo_delay_s if lo_s is None else lo_s
    if not assess_run(simulate(plan, dataclasses.replace(config, servo_delay_s=lo))):
        return lo - resolution_s
    hi = hi_s
    if assess_run(simulate(plan, dataclasses.replace(config, servo_delay_s=hi))):
        return hi
    while hi - lo > resolution_s:
        mid = 0.5 * (lo + hi)
        if assess_run(simulate(plan, dataclasses.replace(config, servo_delay_s=mid))):
            lo = mid
        else:
            hi = mid
    return lo
