"""triswarm-companion: the process on each drone's onboard computer."""

from __future__ import annotations

import asyncio
import logging
import signal
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from triswarm.protocol.airframe import ParameterError
from triswarm.protocol.graph import GraphError
from triswarm.protocol.plan import PlanError

app = typer.Typer(add_completion=False, rich_markup_mode=None)


@app.command()
def companion(
    ctx: typer.Context,
    id: Annotated[Optional[list[int]], typer.Option("--id", metavar="N", help="This drone's number in the swarm (its MAVLink system "
                                                                 "id). Repeat, with --fc and --gcs for each, to fly "
                                                                 "several simulated drones in this process.")] = None,
    fc: Annotated[Optional[list[str]], typer.Option(metavar="URL", help="Flight-controller link (pymavlink connection string, or a serial "
                                                         "port DEVICE:BAUD).")] = None,
    gcs: Annotated[Optional[list[str]], typer.Option(metavar="URL", help="Ground-station link (pymavlink connection string).")] = None,
    plan: Annotated[Optional[Path], typer.Argument(metavar="PLAN", show_default=False,
                                                   help="A plan file (TOML) to load at start; without one, the "
                                                        "ground station uploads it (triswarm plan upload).")] = None,
    plan_option: Annotated[Optional[Path], typer.Option("--plan", hidden=True,
                                                        help="Deprecated spelling of PLAN.")] = None,
    autostart: Annotated[bool, typer.Option(help="Arm, take off and start the plan at the common start time.")] = False,
    start_at: Annotated[Optional[float], typer.Option(help="Common start time [s since the Unix epoch] "
                                                           "(default with --autostart: the next multiple of 10 s, 5 s ahead).")] = None,
    zenoh_config: Annotated[Optional[Path], typer.Option(help="Zenoh configuration file (JSON5): client or router "
                                                              "modes across machines.")] = None,
    zenoh_listen: Annotated[Optional[list[str]], typer.Option(help="Zenoh endpoint to listen on (repeat).")] = None,
    zenoh_connect: Annotated[Optional[list[str]], typer.Option(help="Zenoh endpoint to connect to (repeat).")] = None,
    zenoh_mode: Annotated[str, typer.Option(help="Zenoh mode with --zenoh-listen/--zenoh-connect: peer or client.")] = "peer",
    zenoh_base_port: Annotated[int, typer.Option(help="Default peers on one machine: agent i listens on TCP port base+i.")] = 17447,
    rate_hz: Annotated[float, typer.Option(help="Control rate [Hz] (the telemetry rate it asks for).")] = 200.0,
    gcs_frames_per_s: Annotated[float, typer.Option(help="Frames a second one ground station may send beyond a burst "
                                                         "of twice that; beyond: dropped, counted and said once "
                                                         "(0: no limit).")] = 100.0,
    state_dir: Annotated[Optional[Path], typer.Option(help="Keep the plan and mission here, to resume after a restart "
                                                           "({id} in the path: the drone's number).")] = None,
    swarm: Annotated[Optional[str], typer.Option(help="Swarm name in the Zenoh key space (default: the plan's name).")] = None,
    stats: Annotated[Optional[Path], typer.Option(help="Write loop statistics here at exit (JSON; {id} in the path: the "
                                                       "drone's number).")] = None,
    signing_key: Annotated[Optional[Path], typer.Option(help="MAVLink 2 signing key file (32 bytes, or 64 hex digits): "
                                                             "sign the ground-station link and refuse its unsigned "
                                                             "commands, plans and parameter changes.")] = None,
    verbose: Annotated[bool, typer.Option(help="Log more.")] = False,
    config: Annotated[Optional[Path], typer.Option(help="Per-drone configuration (TOML, keys named like these options; "
                                                        "see deploy/drone.example.toml). Options given here win.")] = None,
    check: Annotated[bool, typer.Option(help="With --config: check the configuration, the flight controller's port, "
                                             "Zenoh, the signing key and the state folder, one line each; exit 0 or 1.")] = False,
) -> None:
    """Fly one drone of a formation: MAVLink to its flight controller, Zenoh to its neighbours."""
    from .config import ConfigError, explicit_options, link_url, resolve_options, run_checks

    agents = [(i, f, g) for i, f, g in zip(id or [], fc or [], gcs or [])]
    params = dict(ctx.params, id=(id or [None])[0], fc=(fc or [None])[0], gcs=(gcs or [None])[0])
    given = explicit_options(ctx)
    del params["plan_option"]
    if plan_option is not None:  # the old spelling, kept for one release
        print("triswarm-companion: warning: --plan FILE is deprecated and goes in the next release: give the plan "
              "as the positional PLAN", file=sys.stderr)
        if plan is not None:
            print("triswarm-companion: error: give the plan once: PLAN or --plan, not both", file=sys.stderr)
            raise typer.Exit(code=2)
        params["plan"] = plan_option
        given = (given - {"plan_option"}) | {"plan"}
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
        o = resolve_options(config, params, given)
        agents = [(i, link_url(f, "fc"), link_url(g, "gcs")) for i, f, g in agents[1:]]
        for i, _, _ in agents:
            if not 1 <= i <= 255:
                raise ConfigError(f"--id must be a MAVLink system id between 1 and 255, got {i}")
    except ConfigError as exc:  # what the operator wrote (anything else is a bug: its traceback)
        print(f"triswarm-companion: error: {exc}", file=sys.stderr)
        raise typer.Exit(code=2) from None
    id, fc, gcs, plan, autostart, start_at = o["id"], o["fc"], o["gcs"], o["plan"], o["autostart"], o["start_at"]
    zenoh_config, zenoh_listen, zenoh_connect = o["zenoh_config"], o["zenoh_listen"], o["zenoh_connect"]
    zenoh_mode, zenoh_base_port, rate_hz, state_dir = o["zenoh_mode"], o["zenoh_base_port"], o["rate_hz"], o["state_dir"]
    swarm, stats, signing_key, verbose = o["swarm"], o["stats"], o["signing_key"], o["verbose"]
    gcs_frames_per_s = o["gcs_frames_per_s"]
    from .agent import CompanionOptions, StartupError
    from .host import CountingLoop, agent_options, run_agents

    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(message)s")
    try:
        opts = CompanionOptions(agent=id, fc_url=fc, gcs_url=gcs, plan_path=plan, autostart=autostart,
                                start_at_unix_s=start_at, zenoh_config=zenoh_config,
                                zenoh_listen=tuple(zenoh_listen or ()), zenoh_connect=tuple(zenoh_connect or ()),
                                zenoh_mode=zenoh_mode, zenoh_base_port=zenoh_base_port, rate_hz=rate_hz,
                                state_dir=state_dir, swarm=swarm, stats_path=stats, signing_key_path=signing_key,
                                gcs_frames_per_s=gcs_frames_per_s)
        every = agent_options(opts, [(id, fc, gcs), *agents])

        async def main() -> list[dict]:
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, stop.set)
            return await run_agents(every, stop)

        with asyncio.Runner(loop_factory=CountingLoop) as runner:
            results = runner.run(main())
    except (PlanError, ParameterError, GraphError, StartupError) as exc:  # (anything else is a bug: its traceback)
        print(f"triswarm-companion: error: {exc}", file=sys.stderr)
        raise typer.Exit(code=2) from None
    for o, result in zip(every, results):
        if o.stats_path is not None:
            try:
                write_stats(o.stats_path, result)
            except OSError as exc:
                print(f"triswarm-companion: error: cannot write the stats to {o.stats_path}: {exc.strerror}", file=sys.stderr)
                raise typer.Exit(code=2) from None


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
