"""triswarm: the operator's command line."""

from __future__ import annotations

import sys
from typing import Annotated

import typer

from .errors import console, err_console
from .plan_cmd import plan_app

app = typer.Typer(no_args_is_help=True, add_completion=False, rich_markup_mode=None,
                  help="triswarm: formation flight for swarms of tri-rotor drones.")
app.add_typer(plan_app, name="plan")


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import version

        console.print(f"triswarm {version('triswarm')}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit.")] = False,
) -> None:
    """triswarm: formation flight for swarms of tri-rotor drones."""


from .sim_cmd import sim  # noqa: E402
from .sitl_cmd import sitl_app  # noqa: E402
from .plot_cmd import plot  # noqa: E402
from .swarm_cmd import register  # noqa: E402
from .demo import demo  # noqa: E402
from .monitor import monitor  # noqa: E402
from .pki_cmd import pki_app  # noqa: E402
from .deploy_cmd import deploy  # noqa: E402

app.command("sim")(sim)
app.add_typer(sitl_app, name="sitl")
app.command("plot")(plot)
app.command("demo")(demo)
app.command("monitor")(monitor)
register(app, plan_app)
app.add_typer(pki_app, name="pki")
app.command("deploy")(deploy)


def main() -> None:
    from triswarm.companion.design_cache import keep_on_disk

    keep_on_disk()  # (the design's solved equations kept across runs: plan check, sim, sitl up, demo)
    try:
        app()
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
