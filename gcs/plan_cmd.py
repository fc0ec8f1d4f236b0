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

from triswarm.protocol.design import Design
from triswarm.protocol.plan import Plan

from .errors import UserError, console, user_errors
from .report import design_summary
from .scenarios import load_plan

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
    conditions (77). A bad plan ends with one sentence and exit status 2."""
    with user_errors():
        if not (math.isfinite(horizon_s) and horizon_s > 0):
            raise UserError(f"--horizon-s must be a positive number, got {horizon_s}")
        plan = load_plan(file)
        design = plan.check(horizon_s=horizon_s)
    if as_json:
        typer.echo(json.dumps(_summary(plan, design, horizon_s), indent=2))
    else:
        _print_design(plan, design, horizon_s)


def _summary(plan: Plan, design: Design, horizon_s: float) -> dict:
    return {
        "source": plan.source,
        "name": plan.name,
        "drones": plan.n_agents,
        "formation": plan.spec["formation"]["type"],
        "switch_period_s": plan.schedule.period_s,
        "feasible_over_s": [0.0, horizon_s],
        "design": design_summary(design),
    }


def _complex(z: complex) -> str:
    """A rounded eigenvalue; an imaginary part below the shown precision (a repeated eigenvalue's
    rounding noise) is left out."""
    return f"{z.real:.4g}" if abs(z.imag) < 1e-4 * max(1.0, abs(z)) else f"{z.real:.4g}{z.imag:+.4g}j"


def _print_design(plan: Plan, design: Design, horizon_s: float) -> None:
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
    console.print(f"[green]{escape(plan.source)}: plan OK[/]")
