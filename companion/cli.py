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
    id: Annotated[Optional[int], typer.Option("--id", help="This drone's number in the swarm (its MAVLink system id).")] = None,
    fc: Annotated[Optional[str], typer.Option(help="Flight-controller link (pymavlink connection string, or a serial "
                                                   "port DEVICE:BAUD).")] = None,
    gcs: Annotated[Optional[str], typer.Option(help="Ground-station link (pymavlink connection string).")] = None,
    plan: Annotated[Optional[Path], typer.Option(help="Plan file (TOML).")] = None,
    autostart: Annotated[bool, typer.Option(help="Arm, take off and start the plan at the common start time.")] = False,
    start_at: Annotated[Optional[float], typer.Option(help="Common start time [s since the Unix epoch] "
                                                           "(default with --autostart: the next multiple of 10 s, 5 s ahead).")] = None,
    zenoh_config: Annotated[Optional[Path], typer.Option(help="Zenoh configuration file (JSON5): client or router "
                                                              "modes across machines.")] = None,
    zenoh_listen: Annotated[Optional[list[str]], typer.Option(help="Zenoh endpoint to listen on (repeat).")] = None,
    zenoh_connect: Annotated[Optional[list[str]], typer.Option(help="Zenoh endpoint to connect to (repeat).")] = None,
    zenoh_mode: Annotated[str, typer.Option(help="Zenoh mode with --zenoh-listen/--zenoh-connect: peer or client.")] = "peer",
    zenoh_base_port: Annotated[int, typer.Option(help="Default peers on loopback: agent i uses TCP and UDP port base+i.")] = 17447,
    rate_hz: Annotated[float, typer.Option(help="Control rate [Hz] (the telemetry rate it asks for).")] = 200.0,
    state_dir: Annotated[Optional[Path], typer.Option(help="Keep the plan and mission here, to resume after a restart.")] = None,
    swarm: Annotated[Optional[str], typer.Option(help="Swarm name in the Zenoh key space (default: the plan's name).")] = None,
    stats: Annotated[Optional[Path], typer.Option(help="Write loop statistics here at exit (JSON).")] = None,
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
    from .config import explicit_options, resolve_options, run_checks

    if check:
        raise typer.Exit(code=run_checks(config, ctx.params, explicit_options(ctx)))
    try:
        o = resolve_options(config, ctx.params, explicit_options(ctx))
    except ValueError as exc:
        print(f"triswarm-companion: error: {exc}", file=sys.stderr)
        raise typer.Exit(code=2) from None
    id, fc, gcs, plan, autostart, start_at = o["id"], o["fc"], o["gcs"], o["plan"], o["autostart"], o["start_at"]
    zenoh_config, zenoh_listen, zenoh_connect = o["zenoh_config"], o["zenoh_listen"], o["zenoh_connect"]
    zenoh_mode, zenoh_base_port, rate_hz, state_dir = o["zenoh_mode"], o["zenoh_base_port"], o["rate_hz"], o["state_dir"]
    swarm, stats, signing_key, verbose = o["swarm"], o["stats"], o["signing_key"], o["verbose"]
    from .companion import Companion, CompanionOptions, write_stats

    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s companion {id}: %(message)s")
    try:
        opts = CompanionOptions(agent=id, fc_url=fc, gcs_url=gcs, plan_path=plan, autostart=autostart,
                                start_at_unix_s=start_at, zenoh_config=zenoh_config,
                                zenoh_listen=tuple(zenoh_listen or ()), zenoh_connect=tuple(zenoh_connect or ()),
                                zenoh_mode=zenoh_mode, zenoh_base_port=zenoh_base_port, rate_hz=rate_hz,
                                state_dir=state_dir, swarm=swarm, stats_path=stats, signing_key_path=signing_key)
        comp = Companion(opts)

        async def main() -> dict:
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, stop.set)
            return await comp.run(stop)

        result = asyncio.run(main())
    except (PlanError, ParameterError, GraphError, ValueError, OSError) as exc:
        print(f"triswarm-companion: error: {exc}", file=sys.stderr)
        raise typer.Exit(code=2) from None
    if stats is not None:
        write_stats(stats, result)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
