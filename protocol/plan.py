"""A formation plan: who flies, where, over which graphs, with which design weights.

Built from a plain dict (what ``tomllib`` gives for a plan file, see ``spec_from_toml``). Every
mistake a user can make raises ``PlanError`` with one sentence naming the source,
the field and, where it applies, the drone (numbered from 1).

Schema (all sections but ``formation`` optional; units in the field names):

    name = "paper-hexagon"
    drones = 6
    duration_s = 60   # the plan's length: what plan check checks and flies (default below)
    [airframe]        # the controller's nominal airframe; fields of Airframe, default Table 1
    [leader]          position_m = [x, y, z], attitude_rad = [roll, pitch, yaw]
    [formation]       type = "rotating-polygon" | "constant" | "keyframes", see _formation()
    [entry]           climb_m, climb_s, blend_s: take-off and formation-entry shaping
    [topology]        switch_period_s, and families = [...] or [[topology.graphs]] with
                      name, pinned = [agents], edges = [[from, to], ...] (agents from 1, 0 = leader)
    [design]          Q_diag (12), R_diag (6), Q_bar_diag (12), R_bar_diag (6), coupling_margin,
                      Q_disturbance_diag (6; zeros switch disturbance estimation off), R_bar_accel_diag (3)
    [controller]      rate_hz, thrust_adaptation_rate_1_s, wind_estimate_rate_1_s, air_density_kg_m3 (drag cancelled),
                      accelerometer (the observer takes the flight controller's specific force; default: in air), latency_s
    [check]           min_separation_m, position_bound_m, attitude_bound_rad, settle_s, rotor_speed_margin_pct,
                      tilt_margin_deg, turbulence_sigmas (CheckSettings)
    [wind]            the air a simulation flies the plan in (``wind.wind_from_table``), not the controller's"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from . import graph as graph_mod
from .air_margin import (DEFAULT_ROTOR_SPEED_MARGIN_PCT, DEFAULT_TILT_MARGIN_DEG, DEFAULT_TURBULENCE_SIGMAS,
                         ActuatorDemand, actuator_demand, demand_in_air, describe_design_air, margin_problem)
from .airframe import Airframe, ParameterError, finite_number
from .certificate import Certificate, LoopMatrices, certify
from .design import DEFAULT_R_BAR_ACCEL, Design, DesignWeights, FormationError, check_feasibility, design
from .errors import PlanError
from .formation import (Blend, ConstantFormation, EntryBlend, Formation, KeyframeFormation, RawOffsets,
                        RotatingPolygon, paper_attitudes)
from .graph import GraphError, Schedule, Topology
from .rfl import RFL
from .separation import Approach, closest_approach
from .sizing import SizingError, resized_spec
from .wind import Wind, wind_from_table


MAX_DRONES = 1000
"""The largest swarm a plan may name (the largest measured, docs/benchmarks.md): a plan's graphs
are N x N, so a plan file naming 50,000 drones would otherwise take gigabytes to read."""


DEFAULT_Q = (1.0,) * 6 + (1e4,) * 3 + (1e3,) * 3
DEFAULT_R = (1e-6,) * 6
DEFAULT_Q_BAR = (1.0,) * 6 + (1e-4,) * 6
DEFAULT_R_BAR = (0.005**2,) * 3 + (0.02**2,) * 3
DEFAULT_Q_DISTURBANCE = (100.0,) * 3 + (1000.0,) * 3
DEFAULT_COUPLING_MARGIN = 2.25
"""c = 2.25 / (2 lambda_R), measured (docs/formations.md): the certificate vouches for the case study
(its switching needs 2.5 s between switches; it switches every 5 s) and for the ring trees at any N,
which margin 1 cannot; the case study keeps its bounds with noise, mismatch and servo delays up to
20 ms; and a 100 Hz controller still flies it (from a margin of 2.5, where c |lambda| of the
triangles graph reaches 6.2, it does not)."""
DEFAULT_DURATION_S = 60.0
MIN_SETTLED_WINDOW_S = 20.0
"""A plan that gives no duration_s lasts 60 s, or longer (whole seconds) so that its settled window
lasts this long."""
MAX_LATENCY_S = 1.0  # the most [controller] latency_s (and a simulation's latency) may be [s]
SEPARATION_ARM_LENGTHS = 8.0
"""Default minimum separation: 8 arm lengths (1.84 m for Table 1's 0.23 m arm), four times the span
between rotor axes: room for the rotor discs, their downwash and the tracking error."""


@dataclass(frozen=True)
class EntrySettings:
    """Take-off and formation entry (reference shaping), from wherever each drone starts."""

    climb_m: float = 3.0
    """Height of the vertical climb, at level attitude, before the formation is blended in."""
    climb_s: float = 3.0
    """Duration of that climb (quintic, rest to rest)."""
    blend_s: float = 12.0
    """Duration of the quintic blend from the climbed position into the formation."""


@dataclass(frozen=True)
class CheckSettings:
    """What ``plan check`` holds the plan to (besides Algorithm 1's conditions)."""

    min_separation_m: float
    """No two drones closer than this along the reference x0 + h_i(t) [m]."""
    position_bound_m: float = 0.10
    """Flown in simulation, every drone within this of its reference over the settled window [m]."""
    attitude_bound_rad: float = 0.02
    """... and within this in roll, pitch and yaw [rad]."""
    settle_s: float = 10.0
    """The settled window starts this long after the entry (climb and blend) ends [s]."""
    rotor_speed_margin_pct: float = DEFAULT_ROTOR_SPEED_MARGIN_PCT
    """In the design air every rotor stays this far below the motor limit [% of it] (``air_margin``)."""
    tilt_margin_deg: float = DEFAULT_TILT_MARGIN_DEG
    """... and every servo this far inside its range [deg]."""
    turbulence_sigmas: float = DEFAULT_TURBULENCE_SIGMAS
    """The design air's turbulence: this many times the [wind] turbulence's intensities."""


@dataclass(frozen=True)
class ControllerSettings:
    rate_hz: float = 200.0
    """Control loop rate."""
    thrust_adaptation_rate_1_s: float = 3.0
    """Adaptation rate of the thrust-effectiveness estimate (0 switches it off)."""
    air_density_kg_m3: float | None = None
    """Density of the air the controllers assume [kg/m^3]: the RFL cancels the body's drag
    1/2 rho C_d A |v| v with it (C_d and A the airframe's). None: the density of the air the plan is
    flown in (ISA sea level, 1.225, unless [wind] says otherwise), and 0 (no drag term: the paper's
    law) when it is flown in no air (``Plan.controller_air_density_kg_m3``)."""
    wind_estimate_rate_1_s: float = 1.0
    """Rate [1/s] of the controllers' horizontal wind estimate, in air (0: drag cancelled as in still air)."""
    accelerometer: bool | None = None
    """The observer takes the specific force the accelerometer measures (``FormationController``
    ``measured_accel``). None: in air, not in no air (``Plan.controller_accelerometer``)."""
    latency_s: float = 0.0
    """From a measurement's stamp to its command taken [s] (at most MAX_LATENCY_S): predicted over."""


@dataclass(frozen=True)
class Plan:
    name: str
    n_agents: int
    airframe: Airframe
    leader: Formation
    """The leader's reference x0(t) as a one-agent formation (position and attitude)."""
    formation: Formation
    entry: EntrySettings
    schedule: Schedule
    weights: DesignWeights
    controller: ControllerSettings
    check_settings: CheckSettings
    duration_s: float
    """The plan's length: checked and flown over [0, duration_s]."""
    source: str = "plan"
    spec: dict = field(default_factory=dict, compare=False, repr=False)
    """The dict the plan was built from (to rebuild it for another number of drones)."""
    wind: Wind | None = None
    """The air a simulation of the plan flies in; None: no air (the paper's model)."""

    @cached_property
    def rfl(self) -> RFL:
        return RFL.from_airframe(self.airframe)

    @cached_property
    def design(self) -> Design:
        try:
            return design(self.rfl, self.schedule, self.weights)
        except (GraphError, ParameterError) as exc:
            raise PlanError(f"{self.source}: {exc}") from None

    @cached_property
    def certificate(self) -> Certificate:
        """The bound on the formation error of the nominal loop under the plan's switching
        (``certificate``), with the design's c."""
        d = self.design
        loop = LoopMatrices(d.A_r, d.B_r, self.weights.Q, self.weights.R, d.P)
        topologies = self.schedule.topologies
        return certify(loop, d.c, [t.L_plus_G for t in topologies], self.schedule.period_s,
                       [t.name for t in topologies])

    @property
    def entry_end_s(self) -> float:
        return self.entry.climb_s + self.entry.blend_s

    @property
    def settled_from_s(self) -> float:
        """Start of the settled window over which a flight is judged: the entry's end plus settle_s."""
        return self.entry_end_s + self.check_settings.settle_s

    def controller_air_density_kg_m3(self, wind: Wind | None) -> float:
        """The air density [kg/m^3] with which the controllers cancel the body's drag when the plan
        is flown in ``wind`` (a simulation's: the plan's [wind] or the one given on the command line;
        a companion's: the plan's [wind]); None is no air at all. [controller] air_density_kg_m3
        when the plan gives it; else the wind's air density in air (still air included; ISA sea
        level unless [wind] says otherwise) and 0 in no air, where the controllers fly the paper's
        law to the bit."""
        if self.controller.air_density_kg_m3 is not None:
            return self.controller.air_density_kg_m3
        return 0.0 if wind is None else wind.air_density_kg_m3

    def controller_accelerometer(self, wind: Wind | None) -> bool:
        """Whether the controllers take the accelerometer in ``wind``: [controller] accelerometer if
        given; else in air (still air too), not in no air (the paper's law to the bit)."""
        if self.controller.accelerometer is not None:
            return self.controller.accelerometer
        return wind is not None

    def leader_state(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """x0(t) and its derivative, (12,) each."""
        h, h_dot = self.leader.offsets(t_s)
        return h[0], h_dot[0]

    def reference(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """x0(t) + h_i(t) and derivative, (N, 12): where each drone should be (x_r coordinates)."""
        x0, x0_dot = self.leader_state(t_s)
        h, h_dot = self.formation.offsets(t_s)
        return x0 + h, x0_dot + h_dot

    def check(self, horizon_s: float | None = None, step_s: float = 0.1) -> Design:
        """Everything but the flight over [0, horizon_s] (default: the plan's duration):
        ``check_formation``, then ``safety_problems``. Returns the design."""
        d = self.check_formation(horizon_s, step_s)
        problems = self.safety_problems(horizon_s, step_s)
        if problems:
            raise PlanError(f"{self.source}: {problems[0]}")
        return d

    def safety_problems(self, horizon_s: float | None = None, step_s: float = 0.1) -> list[str]:
        """What the formation law and the airframe allow but would still end badly, one sentence
        each: a switching schedule the certificate cannot vouch for, a drone that keeps less than
        check's margins of its motor limit or servo range in the plan's design air
        (``margin_problem``), drones closer than check.min_separation_m along the reference."""
        problems = [schedule_problem(self), self.margin_problem(horizon_s, step_s)]
        approach = self.closest_approach(horizon_s, step_s)
        sep = self.check_settings.min_separation_m
        if approach is not None and approach.distance_m < sep:
            i, j = approach.pair
            problems.append(f"drones {i + 1} and {j + 1} come within {approach.distance_m:.2f} m of each other at "
                            f"t = {approach.t_s:.4g} s along the reference, closer than the minimum separation "
                            f"{sep:g} m (check.min_separation_m)")
        return [p for p in problems if p is not None]

    def margin_problem(self, horizon_s: float | None = None, step_s: float = 0.1) -> str | None:
        """Why the airframe cannot hold the formation in the plan's design air with check's margins
        left for the feedback (one sentence, ``air_margin.margin_problem``), or None."""
        times = np.arange(0.0, (self.duration_s if horizon_s is None else horizon_s) + 1e-9, step_s)
        c = self.check_settings
        demand = self.design_demand(times)
        if margin_problem(demand, self.airframe, c.rotor_speed_margin_pct, c.tilt_margin_deg, "") is None:
            return None
        calm = None if self.wind is None else actuator_demand(self.rfl, self.leader, self.formation, times,
                                                               self.wind.air_density_kg_m3, np.zeros((1, 3)))
        return margin_problem(demand, self.airframe, c.rotor_speed_margin_pct, c.tilt_margin_deg,
                              describe_design_air(self.wind, c.turbulence_sigmas), calm)

    def design_demand(self, times_s: np.ndarray) -> ActuatorDemand:
        """``actuator_demand`` in the plan's design air: its [wind] with check.turbulence_sigmas of
        its turbulence (``air_margin.demand_in_air``); in no air when it has no [wind]."""
        return demand_in_air(self.rfl, self.leader, self.formation, times_s, self.wind,
                             self.check_settings.turbulence_sigmas)

    def closest_approach(self, horizon_s: float | None = None, step_s: float = 0.1) -> Approach | None:
        """The closest two drones come along x0 + h_i(t) over [0, horizon_s] (``separation``)."""
        horizon_s = self.duration_s if horizon_s is None else horizon_s
        times = np.arange(0.0, horizon_s + 1e-9, step_s)
        refs = {float(t): self.reference(float(t)) for t in times}
        speed = max(float(np.linalg.norm(x[:, 0:3], axis=1).max()) for x, _ in refs.values())
        accel = max(float(np.linalg.norm(x_dot[:, 0:3], axis=1).max()) for _, x_dot in refs.values())
        bound = speed + accel * step_s  # the speed may peak between samples
        return closest_approach(lambda t: (refs[t][0][:, 9:12], refs[t][0][:, 0:3]), times, bound,
                                self.check_settings.min_separation_m)

    def check_formation(self, horizon_s: float | None = None, step_s: float = 0.1) -> Design:
        """Algorithm 1's checks: (76) for every drone over the horizon, Assumption 1 for every
        topology, (91) and the Hurwitz conditions (77), and (77)'s loops sampled at the control rate
        (``Design.sampled_loop``); then that the formation asks no more of the airframe than its
        motors and servos give (``actuator_demand``). Returns the design."""
        horizon_s = self.duration_s if horizon_s is None else horizon_s
        d = self.design
        problem = d.sampled_loop(self.controller.rate_hz).problem()
        if problem is not None:
            raise PlanError(f"{self.source}: {problem}")
        times = np.arange(0.0, horizon_s + 1e-9, step_s)
        try:
            check_feasibility(d.A_r, d.B_bar, self.formation, times, source=f"{self.source}: formation")
        except FormationError as exc:
            raise PlanError(str(exc)) from None
        problem = self.actuator_demand(times).problem(self.airframe)
        if problem is not None:
            raise PlanError(f"{self.source}: formation cannot be flown: {problem}")
        return d

    def actuator_demand(self, times_s: np.ndarray) -> "ActuatorDemand":
        """What flying the plan's formation exactly asks of each drone's rotors at the given plan
        times (``actuator_demand``). The entry and the rejoins are shaped by the companion and not
        included."""
        return actuator_demand(self.rfl, self.leader, self.formation, times_s)

    def entry_formation(self, start_position_m: np.ndarray, t0_s: float = 0.0, target: Formation | None = None) -> Formation:
        """The formation as flown from rest at ``start_position_m`` (N, 3, earth frame) from t0
        (or one agent's part of it: its start (1, 3) and its ``Row`` of the formation as ``target``):
        climb ``entry.climb_m`` at level attitude, then blend into ``target`` (default: the plan's
        formation). Offsets are
        relative to the leader's position at t0 (the leader is static during entry in every plan)."""
        x0, _ = self.leader_state(t0_s)
        start_offset = np.asarray(start_position_m, dtype=float) - x0[9:12]
        lifted = start_offset + np.array([0.0, 0.0, self.entry.climb_m])
        level = np.zeros_like(start_offset)
        climb = EntryBlend(ConstantFormation(lifted, level), start_offset, level, t0_s, self.entry.climb_s)
        return Blend(climb, target or self.formation, t0_s + self.entry.climb_s, self.entry.blend_s)

    def with_agents(self, n_agents: int) -> "Plan":
        """The same plan for another number of drones, sized so that neighbours keep their
        separation (``sizing.resized_spec``)."""
        try:
            spec = resized_spec(self.spec, n_agents, self.check_settings.min_separation_m, self.entry.blend_s)
        except SizingError as exc:
            raise PlanError(f"{self.source}: {exc}") from None
        return plan_from_dict(spec, self.source)


def schedule_problem(plan: Plan) -> str | None:
    """Why the certificate cannot vouch for the plan's switching (one sentence), or None."""
    cert = plan.certificate
    if cert.certified:
        return None
    names = plan.schedule.topologies
    what = (f"switching every {cert.period_s:g} s between {', '.join(t.name for t in names)}" if len(names) > 1
            else f"topology {names[0].name}")
    growth = math.exp(0.5 * min(cert.log_growth_per_cycle, 1400.0))
    dwell = (f"this bound needs at least {cert.min_dwell_s:.3g} s between switches" if math.isfinite(cert.min_dwell_s)
             else f"no switching period makes this bound decay with coupling margin {plan.weights.coupling_margin:g}")
    hint = (f"or use the {', '.join(graph_mod.RING_FAMILIES)} families, certified for any switching at any N"
            if any(t.name not in graph_mod.RING_FAMILIES for t in names) else "or raise design.coupling_margin")
    return (f"topology schedule cannot be certified: {what} lets the bound on the formation error grow "
            f"{growth:.3g}x per cycle; {dwell} ({hint})")


# -- parsing -----------------------------------------------------------------------------------


class _Fields:
    """Reads one section of the plan dict, remembering which keys were used."""

    def __init__(self, source: str, section: str, data) -> None:
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise PlanError(f"{source}: [{section}] must be a table")
        self.source, self.section, self.data, self.used = source, section, data, set()

    def where(self, key: str) -> str:
        return f"{self.source}: {self.section + '.' if self.section else ''}{key}"

    def get(self, key: str, default=None):
        self.used.add(key)
        return self.data.get(key, default)

    def number(self, key: str, default: float | None = None, *, positive: bool = False,
               non_negative: bool = False) -> float:
        value = self.get(key, default)
        if value is None:
            raise PlanError(f"{self.where(key)} is required")
        try:
            return finite_number(self.where(key), value, positive=positive, non_negative=non_negative)
        except ParameterError as exc:
            raise PlanError(str(exc)) from None

    def flag(self, key: str, default: bool | None = None) -> bool | None:
        value = self.get(key, default)
        if value is not default and not isinstance(value, bool):
            raise PlanError(f"{self.where(key)} must be true or false, got {value!r}")
        return value

    def array(self, key: str, shape: tuple[int, ...], default=None, *, per_drone: int | None = None) -> np.ndarray:
        """A finite array of the given shape; with per_drone = N, a single row is repeated for every drone."""
        value = self.get(key, default)
        if value is None:
            raise PlanError(f"{self.where(key)} is required")
        try:
            arr = np.array(value, dtype=float)
        except (TypeError, ValueError):
            i = _bad_row(value, shape[1:]) if per_drone is not None and isinstance(value, list) else None
            if i is not None:
                raise PlanError(f"{self.where(key)}: drone {i + 1} must have {shape[-1]} numbers, got {value[i]!r}") from None
            raise PlanError(f"{self.where(key)} must be numbers, got {value!r}") from None
        if per_drone is not None and arr.shape == shape[1:]:
            arr = np.tile(arr, (per_drone,) + (1,) * len(shape[1:]))
        if arr.shape != shape:
            what = "one entry per drone, each " if per_drone is not None else ""
            raise PlanError(f"{self.where(key)} must have shape {shape} ({what}{shape[-1]} numbers), got {arr.shape}")
        bad = np.argwhere(~np.isfinite(arr))
        if bad.size:
            at = f" (drone {bad[0][0] + 1})" if per_drone is not None else ""
            raise PlanError(f"{self.where(key)} must be finite numbers{at}")
        return arr

    def done(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            raise PlanError(f"{self.where(unknown[0])} is not a known field")


def _bad_row(rows: list, row_shape: tuple[int, ...]) -> int | None:
    """Index of the first entry of a per-drone list that is not numbers of ``row_shape``."""
    for i, row in enumerate(rows):
        try:
            if np.array(row, dtype=float).shape != row_shape:
                return i
        except (TypeError, ValueError):
            return i
    return None


def _airframe(f: _Fields) -> Airframe:
    values = {}
    for fld in dataclasses.fields(Airframe):
        if fld.name in f.data:
            values[fld.name] = f.number(fld.name)
    f.done()
    try:
        return Airframe(**values)
    except ParameterError as exc:
        raise PlanError(f"{f.source}: [airframe] {exc}") from None


def _attitudes(f: _Fields, n: int) -> np.ndarray:
    value = f.get("attitude_rad", [0.0, 0.0, 0.0])
    if value == "paper-alternating":
        return paper_attitudes(n)
    return f.array("attitude_rad", (n, 3), [0.0, 0.0, 0.0], per_drone=n)


def _formation(f: _Fields, n: int) -> Formation:
    kind = f.get("type")
    if kind is None:
        raise PlanError(f"{f.where('type')} is required: \"rotating-polygon\", \"constant\" or \"keyframes\"")
    try:
        if kind == "rotating-polygon":
            out = RotatingPolygon(n, f.number("radius_m", non_negative=True), f.number("altitude_m"),
                                  f.number("rate_rad_s"), _attitudes(f, n), f.number("phase0_rad", 0.0))
        elif kind == "constant":
            if "offsets" in f.data:
                # Raw offsets in the paper's x_r order [lambda_dot, eta_dot, eta, lambda], held
                # constant: feasible only if the velocity and rate rows are zero (checked by (76)).
                h = f.array("offsets", (n, 12), per_drone=n)
                out = RawOffsets(n, lambda t, h=h: h, lambda t, h=h: np.zeros_like(h))
            else:
                out = ConstantFormation(f.array("position_m", (n, 3), per_drone=n), _attitudes(f, n))
        elif kind == "keyframes":
            frames = f.get("keyframes")
            if not isinstance(frames, list) or len(frames) < 2:
                raise PlanError(f"{f.where('keyframes')} must list at least two keyframes")
            times, pos, att = [], [], []
            for k, frame in enumerate(frames):
                kf = _Fields(f.source, f"{f.section}.keyframes[{k}]", frame)
                times.append(kf.number("t_s"))
                if k and times[-1] <= times[-2]:
                    raise PlanError(f"{kf.where('t_s')} must be later than the keyframe before it ({times[-2]:g} s), "
                                    f"got {times[-1]:g} s")
                pos.append(kf.array("position_m", (n, 3), per_drone=n))
                att.append(_attitudes(kf, n))
                kf.done()
            out = KeyframeFormation(np.array(times), np.array(pos), np.array(att))
        else:
            raise PlanError(f"{f.where('type')} must be \"rotating-polygon\", \"constant\" or \"keyframes\", got {kind!r}")
    except ParameterError as exc:
        raise PlanError(f"{f.source}: [formation] {exc}") from None
    f.done()
    return out


def _schedule(f: _Fields, n: int) -> Schedule:
    period = f.number("switch_period_s", 5.0, positive=True)
    families = f.get("families")
    graphs = f.get("graphs")
    topologies: list[Topology] = []
    try:
        if graphs is not None:
            if families is not None:
                raise PlanError(f"{f.where('graphs')}: give either families or graphs, not both")
            if not isinstance(graphs, list) or not graphs:
                raise PlanError(f"{f.where('graphs')} must list at least one graph")
            for k, g in enumerate(graphs):
                gf = _Fields(f.source, f"{f.section}.graphs[{k}]", g)
                name = str(gf.get("name", f"graph-{k + 1}"))
                edges = gf.get("edges", [])
                pinned = gf.get("pinned", [])
                if not (isinstance(edges, list) and all(isinstance(e, list) and len(e) == 2 and
                                                        all(isinstance(a, int) for a in e) for e in edges)):
                    raise PlanError(f"{gf.where('edges')} must be a list of [from, to] agent numbers")
                if not (isinstance(pinned, list) and all(isinstance(a, int) for a in pinned)):
                    raise PlanError(f"{gf.where('pinned')} must be a list of agent numbers")
                topologies.append(Topology.from_edges(name, n, [tuple(e) for e in edges], pinned))
                gf.done()
        else:
            families = families if families is not None else graph_mod.default_families(n)
            if not isinstance(families, list) or not families:
                raise PlanError(f"{f.where('families')} must list at least one topology family")
            for name in families:
                if not isinstance(name, str) or name not in graph_mod.FAMILIES:
                    raise PlanError(f"{f.where('families')}: unknown family {name!r} "
                                    f"(known: {', '.join(graph_mod.FAMILIES)})")
                topologies.append(graph_mod.FAMILIES[name](n))
        schedule = Schedule(tuple(topologies), period)
        schedule.check()
    except GraphError as exc:
        raise PlanError(f"{f.source}: [topology] {exc}") from None
    f.done()
    return schedule


def _weights(f: _Fields) -> DesignWeights:
    try:
        w = DesignWeights(
            Q=f.array("Q_diag", (12,), DEFAULT_Q),
            R=f.array("R_diag", (6,), DEFAULT_R),
            Q_bar=f.array("Q_bar_diag", (12,), DEFAULT_Q_BAR),
            R_bar=f.array("R_bar_diag", (6,), DEFAULT_R_BAR),
            coupling_margin=f.number("coupling_margin", DEFAULT_COUPLING_MARGIN),
            Q_disturbance=f.array("Q_disturbance_diag", (6,), DEFAULT_Q_DISTURBANCE),
            R_bar_accel=f.array("R_bar_accel_diag", (3,), DEFAULT_R_BAR_ACCEL),
        )
    except ParameterError as exc:
        raise PlanError(f"{f.source}: [design] {exc}") from None
    f.done()
    return w


def plan_from_dict(data: dict, source: str = "plan") -> Plan:
    """Build and validate a plan. Raises PlanError (one sentence) on anything unusable."""
    top = _Fields(source, "", data)
    name = top.get("name", "unnamed")
    if not isinstance(name, str) or not name:
        raise PlanError(f"{source}: name must be a non-empty string")
    n = top.get("drones")
    if n is None:
        raise PlanError(f"{source}: drones is required")
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise PlanError(f"{source}: drones must be a whole number of at least 1, got {n!r}")
    if n > MAX_DRONES:
        raise PlanError(f"{source}: drones must be at most {MAX_DRONES}, got {n}")
    af = _airframe(_Fields(source, "airframe", top.get("airframe")))
    lf = _Fields(source, "leader", top.get("leader"))
    leader = ConstantFormation(lf.array("position_m", (1, 3), [0.0, 0.0, 0.0], per_drone=1),
                               lf.array("attitude_rad", (1, 3), [0.0, 0.0, 0.0], per_drone=1))
    lf.done()
    if "formation" not in data:
        raise PlanError(f"{source}: [formation] is required")
    formation = _formation(_Fields(source, "formation", top.get("formation")), n)
    ef = _Fields(source, "entry", top.get("entry"))
    entry = EntrySettings(ef.number("climb_m", 3.0, non_negative=True), ef.number("climb_s", 3.0, positive=True),
                          ef.number("blend_s", 12.0, positive=True))
    ef.done()
    schedule = _schedule(_Fields(source, "topology", top.get("topology")), n)
    weights = _weights(_Fields(source, "design", top.get("design")))
    cf = _Fields(source, "controller", top.get("controller"))
    ctrl = ControllerSettings(cf.number("rate_hz", 200.0, positive=True),
                              cf.number("thrust_adaptation_rate_1_s", 3.0, non_negative=True),
                              cf.number("air_density_kg_m3", non_negative=True) if "air_density_kg_m3" in cf.data else None,
                              cf.number("wind_estimate_rate_1_s", 1.0, non_negative=True),
                              cf.flag("accelerometer"), cf.number("latency_s", 0.0, non_negative=True))
    if ctrl.latency_s > MAX_LATENCY_S:
        raise PlanError(f"{cf.where('latency_s')} must be at most {MAX_LATENCY_S:g} s, got {ctrl.latency_s:g}")
    cf.done()
    kf = _Fields(source, "check", top.get("check"))
    checks = CheckSettings(kf.number("min_separation_m", default_min_separation_m(af), positive=True),
                           kf.number("position_bound_m", 0.10, positive=True),
                           kf.number("attitude_bound_rad", 0.02, positive=True),
                           kf.number("settle_s", 10.0, non_negative=True),
                           kf.number("rotor_speed_margin_pct", DEFAULT_ROTOR_SPEED_MARGIN_PCT, non_negative=True),
                           kf.number("tilt_margin_deg", DEFAULT_TILT_MARGIN_DEG, non_negative=True),
                           kf.number("turbulence_sigmas", DEFAULT_TURBULENCE_SIGMAS, non_negative=True))
    kf.done()
    settled = entry.climb_s + entry.blend_s + checks.settle_s
    duration = top.number("duration_s", max(DEFAULT_DURATION_S, math.ceil(settled + MIN_SETTLED_WINDOW_S)), positive=True)
    if duration <= settled:
        raise PlanError(f"{source}: duration_s ({duration:g} s) must be longer than the entry and its settling "
                        f"(entry.climb_s + entry.blend_s + check.settle_s = {settled:g} s), so that a flight has a "
                        f"settled window to be judged over")
    try:
        wind = wind_from_table(top.get("wind")) if "wind" in data else None
    except ParameterError as exc:
        raise PlanError(f"{source}: {exc}") from None
    top.done()
    return Plan(name, n, af, leader, formation, entry, schedule, weights, ctrl, checks, duration, source, dict(data),
                wind)


def default_min_separation_m(af: Airframe) -> float:
    return SEPARATION_ARM_LENGTHS * af.arm_length_m


def spec_from_toml(text: str, source: str) -> dict:
    """The dict of a plan file's text; PlanError naming the source if it is not TOML. (Reading the
    file is the caller's: ``protocol/`` does no I/O.)"""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise PlanError(f"{source}: not valid TOML ({exc})") from None


IN_FLIGHT_CHANGEABLE = frozenset({"name", "formation", "entry", "duration_s", "check", "wind"})
"""What a plan put in force during a flight may change: the formation (and its name, length, what
plan check holds it to and the wind a simulation of it assumes)."""


def in_flight_change_problem(flying: dict, new: dict) -> str | None:
    """Why ``new`` cannot replace ``flying`` in the air, or None. The design, graphs, leader and
    airframe must stay: the controllers, the neighbours and x0 carry on through the switch."""
    for key in sorted((set(flying) | set(new)) - IN_FLIGHT_CHANGEABLE):
        if flying.get(key) != new.get(key):
            return f"in flight a new plan may change only its formation, not {key}; land first"
    controller = flying.get("controller")
    if ("wind" in flying) != ("wind" in new) and not (isinstance(controller, dict) and "air_density_kg_m3" in controller):
        return ("in flight a new plan may not add or remove [wind]: it tells the controllers whether they fly in air "
                "(or give [controller] air_density_kg_m3); land first")
    return None
