"""Finding and reading plan files: a built-in name (``paper-hexagon``) or a path to a TOML file."""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from triswarm.protocol.errors import PlanError

if TYPE_CHECKING:
    from triswarm.protocol.plan import Plan

DEFAULT_PLAN = "paper-hexagon"


def builtin_names() -> list[str]:
    folder = resources.files("triswarm.protocol").joinpath("plans")
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


PlanArgument = Annotated[str, typer.Argument(
    metavar="PLAN", show_default=True,
    help=f"A plan file (TOML) or a built-in scenario name ({', '.join(builtin_names())}).")]
"""How every `triswarm` command that takes a plan takes it: one positional PLAN."""


def plan_text(name_or_path: str) -> str:
    """The TOML text of a plan file or a built-in scenario; PlanError if there is none."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        try:
            return path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise PlanError(f"{path}: no such plan file") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise PlanError(f"{path}: cannot read the plan file ({exc.__class__.__name__})") from None
    if name_or_path not in builtin_names():
        raise PlanError(f"{name_or_path}: not a plan file and not a built-in scenario "
                        f"(built-in: {', '.join(builtin_names())})")
    return resources.files("triswarm.protocol").joinpath("plans", f"{name_or_path}.toml").read_text(encoding="utf-8")


def read_plan_spec(name_or_path: str) -> tuple[dict, str]:
    """The plan dict and a label for messages. Raises PlanError for a missing or malformed file."""
    from triswarm.protocol.plan import spec_from_toml

    return spec_from_toml(plan_text(name_or_path), name_or_path), name_or_path


def load_plan(name_or_path: str, drones: int | None = None) -> Plan:
    from triswarm.protocol.plan import plan_from_dict

    spec, label = read_plan_spec(name_or_path)
    plan = plan_from_dict(spec, label)
    if drones is not None and drones != plan.n_agents:
        plan = plan.with_agents(drones)
    return plan
