"""triswarm: the operator's command line."""

from __future__ import annotations

import functools
import importlib
import sys
from typing import Annotated

import typer

from .errors import console, err_console

ROOT_HELP = "triswarm: formation flight for swarms of tri-rotor drones."


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import version

        console.print(f"triswarm {version('triswarm')}")
        raise typer.Exit()


def _root(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit.")] = False,
) -> None:
    """triswarm: formation flight for swarms of tri-rotor drones."""


# The commands in the order the help lists them: name, module, and the command (a function) or group
# (a Typer) it holds.
PARTS = (("plan", "plan_cmd", "plan_app"), ("sim", "sim_cmd", "sim"), ("sitl", "sitl_cmd", "sitl_app"),
         ("plot", "plot_cmd", "plot"), ("demo", "demo", "demo"), ("monitor", "monitor", "monitor"),
         ("leader", "swarm_cmd", "leader_app"), ("arm", "swarm_cmd", "arm"), ("takeoff", "swarm_cmd", "takeoff"),
         ("land", "swarm_cmd", "land"), ("disarm", "swarm_cmd", "disarm"), ("pki", "pki_cmd", "pki_app"),
         ("deploy", "deploy_cmd", "deploy"))
COMMANDS = tuple(name for name, _, _ in PARTS)


@functools.cache
def build(command: str | None = None) -> typer.Typer:
    """The CLI: every command (None), or only ``command`` (one of ``COMMANDS``). A command's module is
    imported only when it is there: the modules bring what their commands need (numba's kernels, the
    MAVLink dialect, matplotlib: seconds of CPU on a slow machine), which `triswarm sim --help` or a
    mistyped option should not wait for."""
    app = typer.Typer(no_args_is_help=True, add_completion=False, rich_markup_mode=None, help=ROOT_HELP)
    app.callback()(_root)
    for name, module, attribute in PARTS:
        if command in (None, name):
            part = getattr(importlib.import_module(f"{__package__}.{module}"), attribute)
            if isinstance(part, typer.Typer):
                app.add_typer(part, name=name)
            else:
                app.command(name)(part)
    return app


def __getattr__(name: str) -> typer.Typer:
    if name == "app":  # the whole CLI (tools/gen_cli_docs.py, tests)
        return build()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def main() -> None:
    from triswarm.companion.design_cache import keep_on_disk

    keep_on_disk()  # (the design's solved equations kept across runs: plan check, sim, sitl up, demo)
    try:
        args = sys.argv[1:]
        build(args[0] if args and args[0] in COMMANDS else None)()
    except KeyboardInterrupt:
        err_console.print("triswarm: interrupted")
        sys.exit(130)
    except Exception:  # not a mistake in the command (those end in one sentence and exit status 2): a bug
        sys.excepthook(*sys.exc_info())
        err_console.print("triswarm: internal error: a bug in triswarm, not a mistake in the command "
                          "(the traceback above says where)", markup=False, highlight=False, soft_wrap=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
