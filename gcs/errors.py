"""How the operator's CLI reports: its consoles, numbers in tables, and a user's mistake as one sentence and
exit status 2."""

from __future__ import annotations

import contextlib
import math

import typer
from rich.console import Console

from triswarm.protocol.airframe import ParameterError
from triswarm.protocol.design import FormationError
from triswarm.protocol.graph import GraphError
from triswarm.protocol.plan import PlanError

console = Console()
err_console = Console(stderr=True)

USER_ERRORS = (PlanError, ParameterError, FormationError, GraphError, ValueError, FileNotFoundError)


class UserError(Exception):
    """A mistake in what the operator asked for (exit status 2)."""


@contextlib.contextmanager
def user_errors():
    """Turn a user's mistake into one sentence on stderr and exit status 2, never a traceback."""
    try:
        yield
    except (UserError, *USER_ERRORS) as exc:
        err_console.print(f"triswarm: error: {exc}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(code=2) from None


def short_number(x: float | None) -> str:
    """A short, honest rendering for tables: tiny errors in scientific notation rather than 0.0000."""
    if x is None or not math.isfinite(x):
        return "-"
    return f"{x:.2e}" if 0 < abs(x) < 1e-3 else f"{x:.4f}"
