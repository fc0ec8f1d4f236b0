"""How the operator's CLI reports: its consoles, numbers in tables, and a user's mistake as one sentence and
exit status 2.

A user's mistake is an error one of triswarm's layers raises on purpose, with a sentence that names the option
or the file: each layer's errors derive from its base (GcsError here, UserError among them; SitlError,
CompanionError, ProtocolError), and a command catches those bases once (``user_errors``). Anything else, a
ValueError or an OSError from deep inside included, is a bug or a fault of the machine and is shown as one (a
traceback, exit status 1): never as the user's mistake."""

from __future__ import annotations

import contextlib
import math
from typing import TYPE_CHECKING

import typer
from rich.console import Console

from triswarm.companion.errors import CompanionError
from triswarm.protocol.errors import ProtocolError
from triswarm.sitl.errors import SitlError

if TYPE_CHECKING:
    from triswarm.protocol.plan import Plan

console = Console()
err_console = Console(stderr=True)


class GcsError(Exception):
    """The base of every error the ground station raises on purpose: one sentence for the operator."""


class UserError(GcsError):
    """A mistake in what the operator asked for (exit status 2)."""


USER_ERRORS: tuple[type[Exception], ...] = (GcsError, SitlError, CompanionError, ProtocolError)
"""The layers' bases, which every command reports as one sentence: the ground station's own, the simulator's,
the companion's modules', and protocol/'s (the plan, the airframe, the formation design, the graphs)."""


@contextlib.contextmanager
def user_errors():
    """Turn a user's mistake (USER_ERRORS) into one sentence on stderr and exit status 2, never a traceback.
    Every other exception passes: a bug shows as a bug."""
    try:
        yield
    except USER_ERRORS as exc:
        err_console.print(f"triswarm: error: {exc}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(code=2) from None


def require_positive(**options: float | None) -> None:
    """Each option given (its name with ``_`` for ``-``; None: not given) is a positive finite number, or
    the first that is not is the user's mistake."""
    for name, value in options.items():
        if value is not None and not (math.isfinite(value) and value > 0):
            raise UserError(f"--{name.replace('_', '-')} must be a positive number, got {value}")


def require_settled_window(plan: Plan, end_s: float, option: str) -> None:
    """A flight of ``plan`` that ends at ``end_s`` (given by ``option``) reaches the settled window it
    is judged over, or that is the user's mistake."""
    if end_s <= plan.settled_from_s:
        raise UserError(f"{option} {end_s:g} ends before the settled window the formation is judged over begins "
                        f"({plan.settled_from_s:g} s: the entry's end plus {plan.check_settings.settle_s:g} s)")


def short_number(x: float | None) -> str:
    """A short, honest rendering for tables: tiny errors in scientific notation rather than 0.0000."""
    if x is None or not math.isfinite(x):
        return "-"
    return f"{x:.2e}" if 0 < abs(x) < 1e-3 else f"{x:.4f}"


def finite_option(name: str, value: float | None, *, positive: bool = False, non_negative: bool = False) -> None:
    """--NAME must be a finite number (positive or not negative, if asked); None passes."""
    if value is None:
        return
    if not math.isfinite(value):
        raise UserError(f"--{name} must be a finite number, got {value}")
    if positive and value <= 0:
        raise UserError(f"--{name} must be positive, got {value}")
    if non_negative and value < 0:
        raise UserError(f"--{name} must not be negative, got {value}")
