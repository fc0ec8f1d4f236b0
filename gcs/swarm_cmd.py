"""The operator's commands to a flying swarm, over MAVLink: plan upload / download / clear, leader
goto / hold, and arm, takeoff, land, disarm, for some drones (--drone N, repeated) or all. With --signing-key, every
frame they send is signed (MAVLink 2 signing): companions started with the same key refuse unsigned
commands, plans and parameter changes."""

from __future__ import annotations

import contextlib
import math
import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from triswarm.companion.state import read_signing_key
from triswarm.protocol.frames import flip
from triswarm.protocol.mavlink import COMP_AUTOPILOT, COMP_ONBOARD, mavlink
from triswarm.protocol.plan_transfer import PlanTransferError, decode_plan, encode_plan

from . import missions
from .errors import UserError, console, err_console, user_errors
from .link import GroundLink, parse_endpoints
from .scenarios import PlanArgument
from .swarm import command_all, flight_clock, for_each, start_all, take_off_all, upload_all

Manifest = Annotated[Optional[Path], typer.Option("--manifest", envvar="TRISWARM_MANIFEST",
                                                  help="Swarm manifest (swarm.json) with each drone's MAVLink endpoint.")]
Endpoints = Annotated[Optional[list[str]], typer.Option("--endpoint", metavar="ID=URL",
                                                        help="A drone's MAVLink endpoint as ID=URL (repeat), e.g. "
                                                             "1=udpout:192.168.1.11:14550.")]
Drones = Annotated[Optional[list[int]], typer.Option("--drone", metavar="N", help="Only this drone (repeat); "
                                                                                  "default: all.")]
Tlog = Annotated[Path, typer.Option("--tlog", help="Append every MAVLink message received to this .tlog.")]
SigningKey = Annotated[Optional[Path], typer.Option("--signing-key", envvar="TRISWARM_SIGNING_KEY",
                                                    help="MAVLink 2 signing key file (32 bytes, or 64 hex digits), "
                                                         "the companions' own: sign every frame sent.")]
DEFAULT_TLOG = Path("gcs.tlog")
LINK_WAIT_S = 5.0

leader_app = typer.Typer(no_args_is_help=True, add_completion=False, rich_markup_mode=None,
                         help="Move the formation's leader x0 (the whole formation follows).")


@contextlib.contextmanager
def swarm_link(manifest: Path | None, endpoint: list[str] | None, drones: list[int] | None, tlog: Path,
               signing_key: Path | None = None, require_all: bool = True):
    """The link to the selected drones, once each companion's heartbeat is heard (with
    ``require_all`` False, at once: a monitor shows the silent ones as lost)."""
    with user_errors():
        try:
            key = None if signing_key is None else read_signing_key(signing_key)
        except ValueError as exc:  # unreadable, or not a key (a sentence naming the file)
            raise UserError(f"--signing-key {exc}") from None
        endpoints, fc_endpoints = parse_endpoints(manifest, endpoint)
        unknown = sorted(set(drones or []) - set(endpoints))
        if unknown:
            raise UserError(f"--drone {unknown[0]}: not in the swarm (drones {', '.join(map(str, sorted(endpoints)))})")
        chosen = sorted(set(drones or endpoints))
        link = GroundLink({i: endpoints[i] for i in chosen}, tlog=tlog, signing_key=key,
                          fc_endpoints={i: fc_endpoints[i] for i in chosen if i in fc_endpoints})
    with link:
        if not require_all:
            yield link, chosen
            return
        deadline = time.monotonic() + LINK_WAIT_S
        while time.monotonic() < deadline and not all(link.companion(i).heartbeat for i in chosen):
            time.sleep(0.05)
        silent = [i for i in chosen if link.companion(i).heartbeat is None]
        if silent:
            other_key = (" (frames signed with another key came: check --signing-key)"
                         if link.counters["refused_bad_signature"] else "")
            err_console.print(f"triswarm: error: no heartbeat from the companion of drone "
                              f"{', '.join(map(str, silent))} in {LINK_WAIT_S:g} s "
                              f"({', '.join(link.endpoints[i] for i in silent)}){other_key}", soft_wrap=True)
            raise typer.Exit(code=1)
        yield link, chosen


def report(title: str, outcomes: dict[int, tuple[bool, str]]) -> None:
    """A table of what each drone answered; exit 1 if any refused or did not answer."""
    table = Table(title=title, title_justify="left")
    table.add_column("drone", justify="right")
    table.add_column("result")
    table.add_column("detail")
    for i, (ok, detail) in sorted(outcomes.items()):
        table.add_row(str(i), "[green]ok[/]" if ok else "[red]refused[/]", detail)
    console.print(table)
    if not all(ok for ok, _ in outcomes.values()):
        raise typer.Exit(code=1)


# -- plans --------------------------------------------------------------------------------------

def upload(
    plan_name: PlanArgument,
    manifest: Manifest = None, endpoint: Endpoints = None, drone: Drones = None, tlog: Tlog = DEFAULT_TLOG, signing_key: SigningKey = None,
    start_in_s: Annotated[float, typer.Option("--start-in-s", help="Start the plan this long after the upload [s].")] = 10.0,
    no_start: Annotated[bool, typer.Option("--no-start", help="Upload only; the plan in force stays.")] = False,
) -> None:
    """Check a plan, upload it to every drone's companion, and start it at one common time.

    The plan starts only if every drone accepted it; otherwise the plan in force stays in force."""
    from .scenarios import load_plan

    with user_errors():
        if not (math.isfinite(start_in_s) and start_in_s >= 1.0):
            raise UserError(f"--start-in-s must be at least 1 s, got {start_in_s}")
        plan = load_plan(plan_name)
        plan.check()
        try:
            items = encode_plan(plan.spec)
        except PlanTransferError as exc:
            raise UserError(f"{plan_name}: {exc}") from None
    pid = decode_plan(items)[1]
    with swarm_link(manifest, endpoint, drone, tlog, signing_key) as (link, chosen):
        outside = [i for i in chosen if i > plan.n_agents]
        if outside:
            raise typer.Exit(_refuse(f"{plan_name}: the plan has {plan.n_agents} drones; drone {outside[0]} is not one of them"))
        outcomes = upload_all(link, chosen, items)
        if no_start or not all(ok for ok, _ in outcomes.values()):
            report(f"plan {plan.name} ({pid:08x}) uploaded, not started" if no_start else
                   f"plan {plan.name} ({pid:08x}): not started, the plan in force stays", outcomes)
            return
        start = flight_clock(link) + start_in_s
        report(f"plan {plan.name} ({pid:08x}) starts at {time.strftime('%H:%M:%S', time.localtime(start))}",
               start_all(link, chosen, pid, start))


def _refuse(sentence: str) -> int:
    err_console.print(f"triswarm: error: {sentence}", markup=False, highlight=False, soft_wrap=True)
    return 2


def download(
    drone: Annotated[int, typer.Option("--drone", metavar="N", help="The drone to read the plan from.")],
    manifest: Manifest = None, endpoint: Endpoints = None, tlog: Tlog = DEFAULT_TLOG, signing_key: SigningKey = None,
    out: Annotated[Optional[Path], typer.Option(help="Write the plan here (TOML); default: print it.")] = None,
) -> None:
    """Read back the plan a drone holds (the one in force, else the one waiting for its start)."""
    import tomli_w

    with swarm_link(manifest, endpoint, [drone], tlog, signing_key) as (link, _):
        try:
            items = missions.download(link, drone)
        except (missions.NoAnswer, PlanTransferError) as exc:
            raise typer.Exit(_refuse(f"drone {drone}: {exc}"))
    if not items:
        console.print(f"drone {drone} holds no plan")
        return
    try:
        spec, pid = decode_plan(items)
    except PlanTransferError as exc:
        raise typer.Exit(_refuse(f"drone {drone}: {exc}"))
    text = f"# plan {pid:08x}, downloaded from drone {drone}\n" + tomli_w.dumps(spec)
    if out is None:
        console.print(text, markup=False, highlight=False)
    else:
        try:
            out.write_text(text, encoding="utf-8")
        except OSError as exc:
            raise typer.Exit(_refuse(f"--out {out}: cannot write the plan ({exc.strerror})")) from None
        console.print(f"drone {drone}: plan {spec.get('name', '?')} ({pid:08x}, {len(items)} items) written to {out}")


def clear(manifest: Manifest = None, endpoint: Endpoints = None, drone: Drones = None, tlog: Tlog = DEFAULT_TLOG,
          signing_key: SigningKey = None) -> None:
    """Clear the plans the companions hold (refused while flying)."""
    with swarm_link(manifest, endpoint, drone, tlog, signing_key) as (link, chosen):
        report("plan clear", for_each(chosen, lambda i: (lambda o: (o.ok, o.detail))(missions.clear(link, i))))


# -- the leader ---------------------------------------------------------------------------------

def _leader(link: GroundLink, chosen: list[int], command: int, params: list[float], lead_s: float) -> dict:
    """Send a leader command timed lead_s ahead in plan time (read from the first drone)."""
    t_plan = link.param(chosen[0], COMP_ONBOARD, "PLAN_T_S")
    if t_plan is None or math.isnan(t_plan):
        raise typer.Exit(_refuse(f"drone {chosen[0]}: no plan in force (upload and start one first)"))
    params = params[:2] + [t_plan + lead_s] + params[3:]
    return command_all(link, chosen, COMP_ONBOARD, command, params)


@leader_app.command("goto", context_settings={"ignore_unknown_options": True})  # "-5" is a number, not an option
def leader_goto(
    x_m: Annotated[float, typer.Argument(help="x [m], north of home, in the plan's earth frame (x north, y west, z up); sent in NED.")],
    y_m: Annotated[float, typer.Argument(help="y [m], west of home.")],
    z_m: Annotated[float, typer.Argument(help="z [m], up from home.")],
    yaw: Annotated[Optional[float], typer.Option("--yaw", help="Leader yaw at the end [deg] (default: kept).")] = None,
    speed: Annotated[float, typer.Option("--speed", help="Peak speed [m/s].")] = 2.0,
    lead_s: Annotated[float, typer.Option("--lead-s", help="Start the move this long from now [s], on every drone at once.")] = 1.0,
    manifest: Manifest = None, endpoint: Endpoints = None, tlog: Tlog = DEFAULT_TLOG, signing_key: SigningKey = None,
) -> None:
    """Move the leader (and with it the formation) to a point, at a peak speed."""
    with user_errors():
        for name, v in (("X", x_m), ("Y", y_m), ("Z", z_m), ("--yaw", yaw or 0.0), ("--lead-s", lead_s)):
            if not math.isfinite(v):
                raise UserError(f"{name} must be a finite number, got {v}")
        if not (math.isfinite(speed) and 0 < speed <= 20):
            raise UserError(f"--speed must be in (0, 20] m/s, got {speed}")
    with swarm_link(manifest, endpoint, None, tlog, signing_key) as (link, chosen):
        # the wire speaks NED, as every MAVLink tool does: north, east, down; yaw clockwise from north
        north_m, east_m, down_m = (float(v) for v in flip([x_m, y_m, z_m]))
        yaw_ned_rad = math.nan if yaw is None else -math.radians(yaw)
        report(f"leader goto {x_m:g} {y_m:g} {z_m:g}", _leader(link, chosen, mavlink.MAV_CMD_TRISWARM_LEADER_GOTO,
                                                               [speed, yaw_ned_rad, 0.0, 0.0, north_m, east_m, down_m],
                                                               lead_s))


@leader_app.command("hold")
def leader_hold(
    lead_s: Annotated[float, typer.Option("--lead-s", help="Stop this long from now [s], on every drone at once.")] = 0.5,
    manifest: Manifest = None, endpoint: Endpoints = None, tlog: Tlog = DEFAULT_TLOG, signing_key: SigningKey = None,
) -> None:
    """Stop the leader where it is (it brakes to rest)."""
    with swarm_link(manifest, endpoint, None, tlog, signing_key) as (link, chosen):
        report("leader hold", _leader(link, chosen, mavlink.MAV_CMD_TRISWARM_LEADER_HOLD, [0.0, 0.0, 0.0], lead_s))


# -- vehicles -----------------------------------------------------------------------------------

def _vehicles(title: str, command: int, params: list[float], manifest, endpoint, drone, tlog, signing_key) -> None:
    with swarm_link(manifest, endpoint, drone, tlog, signing_key) as (link, chosen):
        report(title, command_all(link, chosen, COMP_AUTOPILOT, command, params))


def arm(manifest: Manifest = None, endpoint: Endpoints = None, drone: Drones = None, tlog: Tlog = DEFAULT_TLOG,
        signing_key: SigningKey = None) -> None:
    """Arm the flight controllers (on the ground)."""
    _vehicles("arm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [1.0], manifest, endpoint, drone, tlog, signing_key)


def disarm(force: Annotated[bool, typer.Option(help="Disarm in the air too (the rotors stop: it falls).")] = False,
           manifest: Manifest = None, endpoint: Endpoints = None, drone: Drones = None, tlog: Tlog = DEFAULT_TLOG,
           signing_key: SigningKey = None) -> None:
    """Disarm the flight controllers (on the ground, unless --force)."""
    _vehicles("disarm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [0.0, 21196.0 if force else 0.0],
              manifest, endpoint, drone, tlog, signing_key)


def takeoff(manifest: Manifest = None, endpoint: Endpoints = None, drone: Drones = None, tlog: Tlog = DEFAULT_TLOG,
            signing_key: SigningKey = None,
            height_m: Annotated[Optional[float], typer.Option(help="Height above home [m] for ArduPilot (default 2.5; "
                                                                   "triswarm's simulated flight controllers take off "
                                                                   "to their TKO_ALT_M).")] = None) -> None:
    """Take off with the flight controllers' own controllers and hover (a plan starting later takes
    over from there). ArduCopter is put in GUIDED first."""
    with user_errors():
        if height_m is not None and not (math.isfinite(height_m) and 0.5 <= height_m <= 100.0):
            raise UserError(f"--height-m must be between 0.5 and 100 m, got {height_m}")
    with swarm_link(manifest, endpoint, drone, tlog, signing_key) as (link, chosen):
        report("takeoff", take_off_all(link, chosen, height_m))


def land(manifest: Manifest = None, endpoint: Endpoints = None, drone: Drones = None, tlog: Tlog = DEFAULT_TLOG,
         signing_key: SigningKey = None,
         companion: Annotated[bool, typer.Option(help="The companions land the drones themselves (brake, descend at "
                                                      "their LAND_SPEED, disarm on the ground): for flight controllers "
                                                      "whose own controllers do not fly the tri-rotor, as PX4 with "
                                                      "the shipped airframe.")] = False) -> None:
    """Land where they are (the flight controllers take over, or with --companion the companions
    fly the descent; the formation flight ends)."""
    if not companion:
        _vehicles("land", mavlink.MAV_CMD_NAV_LAND, [], manifest, endpoint, drone, tlog, signing_key)
        return
    with swarm_link(manifest, endpoint, drone, tlog, signing_key) as (link, chosen):
        report("land (by the companions)", command_all(link, chosen, COMP_ONBOARD, mavlink.MAV_CMD_NAV_LAND, []))
