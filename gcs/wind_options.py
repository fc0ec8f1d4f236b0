"""The wind flags that `triswarm sim` and `triswarm sitl up` share, and the Wind they make
(``protocol.wind``; docs/wind.md)."""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from triswarm.protocol.errors import ParameterError

from .errors import UserError

if TYPE_CHECKING:
    from triswarm.protocol.wind import Gust, Wind

WindSpeed = Annotated[Optional[float], typer.Option(
    "--wind-m-s", help="Steady wind speed [m/s], the same everywhere. 0 is still air: the drones feel the drag of "
                       "their own motion. Without any wind flag (and no [wind] in the plan) there is no air at all, "
                       "the paper's drag-free model.")]
WindFrom = Annotated[Optional[float], typer.Option(
    "--wind-from-deg", help="Where the wind blows from, degrees clockwise from north (meteorological: 0 from the "
                            "north, 90 from the east, 270 a westerly blowing east) (default 0).")]
Turbulence = Annotated[Optional[str], typer.Option(
    "--turbulence", metavar="LEVEL", help="Dryden turbulence of MIL-F-8785C, each drone its own, seeded by --seed: "
                                          "none, light, moderate, severe (sigma_w 0.77, 1.54, 2.32 m/s), or sigma_w "
                                          "in m/s (vertical intensity; horizontal 1.8 times that at 20 m).")]
Gusts = Annotated[Optional[list[str]], typer.Option(
    "--gust", metavar="SPEC", help="A 1-cosine gust, SPEED_M_S,DURATION_S,START_S[,FROM_DEG]: its peak speed, its "
                                   "duration from calm to calm, its start on the simulated clock and where it blows "
                                   "from (default: the wind's direction), e.g. 5,2,30. Repeat for several.")]


def wind_from_options(base: Wind | None, speed_m_s: float | None, from_deg: float | None, turbulence: str | None,
                      gusts: list[str] | None) -> Wind | None:
    """``base`` (a plan's wind, or None) with what the flags change; None when no flag is given and
    there is no base."""
    from triswarm.protocol.wind import Wind, turbulence_sigma_w

    if speed_m_s is None and from_deg is None and turbulence is None and not gusts:
        return base
    changes = {}
    for flag, name, value in (("--wind-m-s", "speed_m_s", speed_m_s), ("--wind-from-deg", "from_deg", from_deg)):
        if value is not None:
            if not math.isfinite(value) or (name == "speed_m_s" and value < 0):
                raise UserError(f"{flag} must be a finite number{' (not negative)' if name == 'speed_m_s' else ''}, "
                                f"got {value}")
            changes[name] = value
    if turbulence is not None:
        changes["turbulence_sigma_w_m_s"] = turbulence_sigma_w(turbulence, "--turbulence")
    if gusts:
        changes["gusts"] = tuple(_gust(text) for text in gusts)
    try:
        return dataclasses.replace(base or Wind(), **changes)
    except ParameterError as exc:
        raise UserError(f"--gust: {exc}") from None


def _gust(text: str) -> Gust:
    from triswarm.protocol.wind import Gust

    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (3, 4) or not all(math.isfinite(v) for v in values):
        raise UserError(f"--gust must be SPEED_M_S,DURATION_S,START_S[,FROM_DEG] (three or four numbers), got {text!r}")
    return Gust(*values)
