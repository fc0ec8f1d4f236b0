"""triswarm-companion: the process on each drone's onboard computer."""

from __future__ import annotations

import asyncio
import inspect
import signal
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from triswarm.protocol.errors import ProtocolError

from .errors import CompanionError
from .options import BY_NAME, OPTIONS, PYTHON_TYPE, CompanionOptions

app = typer.Typer(add_completion=False, rich_markup_mode=None)

USER_ERRORS = (CompanionError, ProtocolError)
"""What the companion reports as the operator's mistake (one line, exit status 2): the errors it and
protocol/ raise on purpose. Anything else is a bug: its traceback."""


def _cli_signature() -> inspect.Signature:
    """The command's parameters: every ``options.OPTIONS`` entry (the per-agent ones repeatable, the
    plan a positional argument), and the command line's own --config and --check."""
    import typer

    params = [inspect.Parameter("ctx", inspect.Parameter.POSITIONAL_OR_KEYWORD, annotation=typer.Context)]
    for o in OPTIONS:
        kind = PYTHON_TYPE[o.kind]
        if o.name == "plan":
            info = typer.Argument(metavar=o.metavar, show_default=False, help=o.help)
            annotation = Optional[kind]
        elif o.per_agent:
            info = typer.Option(metavar=o.metavar, help=o.help)
            annotation = Optional[list[kind]]
        elif o.kind == "strlist":
            info = typer.Option(help=o.help)
            annotation = Optional[list[str]]
        else:
            info = typer.Option(metavar=o.metavar, help=o.help)
            annotation = kind if o.default is not None else Optional[kind]
        default = None if o.per_agent or o.kind == "strlist" else o.default
        params.append(inspect.Parameter(o.name, inspect.Parameter.KEYWORD_ONLY, default=default,
                                        annotation=Annotated[annotation, info]))
        if o.name == "plan":
            params.append(inspect.Parameter("plan_option", inspect.Parameter.KEYWORD_ONLY, default=None,
                                            annotation=Annotated[Optional[Path], typer.Option(
                                                "--plan", hidden=True, help="Deprecated spelling of PLAN.")]))
    params.append(inspect.Parameter("config", inspect.Parameter.KEYWORD_ONLY, default=None, annotation=Annotated[
        Optional[Path], typer.Option(help="Per-drone configuration (TOML, keys named like these options; see "
                                          "deploy/drone.example.toml). Options given here win.")]))
    params.append(inspect.Parameter("check", inspect.Parameter.KEYWORD_ONLY, default=False, annotation=Annotated[
        bool, typer.Option(help="With --config: check the configuration, the flight controller's port, Zenoh, the "
                                "signing key and the state folder, one line each; exit 0 or 1.")]))
    return inspect.Signature(params)


def companion(ctx, **given_params) -> None:
    """Fly one drone of a formation: MAVLink to its flight controller, Zenoh to its neighbours."""
    import typer

    from .config import ConfigError, explicit_options, fc_url, link_url, resolve_options, run_checks

    id, fc, gcs = given_params["id"], given_params["fc"], given_params["gcs"]
    config, check, plan_option = given_params.pop("config"), given_params.pop("check"), given_params.pop("plan_option")
    agents = [(i, f, g) for i, f, g in zip(id or [], fc or [], gcs or [])]
    params = dict(given_params, id=(id or [None])[0], fc=(fc or [None])[0], gcs=(gcs or [None])[0])
    for o in OPTIONS:  # (a repeated option's default is no value: the dataclass's is an empty tuple)
        if o.kind == "strlist":
            params[o.name] = tuple(params[o.name] or ())
    given = explicit_options(ctx) - {"config", "check", "plan_option"}
    if plan_option is not None:  # the old spelling, kept for one release
        print("triswarm-companion: warning: --plan FILE is deprecated and goes in the next release: give the plan "
              "as the positional PLAN", file=sys.stderr)
        if params["plan"] is not None:
            print("triswarm-companion: error: give the plan once: PLAN or --plan, not both", file=sys.stderr)
            raise typer.Exit(code=2)
        params["plan"] = plan_option
        given |= {"plan"}
    if check:
        raise typer.Exit(code=run_checks(config, params, given))
    try:
        if len(id or []) > 1 or len(fc or []) > 1 or len(gcs or []) > 1:
            if not len(id or []) == len(fc or []) == len(gcs or []):
                raise ConfigError("several drones need one --fc and one --gcs for each --id, in the same order")
            if config is not None:
                raise ConfigError("--config describes one drone: give several drones their options on the command line")
            if len({i for i, _, _ in agents}) != len(agents):
                raise ConfigError("every --id must be a different drone")
        values = resolve_options(config, params, given)
        agents = [(i, fc_url(f), link_url(g, "gcs")) for i, f, g in agents[1:]]
        for i, _, _ in agents:
            problem = BY_NAME["id"].check(i)
            if problem:
                raise ConfigError(problem)
        from .host import CountingLoop, agent_options, run_agents

        from .logs import start_logging

        opts = CompanionOptions(**{o.name: values[o.name] for o in OPTIONS})
        every = agent_options(opts, [(opts.id, opts.fc, opts.gcs), *agents])

        async def main() -> list[dict]:
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, stop.set)
            return await run_agents(every, stop)

        log_writer = start_logging(sys.stderr, values["verbose"])
        try:
            with asyncio.Runner(loop_factory=CountingLoop) as runner:
                results = runner.run(main())
        finally:
            log_writer.stop()
    except USER_ERRORS as exc:  # what the operator wrote or gave (anything else is a bug: its traceback)
        print(f"triswarm-companion: error: {exc}", file=sys.stderr)
        raise typer.Exit(code=2) from None
    for o, result in zip(every, results):
        if o.stats is not None:
            try:
                write_stats(o.stats, result)
            except OSError as exc:
                print(f"triswarm-companion: error: cannot write the stats to {o.stats}: {exc.strerror}", file=sys.stderr)
                raise typer.Exit(code=2) from None


companion.__signature__ = _cli_signature()
companion.__annotations__ = {p.name: p.annotation for p in companion.__signature__.parameters.values()}
app.command()(companion)


def write_stats(path: Path, stats: dict) -> None:
    import json

    from .state import write_json_atomically

    write_json_atomically(path, json.loads(json.dumps(stats, default=float)))


def main() -> None:
    import zenoh

    from .design_cache import keep_on_disk

    zenoh.init_log_from_env_or("error")  # (Zenoh's own log: RUST_LOG=zenoh=debug for more)
    keep_on_disk()  # (the design's solved equations kept across runs)
    app()


if __name__ == "__main__":
    main()
