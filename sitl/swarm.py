"""N simulated flight controllers around one batched plant: the clock, the sensors, the autopilots'
own position controller, and what the actuators receive. No sockets (see ``server.py``).

The autopilots' own controller (modes HOLD, LAND, TAKEOFF and the failsafe) is the math core's
``FormationController`` with every vehicle pinned to its own reference (no neighbours), so the
SITL flies its failsafe with the same code the companions fly formations with.
"""

from __future__ import annotations

import functools
import math
import time

import numpy as np

from triswarm.protocol import model
from triswarm.protocol.agent import no_leader, pinned_input, reference_at
from triswarm.protocol.airframe import TABLE_1, Airframe
from triswarm.protocol.controller import FormationController
from triswarm.protocol.design import DesignWeights, design
from triswarm.protocol.formation import QuinticTransfer
from triswarm.protocol.frames import DEFAULT_HOME, LocalProjection
from triswarm.protocol.graph import Schedule, Topology
from triswarm.protocol.mavlink import CustomMode
from triswarm.protocol.plan import DEFAULT_Q, DEFAULT_Q_BAR, DEFAULT_Q_DISTURBANCE, DEFAULT_R, DEFAULT_R_BAR
from triswarm.protocol.rfl import RFL
from triswarm.protocol.wind import Wind

from .estimator import Estimator, EstimatorProfile
from .fc import FlightController, drain_batteries
from .physics import SENSOR_COLUMNS, Plant, quaternion_from_euler
from .profiles import TRISWARM, Profile
from .telemetry import Snapshot

INTERNAL_MODES = (CustomMode.HOLD, CustomMode.LAND, CustomMode.TAKEOFF)
BATTERY_PERIOD_S = 0.1  # the batteries drain in steps of this much simulated time (the power sampled then)


def ground_grid(n: int, spacing_m: float = 2.5, first_id: int = 1) -> np.ndarray:
    """Resting places on the ground, a few metres apart, in rows, centred on the origin (paper frame).

    With ``first_id`` K > 1 (vehicles K .. K+n-1 of a swarm split over several processes), each
    vehicle rests where it would if one process flew vehicles 1 .. K+n-1: its place follows its id,
    so the vehicles of different processes do not start on top of each other."""
    if first_id < 1:
        raise ValueError(f"the first vehicle id must be at least 1, got {first_id}")
    total = first_id - 1 + n
    cols = max(1, math.ceil(math.sqrt(total)))
    rows = math.ceil(total / cols)
    k = np.arange(first_id - 1, total)
    north = (k // cols - (rows - 1) / 2.0) * spacing_m
    west = ((cols - 1) / 2.0 - k % cols) * spacing_m
    return np.stack([north, west, np.zeros(n)], axis=1)


def autopilot_design(airframe: Airframe):
    """The flight controller's own position controller: the plan defaults, one agent, c = 1."""
    weights = DesignWeights(np.array(DEFAULT_Q), np.array(DEFAULT_R), np.array(DEFAULT_Q_BAR), np.array(DEFAULT_R_BAR),
                            coupling_margin=2.0, Q_disturbance=np.array(DEFAULT_Q_DISTURBANCE))
    solo = Schedule((Topology("solo", np.zeros((1, 1)), np.ones(1)),), 1.0)
    return design(RFL.from_airframe(airframe), solo, weights)


class SitlSwarm:
    def __init__(self, n: int, home: LocalProjection | None = None, airframe: Airframe = TABLE_1,
                 physics_hz: float = 1000.0, control_hz: float = 200.0, spacing_m: float = 2.5, seed: int = 0,
                 boot_unix_s: float | None = None, first_id: int = 1, wind: Wind | None = None,
                 profile: Profile = TRISWARM, estimator: EstimatorProfile | None = None) -> None:
        """estimator: what the flight controllers' estimators report (``sitl.estimator``: lag,
        wandering bias, noise), before their NOISE_* parameters' white noise; None: the truth."""
        if n < 1:
            raise ValueError(f"a swarm needs at least one vehicle, got {n}")
        self.n = n
        self.home = home or LocalProjection(*DEFAULT_HOME)
        self.physics_hz = float(physics_hz)
        dt_s = 1.0 / self.physics_hz
        self.control_every = max(1, int(round(self.physics_hz / control_hz)))
        self.control_dt_s = self.control_every * dt_s
        if not 1 <= first_id <= 256 - n:
            raise ValueError(f"system ids {first_id}..{first_id + n - 1} are not all within 1..255")
        self.start_m = ground_grid(n, spacing_m, first_id)
        self.plant = Plant(airframe, n, dt_s=dt_s, wind=wind, wind_seed=seed)
        self.plant.reset(self.start_m)
        boot = time.time() if boot_unix_s is None else boot_unix_s
        self.profile = profile
        self.fcs = [FlightController(first_id + i, airframe, self.home, self.start_m[i], boot, profile) for i in range(n)]
        self._commanded: set[int] = set()
        """The vehicles whose flight controllers took an actuator command since the last step."""
        for i, fc in enumerate(self.fcs):
            fc.on_command = functools.partial(self._commanded.add, i)
        self.seed = seed
        self.estimator = None if estimator is None else Estimator(estimator, n, np.random.default_rng((seed, 1)))
        self._rows: Snapshot | None = None
        self._rows_step = -1
        self._snapshots: dict[int, Snapshot] = {}
        self._battery_every = max(1, int(round(BATTERY_PERIOD_S / self.control_dt_s)))
        self._control_ticks = 0
        self._noise: tuple = (-1, None)  # (the parameters' version, each vehicle's noise sigmas (N, 4))
        self.omega_cmd = np.zeros((n, 3))
        self.alpha_cmd = np.zeros((n, 3))
        self.inner = FormationController(autopilot_design(airframe), n, 1.0 / self.control_dt_s)
        FormationController.warm_up(self.inner.design, 1.0 / self.control_dt_s)  # not at the first takeoff
        self.inner.reset(self.plant.observe().paper_state())
        self.inner_ref: list[QuinticTransfer | None] = [None] * n
        self._hover_omega = float(model.hover_trim(airframe)[0][0])

    @property
    def dt_s(self) -> float:
        """The physics step [s]."""
        return self.plant.dt_s

    @property
    def steps(self) -> int:
        """Physics steps since boot."""
        return self.plant.steps

    @property
    def time_s(self) -> float:
        """Simulated time since boot [s]."""
        return self.plant.time_s

    # -- sensors ----------------------------------------------------------------------------

    def sensor_rows(self) -> Snapshot:
        """Every vehicle's estimate this step: the plant's state plus each vehicle's noise."""
        if self._rows_step == self.steps:
            return self._rows
        ideal = self.plant.sensors()
        col = {name: ideal[:, c] for name, c in SENSOR_COLUMNS.items()}
        if self.estimator is not None:
            y, col["rate_b_rad_s"], col["velocity_e_m_s"] = self.estimator.report(
                self.time_s, np.concatenate([col["euler_rad"], col["position_m"]], axis=1), col["rate_b_rad_s"],
                col["velocity_e_m_s"])
            col["euler_rad"], col["position_m"] = y[:, 0:3], y[:, 3:6]
            col["specific_force_b"] = self.estimator.accelerometer(col["specific_force_b"])
            col["velocity_b_m_s"] = np.einsum("nji,nj->ni", model.rotation_body_to_earth(col["euler_rad"]), col["velocity_e_m_s"])
            col["quaternion"] = quaternion_from_euler(col["euler_rad"])
        version = sum(fc.params_version for fc in self.fcs)
        if self._noise[0] != version:
            self._noise = (version, np.array([[fc.params["NOISE_POS_M"], fc.params["NOISE_VEL_MS"], fc.params["NOISE_ATT_RAD"],
                                               fc.params["NOISE_GYRO_RADS"], fc.params["NOISE_ACC_MS2"]] for fc in self.fcs]))
        sig = self._noise[1]
        if np.any(sig[:, 4] > 0):  # (a stream of its own: the others' draws are as without it)
            col["specific_force_b"] = col["specific_force_b"] + sig[:, 4, None] * np.random.default_rng(
                (self.seed, self.steps, 1)).standard_normal((self.n, 3))
        sig = sig[:, :4]
        if np.any(sig > 0):  # (drawn per step from the seed: the same whenever a snapshot is taken)
            noise = np.random.default_rng((self.seed, self.steps)).standard_normal((self.n, 4, 3)) * sig[:, :, None]
            col["position_m"] = col["position_m"] + noise[:, 0]
            col["velocity_e_m_s"] = col["velocity_e_m_s"] + noise[:, 1]
            col["velocity_b_m_s"] = col["velocity_b_m_s"] + noise[:, 1]
            col["euler_rad"] = col["euler_rad"] + noise[:, 2]
            col["rate_b_rad_s"] = col["rate_b_rad_s"] + noise[:, 3]
            if np.any(sig[:, 2] > 0):
                col["quaternion"] = quaternion_from_euler(col["euler_rad"])
        self._rows = Snapshot(landed=self.plant.landed.copy(), rho=self.plant.rho.copy(), **col)
        self._rows_step = self.steps
        self._snapshots = {}
        return self._rows

    def snapshot(self, i: int) -> Snapshot:
        rows = self.sensor_rows()
        snap = self._snapshots.get(i)
        if snap is None:
            snap = rows.row(i)
            snap.landed = bool(snap.landed)
            self._snapshots[i] = snap
        return snap

    def apply_airframe(self, i: int) -> None:
        """After a parameter set: the plant of vehicle i takes its flight controller's values."""
        fc = self.fcs[i]
        if fc.airframe_changed:
            self.plant.set_airframe(i, fc.airframe())
            fc.airframe_changed = False

    # -- time -------------------------------------------------------------------------------

    def step(self, n: int = 1) -> None:
        """``n`` physics steps with the commands held (none of them past the next control period's
        start); the flight controllers run at every control period's start. The actuator commands
        taken since the last step (``commanded``) apply from this one."""
        changed = False
        if self.steps % self.control_every == 0:
            self._control_tick()
            changed = True
        for i in range(self.n) if changed else self._commanded:
            fc = self.fcs[i]
            fc.actuators_changed = False
            if fc.armed and fc.mode == CustomMode.EXTERNAL:
                self.omega_cmd[i] = fc.ext_omega
                self.alpha_cmd[i] = fc.ext_alpha
            changed = True
        self._commanded.clear()
        if changed:
            self.plant.command(self.omega_cmd, self.alpha_cmd)
        self.plant.advance(n)

    def steps_to_control(self) -> int:
        """Physics steps from now to the next control period's start (at least 1)."""
        return self.control_every - self.steps % self.control_every

    def _control_tick(self) -> None:
        now = self.time_s
        internal = []
        rows = self.sensor_rows()
        landed = rows.landed.tolist()
        for i, fc in enumerate(self.fcs):
            ref = self.inner_ref[i]
            fc.tick(now, landed[i], internal_done=ref is not None and now >= ref.end_s)
            if fc.mode_changed:
                fc.mode_changed = False
                self._start_manoeuvre(i, fc, self.snapshot(i), now)
            if not fc.armed:
                self.omega_cmd[i] = 0.0
                self.alpha_cmd[i] = 0.0
                self.inner_ref[i] = None
            elif fc.mode in INTERNAL_MODES:
                internal.append(i)
        self._control_ticks += 1
        if self._control_ticks % self._battery_every == 0:
            drain_batteries(self.fcs, rows.rho, self._battery_every * self.control_dt_s)
        if internal:
            self._fly_internal(np.array(internal), now)

    def _start_manoeuvre(self, i: int, fc: FlightController, snap: Snapshot, now: float) -> None:
        """A new internal mode: restart vehicle i's own controller from where it is now."""
        if fc.mode not in INTERNAL_MODES or not fc.armed:
            self.inner_ref[i] = None
            return
        self.inner.reset(snap.paper_state()[None, :], rows=np.array([i]))
        p0, v0 = snap.position_m.copy(), snap.velocity_e_m_s.copy()
        eta0 = snap.euler_rad.copy()
        eta_dot0 = model.euler_rate_matrix(eta0) @ snap.rate_b_rad_s
        level = np.array([0.0, 0.0, eta0[2]])
        if fc.mode == CustomMode.HOLD:
            T = max(2.0, float(np.linalg.norm(v0)) / 2.0)
            p1 = p0 + v0 * T / 2.0
            p1[2] = p0[2] if snap.landed else max(p1[2], 0.5)
        elif fc.mode == CustomMode.LAND:
            height = max(p0[2], 0.0) + 0.3  # aim 0.3 m below the ground so it touches down
            T = max(2.0, 1.875 * height / fc.params["LAND_SPEED_M_S"])
            p1 = np.array([p0[0] + v0[0] * 0.5, p0[1] + v0[1] * 0.5, -0.3])
        else:  # TAKEOFF
            alt = fc.takeoff_alt_m
            T = max(2.0, 1.875 * alt / 1.5)
            p1 = np.array([p0[0], p0[1], alt])
        self.inner_ref[i] = QuinticTransfer(p0, v0, p1, eta0, eta_dot0, level, now, T)

    def _fly_internal(self, rows: np.ndarray, now: float) -> None:
        s = self.sensor_rows()
        y = np.concatenate([s.euler_rad, s.position_m], axis=1)
        xhat = self.inner.observe(y, None, s.rate_b_rad_s)
        h = xhat.copy()  # vehicles not in an internal mode: xi = 0, their commands are not used
        gamma = np.zeros((self.n, 6))
        for i in rows:
            ref = reference_at(self.inner.design, self.inner_ref[i].offsets, no_leader, now, self.inner.lead_s,
                               self.control_dt_s)
            h[i], gamma[i] = ref.h[0], ref.gamma[0]
        v = pinned_input(self.inner.design, xhat - h, np.zeros(12), gamma)
        act = self.inner.actuate(v)
        for i in rows:
            fc = self.fcs[i]
            on_ground_done = s.landed[i] and (fc.mode == CustomMode.LAND or (fc.mode == CustomMode.HOLD and
                                                                               self.inner_ref[i].p1[0, 2] <= 0.0))
            if on_ground_done:
                self.omega_cmd[i] = 0.3 * self._hover_omega  # idle, well below lift-off
                self.alpha_cmd[i] = 0.0
            else:
                self.omega_cmd[i] = act.omega_rad_s[i]
                self.alpha_cmd[i] = act.alpha_rad[i]
