"""`triswarm plan check`'s work once the plan is read: the checks, the flight in simulation, and
what is printed of them (a table, or JSON)."""

from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING

import numpy as np
import typer
from rich.markup import escape
from rich.panel import Panel
from rich.table import Table

from triswarm.protocol import air_margin
from triswarm.protocol.airframe import RPM_TO_RAD_S
from triswarm.protocol.errors import PlanError

from .errors import console, require_settled_window, user_errors
from .report import design_summary

if TYPE_CHECKING:
    from triswarm.protocol.design import Design
    from triswarm.protocol.air_margin import ActuatorDemand
    from triswarm.protocol.plan import Plan
    from triswarm.protocol.separation import Approach

    from . import plan_flight

CHECK_STEP_S = 0.1  # plan time between the instants checked [s]


def check_and_report(plan: Plan, horizon_s: float | None, no_simulate: bool, max_wind: bool, as_json: bool) -> None:
    """Check ``plan`` over [0, horizon_s] (its duration_s by default), fly it unless ``no_simulate``,
    and print the outcome; a refusal raises the error that says why."""
    with user_errors():
        horizon = plan.duration_s if horizon_s is None else horizon_s
        design = plan.check(horizon_s=horizon, step_s=CHECK_STEP_S)
        times = np.arange(0.0, horizon + 1e-9, CHECK_STEP_S)
        demand = plan.design_demand(times)
        approach = plan.closest_approach(horizon, CHECK_STEP_S)
        largest = None
        if max_wind:
            c = plan.check_settings
            largest = air_margin.largest_steady_wind_m_s(plan.rfl, plan.leader, plan.formation, times, plan.wind,
                                                         c.turbulence_sigmas, c.rotor_speed_margin_pct, c.tilt_margin_deg)
        flight = None
        if not no_simulate:
            require_settled_window(plan, horizon, "--horizon-s")
            from . import plan_flight

            flight = plan_flight.fly(plan, horizon)
            if flight.problem is not None:
                raise PlanError(f"{plan.source}: {flight.problem}")
    if as_json:
        typer.echo(json.dumps(_summary(plan, design, demand, horizon, approach, flight, largest), indent=2))
    else:
        _print_design(plan, design, demand, horizon, approach, flight, largest)


def _actuators(plan: Plan, demand: ActuatorDemand) -> list[dict]:
    af = plan.airframe
    speed_margin, tilt_margin = demand.rotor_speed_margin_pct(af), demand.tilt_margin_rad(af)
    return [{"drone": i + 1,
             "rotor_speed_rpm": [round(float(demand.omega_min_rad_s[:, i].min()) / RPM_TO_RAD_S, 1),
                                 round(float(demand.omega_max_rad_s[:, i].max()) / RPM_TO_RAD_S, 1)],
             "motor_limit_rpm": round(af.max_rotor_speed_rad_s / RPM_TO_RAD_S, 1),
             "rotor_speed_margin_pct": round(float(speed_margin[i]), 2),
             "tilt_max_deg": round(math.degrees(float(demand.tilt_max_rad[:, i].max())), 2),
             "servo_range_deg": round(math.degrees(af.servo_limit_rad), 2),
             "tilt_margin_deg": round(math.degrees(float(tilt_margin[i])), 2)}
            for i in range(plan.n_agents)]


def _design_air(plan: Plan, demand: ActuatorDemand, largest_steady_wind_m_s: float | None) -> dict:
    c, af = plan.check_settings, plan.airframe
    speed, tilt = demand.rotor_speed_margin_pct(af), np.degrees(demand.tilt_margin_rad(af))
    return {"air": air_margin.describe_design_air(plan.wind, c.turbulence_sigmas),
            "turbulence_sigmas": c.turbulence_sigmas,
            "required_rotor_speed_margin_pct": c.rotor_speed_margin_pct, "required_tilt_margin_deg": c.tilt_margin_deg,
            "rotor_speed_margin_pct": round(float(speed.min()), 2), "rotor_speed_margin_drone": int(speed.argmin()) + 1,
            "tilt_margin_deg": round(float(tilt.min()), 2), "tilt_margin_drone": int(tilt.argmin()) + 1,
            "largest_steady_wind_m_s": largest_steady_wind_m_s}


def _summary(plan: Plan, design: Design, demand: ActuatorDemand, horizon_s: float, approach: Approach | None,
             flight: plan_flight.Flight | None, largest_steady_wind_m_s: float | None) -> dict:
    return {
        "source": plan.source,
        "name": plan.name,
        "drones": plan.n_agents,
        "formation": plan.spec["formation"]["type"],
        "switch_period_s": plan.schedule.period_s,
        "feasible_over_s": [0.0, horizon_s],
        "design": design_summary(design),
        "certificate": plan.certificate.summary(),
        "separation": {"min_separation_m": plan.check_settings.min_separation_m,
                       "closest_m": None if approach is None else approach.distance_m,
                       "closest_drones": None if approach is None else [i + 1 for i in approach.pair],
                       "closest_t_s": None if approach is None else approach.t_s},
        "actuators": _actuators(plan, demand),
        "design_air": _design_air(plan, demand, largest_steady_wind_m_s),
        "controller": {"rate_hz": plan.controller.rate_hz,
                       "thrust_adaptation_rate_1_s": plan.controller.thrust_adaptation_rate_1_s,
                       "air_density_kg_m3": plan.controller_air_density_kg_m3(plan.wind),
                       "wind_estimate_rate_1_s": plan.controller.wind_estimate_rate_1_s,
                       "accelerometer": plan.controller_accelerometer(plan.wind),
                       "latency_s": plan.controller.latency_s,
                       "sampled_loop": _sampled_loop(plan, design)},
        "flight": flight.summary() if flight is not None else {"flown": False},
        "ok": flight is not None,
    }


def _sampled_loop(plan: Plan, design: Design) -> dict:
    """(77)'s loops sampled at the control rate: the largest |z| of their poles (< 1: they settle)."""
    s = design.sampled_loop(plan.controller.rate_hz)
    return {"max_abs_z": s.radius, "topology": s.topology, "eigenvalue": [s.eigenvalue.real, s.eigenvalue.imag]}


def _drag_term(plan: Plan) -> str:
    """What the controllers make of the air: the drag the RFL cancels, or none."""
    rho = plan.controller_air_density_kg_m3(plan.wind)
    if rho == 0.0:
        return "none (" + ("[controller] air_density_kg_m3 = 0" if plan.wind is not None else "flown in no air") + \
            ": the paper's law)"
    af = plan.airframe
    return (f"rho = {rho:g} kg/m^3, C_d A = {af.drag_coefficient * af.frontal_area_m2:g} m^2: the RFL cancels the "
            "body's drag 1/2 rho C_d A |v| v")


def _complex(z: complex) -> str:
    """A rounded eigenvalue; an imaginary part below the shown precision (a repeated eigenvalue's
    rounding noise) is left out."""
    return f"{z.real:.4g}" if abs(z.imag) < 1e-4 * max(1.0, abs(z)) else f"{z.real:.4g}{z.imag:+.4g}j"


def _print_design(plan: Plan, design: Design, demand: ActuatorDemand, horizon_s: float, approach: Approach | None,
                  flight: plan_flight.Flight | None, largest_steady_wind_m_s: float | None) -> None:
    facts = Table.grid(padding=(0, 2))
    facts.add_column(style="bold")
    facts.add_column()
    facts.add_row("name", plan.name)
    facts.add_row("drones", str(plan.n_agents))
    facts.add_row("formation", plan.spec["formation"]["type"])
    facts.add_row("switching", f"{len(design.topology_names)} topologies, every {plan.schedule.period_s:g} s")
    facts.add_row("lambda_R", f"{design.lambda_R:.6g} (min Re of eig(L+G) over the topologies)")
    facts.add_row("c", f"{design.c:.6g} = {design.weights.coupling_margin:g} / (2 lambda_R), (91)")
    facts.add_row("drag term", _drag_term(plan))
    from triswarm.protocol.controller import lead_ticks

    dt_s = 1.0 / plan.controller.rate_hz
    lead_ms = lead_ticks(plan.airframe.servo_delay_s, plan.controller.latency_s, dt_s)[1] * dt_s * 1000
    facts.add_row("prediction", escape(f"{lead_ms:.4g} ms ahead: the servo delay and [controller] latency_s "
                                       f"({plan.controller.latency_s * 1000:g} ms), in whole control periods"))
    for key, value in design.stability_margins().items():
        facts.add_row(key.replace("_", " "), f"{value:.4g} (< 0: Hurwitz, (77))")
    sampled = _sampled_loop(plan, design)
    facts.add_row("sampled loop", f"{sampled['max_abs_z']:.4g} (< 1: stable), largest |z| at {plan.controller.rate_hz:g} Hz")
    console.print(Panel(facts, title=f"plan {escape(plan.source)}", expand=False))

    topologies = Table(title="Assumption 1: eigenvalues of L+G per topology")
    topologies.add_column("topology")
    topologies.add_column("min Re", justify="right")
    topologies.add_column("eigenvalues")
    for name, eigs in zip(design.topology_names, design.eigenvalues):
        topologies.add_row(name, f"{np.min(eigs.real):.4g}", _eigenvalue_list(eigs))
    console.print(topologies)
    _print_certificate(plan)

    feasibility = Table(title="(76) per drone")
    feasibility.add_column("drone", justify="right")
    feasibility.add_column("formation offsets")
    for i in _shown(plan.n_agents):
        feasibility.add_row(str(i + 1), f"feasible over [0, {horizon_s:g}] s")
    console.print(feasibility)

    c = plan.check_settings
    air = escape(air_margin.describe_design_air(plan.wind, c.turbulence_sigmas))
    actuators = Table(title=f"Actuators on the exact reference in the design air: {air} (the margins are the "
                            f"feedback's room: at least {c.rotor_speed_margin_pct:g} % and {c.tilt_margin_deg:g} deg)")
    actuators.add_column("drone", justify="right")
    actuators.add_column("rotor speed [RPM]", justify="right")
    actuators.add_column("speed margin", justify="right")
    actuators.add_column("largest tilt [deg]", justify="right")
    actuators.add_column("tilt margin [deg]", justify="right")
    rows = _actuators(plan, demand)
    for i in _shown(plan.n_agents):
        row = rows[i]
        lo, hi = row["rotor_speed_rpm"]
        actuators.add_row(str(row["drone"]), f"{lo:.0f} - {hi:.0f}",
                          f"{row['rotor_speed_margin_pct']:.1f} % of {row['motor_limit_rpm']:.0f}",
                          f"{row['tilt_max_deg']:.1f}", f"{row['tilt_margin_deg']:.1f} of +-{row['servo_range_deg']:.0f}")
    console.print(actuators)
    if largest_steady_wind_m_s is not None:
        console.print(f"largest steady wind from any direction (every 15 deg) in which every drone keeps these margins: "
                      f"{largest_steady_wind_m_s:.1f} m/s (with the plan's turbulence and gusts on top)", soft_wrap=True)
    if approach is not None:
        i, j = approach.pair
        console.print(f"separation: drones {i + 1} and {j + 1} come closest, {approach.distance_m:.3g} m apart at "
                      f"t = {approach.t_s:.4g} s (minimum {plan.check_settings.min_separation_m:g} m)", soft_wrap=True)
    if flight is None:
        console.print(f"[yellow]{escape(plan.source)}: plan passes the checks; not flown in simulation (--no-simulate)[/]",
                      soft_wrap=True)
        return
    p = flight.performance
    console.print(f"flown in simulation over [0, {flight.window_s[1]:g}] s in {flight.result.wall_s:.1f} s: worst over the "
                  f"settled window [{flight.window_s[0]:.3g} s, {flight.window_s[1]:g} s] {p.worst_position_m:.3g} m "
                  f"(drone {p.worst_position_drone}), {p.worst_attitude_rad:.3g} rad (drone {p.worst_attitude_drone}); "
                  f"bounds {p.position_bound_m:g} m, {p.attitude_bound_rad:g} rad", soft_wrap=True)
    console.print(f"[green]{escape(plan.source)}: plan OK[/]", soft_wrap=True)


def _shown(n: int) -> list[int]:
    """Rows of a per-drone table: all for up to 20 drones, else the first ten and the last five."""
    return list(range(n)) if n <= 20 else list(range(10)) + list(range(n - 5, n))


def _eigenvalue_list(eigs: np.ndarray) -> str:
    if eigs.size <= 24:
        return ", ".join(_complex(z) for z in eigs)
    values, counts = np.unique(np.round(eigs, 6), return_counts=True)
    if values.size <= 24:
        return ", ".join(f"{_complex(z)}{f' (x{k})' if k > 1 else ''}" for z, k in zip(values, counts))
    return f"{eigs.size} eigenvalues, real parts {eigs.real.min():.4g} to {eigs.real.max():.4g}"


def _print_certificate(plan: Plan) -> None:
    cert = plan.certificate
    facts = Table.grid(padding=(0, 2))
    facts.add_column(style="bold")
    facts.add_column()
    growth = math.exp(0.5 * cert.log_growth_per_cycle)
    facts.add_row("bound per cycle", f"x{growth:.3g} on ||delta|| every {cert.cycle_s:g} s "
                                     f"({'decays' if cert.certified else 'does not decay'})")
    if cert.certified:
        facts.add_row("decay rate", f"{cert.decay_rate_1_s:.3g} 1/s on average")
        facts.add_row("transient", f"||delta(t)|| <= {cert.transient_bound:.3g} ||delta(0)||")
    dwell = cert.min_dwell_s
    facts.add_row("switching", "any switching signal" if cert.any_switching else
                  f"every {cert.period_s:g} s; this bound needs at least "
                  f"{dwell:.3g} s" if math.isfinite(dwell) else "no switching period makes this bound decay")
    if cert.best is not None:
        facts.add_row("Lyapunov function", cert.best.candidate)
    console.print(Panel(facts, title="certificate of the switched formation error (docs/formations.md)", expand=False))
