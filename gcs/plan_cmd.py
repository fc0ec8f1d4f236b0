"""`triswarm plan`: formation plans, checked before they fly."""

from __future__ import annotations

import json
import math
from typing import Annotated

import numpy as np
import typer
from rich.markup import escape
from rich.panel import Panel
from rich.table import Table

from triswarm.protocol.airframe import RPM_TO_RAD_S
from triswarm.protocol.design import Design
from triswarm.protocol.plan import ActuatorDemand, Plan

from .errors import UserError, console, user_errors
from .report import design_summary
from .scenarios import load_plan

CHECK_STEP_S = 0.1  # plan time between the instants checked [s]

plan_app = typer.Typer(no_args_is_help=True, add_completion=False, rich_markup_mode=None,
                       help="Formation plans: check, upload, download, clear.")


@plan_app.command("check")
def check(
    file: Annotated[str, typer.Argument(help="Plan TOML file (or a built-in scenario name).")],
    horizon_s: Annotated[float, typer.Option("--horizon-s", help="Check the feasibility condition (76) over [0, S] s.")] = 60.0,
    as_json: Annotated[bool, typer.Option("--json", help="Print the design summary as JSON.")] = False,
) -> None:
    """Check a plan as Algorithm 1 does and print its design.

    The checks: (76) per drone over [0, S] s, Assumption 1 per topology, (91) and the Hurwitz
    conditions (77), and the rotor speeds and servo angles that flying the formation exactly needs,
    against the airframe's limits. A bad plan ends with one sentence and exit status 2."""
    with user_errors():
        if not (math.isfinite(horizon_s) and horizon_s > 0):
            raise UserError(f"--horizon-s must be a positive number, got {horizon_s}")
        plan = load_plan(file)
        design = plan.check(horizon_s=horizon_s, step_s=CHECK_STEP_S)
        demand = plan.actuator_demand(np.arange(0.0, horizon_s + 1e-9, CHECK_STEP_S))
    if as_json:
        typer.echo(json.dumps(_summary(plan, design, demand, horizon_s), indent=2))
    else:
        _print_design(plan, design, demand, horizon_s)


def _actuators(plan: Plan, demand: ActuatorDemand) -> list[dict]:
    af = plan.airframe
    return [{"drone": i + 1,
             "rotor_speed_rpm": [round(float(demand.omega_min_rad_s[:, i].min()) / RPM_TO_RAD_S, 1),
                                 round(float(demand.omega_max_rad_s[:, i].max()) / RPM_TO_RAD_S, 1)],
             "motor_limit_rpm": round(af.max_rotor_speed_rad_s / RPM_TO_RAD_S, 1),
             "tilt_max_deg": round(math.degrees(float(demand.tilt_max_rad[:, i].max())), 2),
             "servo_range_deg": round(math.degrees(af.servo_limit_rad), 2)}
            for i in range(plan.n_agents)]


def _summary(plan: Plan, design: Design, demand: ActuatorDemand, horizon_s: float) -> dict:
    return {
        "source": plan.source,
        "name": plan.name,
        "drones": plan.n_agents,
        "formation": plan.spec["formation"]["type"],
        "switch_period_s": plan.schedule.period_s,
        "feasible_over_s": [0.0, horizon_s],
        "design": design_summary(design),
        "actuators": _actuators(plan, demand),
    }


def _complex(z: complex) -> str:
    """A rounded eigenvalue; an imaginary part below the shown precision (a repeated eigenvalue's
    rounding noise) is left out."""
    return f"{z.real:.4g}" if abs(z.imag) < 1e-4 * max(1.0, abs(z)) else f"{z.real:.4g}{z.imag:+.4g}j"


def _print_design(plan: Plan, design: Design, demand: ActuatorDemand, horizon_s: float) -> None:
    facts = Table.grid(padding=(0, 2))
    facts.add_column(style="bold")
    facts.add_column()
    facts.add_row("name", plan.name)
    facts.add_row("drones", str(plan.n_agents))
    facts.add_row("formation", plan.spec["formation"]["type"])
    facts.add_row("switching", f"{len(design.topology_names)} topologies, every {plan.schedule.period_s:g} s")
    facts.add_row("lambda_R", f"{design.lambda_R:.6g} (min Re of eig(L+G) over the topologies)")
    facts.add_row("c", f"{design.c:.6g} = {design.weights.coupling_margin:g} / (2 lambda_R), (91)")
    for key, value in design.stability_margins().items():
        facts.add_row(key.replace("_", " "), f"{value:.4g} (< 0: Hurwitz, (77))")
    console.print(Panel(facts, title=f"plan {escape(plan.source)}", expand=False))

    topologies = Table(title="Assumption 1: eigenvalues of L+G per topology")
    topologies.add_column("topology")
    topologies.add_column("min Re", justify="right")
    topologies.add_column("eigenvalues")
    for name, eigs in zip(design.topology_names, design.eigenvalues):
        topologies.add_row(name, f"{np.min(eigs.real):.4g}", ", ".join(_complex(z) for z in eigs))
    console.print(topologies)

    feasibility = Table(title="(76) per drone")
    feasibility.add_column("drone", justify="right")
    feasibility.add_column("formation offsets")
    for i in range(plan.n_agents):
        feasibility.add_row(str(i + 1), f"feasible over [0, {horizon_s:g}] s")
    console.print(feasibility)

    actuators = Table(title="Actuators on the exact reference (the feedback needs room on top)")
    actuators.add_column("drone", justify="right")
    actuators.add_column("rotor speed [RPM]", justify="right")
    actuators.add_column("motor limit", justify="right")
    actuators.add_column("largest tilt [deg]", justify="right")
    actuators.add_column("servo range", justify="right")
    for row in _actuators(plan, demand):
        lo, hi = row["rotor_speed_rpm"]
        actuators.add_row(str(row["drone"]), f"{lo:.0f} - {hi:.0f}", f"{hi / row['motor_limit_rpm']:.0%} of "
                          f"{row['motor_limit_rpm']:.0f}", f"{row['tilt_max_deg']:.1f}",
                          f"{row['tilt_max_deg'] / row['servo_range_deg']:.0%} of +-{row['servo_range_deg']:.0f}")
    console.print(actuators)
    console.print(f"[green]{escape(plan.source)}: plan OK[/]")
