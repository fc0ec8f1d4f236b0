"""`triswarm plan`: formation plans, checked before they fly."""

from __future__ import annotations

import dataclasses
from typing import Annotated, Optional

import typer

from .errors import UserError, require_positive, user_errors
from .scenarios import PlanArgument, load_plan
from .swarm_cmd import clear, download, upload

plan_app = typer.Typer(no_args_is_help=True, add_completion=False, rich_markup_mode=None,
                       help="Formation plans: check, upload, download, clear.")


@plan_app.command("check")
def check(
    plan_name: PlanArgument,
    drones: Annotated[Optional[int], typer.Option(help="Resize the plan to N drones first, as `sim --drones` does.")] = None,
    horizon_s: Annotated[Optional[float], typer.Option("--horizon-s", help="Check and fly over [0, S] s (default: the plan's "
                                                                           "duration_s, 60 s unless it says).")] = None,
    no_simulate: Annotated[bool, typer.Option("--no-simulate", help="Skip the flight in simulation (then the plan is "
                                                                    "checked, not flown).")] = False,
    min_separation_m: Annotated[Optional[float], typer.Option("--min-separation-m", help="Minimum distance between drones "
                                                              "along the reference (default: check.min_separation_m, "
                                                              "8 arm lengths).")] = None,
    position_bound_m: Annotated[Optional[float], typer.Option("--position-bound-m", help="Flight verdict: position bound "
                                                              "(default: check.position_bound_m, 0.10).")] = None,
    attitude_bound_rad: Annotated[Optional[float], typer.Option("--attitude-bound-rad", help="Flight verdict: attitude "
                                                                "bound (default: check.attitude_bound_rad, 0.02).")] = None,
    max_wind: Annotated[bool, typer.Option("--max-wind", help="Also find the largest steady wind, from any direction "
                                           "(every 15 deg) with the plan's turbulence and gusts on top, in which every "
                                           "drone keeps check's margins.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the design summary as JSON.")] = False,
) -> None:
    """Check a plan as Algorithm 1 does, certify its switching, and fly it in simulation.

    The checks: (76) per drone, Assumption 1 per topology, (91) and the Hurwitz conditions (77),
    the same loops sampled at the control rate (every pole within the unit circle), the rotor
    speeds and servo angles that flying the formation exactly needs, the margins that leaves to the
    motor limit and the servo range in the plan's design air ([wind]: its steady wind, its gusts at
    their peak, 3 sigma of its turbulence from the worst direction), the certificate of the switched
    formation-error system, and the minimum separation along the reference. Then the plan is flown
    in the in-process simulation (nominal plant, from the ground, in the plan's [wind]) and every
    drone must stay within the bounds over the settled window. "plan OK" means
    all of that passed. A refused plan ends with one sentence and exit status 2."""
    with user_errors():
        require_positive(horizon_s=horizon_s, min_separation_m=min_separation_m, position_bound_m=position_bound_m,
                         attitude_bound_rad=attitude_bound_rad)
        if drones is not None and drones < 1:
            raise UserError(f"--drones must be at least 1, got {drones}")
        plan = load_plan(plan_name, drones)
        changes = {k: v for k, v in (("min_separation_m", min_separation_m), ("position_bound_m", position_bound_m),
                                     ("attitude_bound_rad", attitude_bound_rad)) if v is not None}
        if changes:
            plan = dataclasses.replace(plan, check_settings=dataclasses.replace(plan.check_settings, **changes))
    from .plan_report import check_and_report

    check_and_report(plan, horizon_s, no_simulate, max_wind, as_json)


plan_app.command("upload")(upload)
plan_app.command("download")(download)
plan_app.command("clear")(clear)
