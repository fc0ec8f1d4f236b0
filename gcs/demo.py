"""`triswarm demo`: the paper's case study, whole stack, on this machine, driven as an operator would.

`sitl up -n 6` and the six agents' companions (one process flying all six, as simulations of a swarm
on one machine do) on loopback; the ground station uploads the plan over MAVLink, arms, takes off,
starts the plan at one common time, lets the formation fly, lands, disarms and stops every process.
With ``--autopilot ardupilot`` or ``px4`` a real firmware flies each drone between its companion and
the plant. PX4's own controllers do not fly the tri-rotor (``protocol.autopilots.flies_itself``):
there the companions' entry takes off from the ground and the companions land the drones.
In real time by default; with ``--lockstep`` on simulated time, as fast as the machine allows (the
times below are then the flight controllers' clock, which the ground station follows). The run folder gets gcs.tlog (everything the ground station
received), plan.toml, run.json, and from the log (`triswarm plot`) telemetry.csv, summary.json and
the figures. Exit 0 only if the formation met the bounds over the plan's settled window (from its
entry's end plus check.settle_s: [25 s, end] for the case study).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import math
import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.progress import BarColumn, Progress, TextColumn

from triswarm.protocol.autopilots import flies_itself, launch_mode_command
from triswarm.protocol.mavlink import COMP_AUTOPILOT, COMP_ONBOARD, mavlink
from triswarm.protocol.plan_transfer import decode_plan, encode_plan

from .errors import UserError, console, err_console, require_positive, require_settled_window, user_errors
from .link import GroundLink, LinkError
from .plot_cmd import plot
from .scenarios import DEFAULT_PLAN, PlanArgument, plan_text, read_plan_spec
from .stack import Stack, StackError
from .swarm import command_all, for_each, result_text, start_all, take_off_all, upload_all

STARTUP_S = 120.0  # companions load numba kernels and open Zenoh; two busy cores can take a while
ARM_READY_S = 120.0
"""A flight controller refuses to arm until its pre-arm checks pass: ArduCopter's EKF3 takes 40 s
of its clock from boot to a position estimate."""
FIRMWARE_RATE_HZ = 100.0
"""The companions' rate with a real firmware: what ArduPilot's script delivers to the outputs in
full (PX4's companions run at its estimator's rate whatever is asked)."""
FIRMWARE_TRUTH_BOUNDS = (0.10, 0.02)
FIRMWARE_TELEMETRY_BOUNDS = (0.25, 0.05)
"""With a real firmware the formation is judged on the plant's truth (the paper's bounds) and
never worse than these in the firmware's own telemetry (its EKF's estimates)."""
FIRMWARES = {"ardupilot": "ArduPilot", "px4": "PX4"}
FC_SILENT_S = 15.0
"""A flight controller unheard for this long [s, wall] in the formation flight is gone: the demo
stops with one sentence (a firmware that died; a simulator's lockstep can pause one for seconds)."""
COMPANION_LANDING_S = 120.0
"""The companions' landings descend at their LAND_SPEED, 0.5 m/s: 41 s from the case study's 20 m."""
SENSOR_NOISE = (("NOISE_POS_M", 0.005), ("NOISE_VEL_MS", 0.01), ("NOISE_ATT_RAD", 0.001), ("NOISE_GYRO_RADS", 0.005),
                ("NOISE_ACC_MS2", 0.1))
"""The estimators' noise the demo's flight controllers report with (1 sigma; what an RTK-GNSS-aided
EKF gives), in every message, the ground station's included."""


def _step(title: str, outcomes: dict) -> None:
    bad = {i: detail for i, (ok, detail) in outcomes.items() if not ok}
    console.print(f"{title}: " + ("[green]all drones[/]" if not bad else f"[red]refused by {bad}[/]"), soft_wrap=True)
    if bad:
        raise typer.Exit(code=1)


def _fail(sentence: str) -> typer.Exit:
    """The demo cannot go on (not the user's mistake, not a bug): one sentence, exit status 1."""
    err_console.print(f"triswarm demo: {sentence}", markup=False, highlight=False, soft_wrap=True)
    return typer.Exit(code=1)


def _wait(stack: Stack, what: str, missing, timeout_s: float) -> None:
    """Until ``missing()`` (what is still awaited, a sentence or "") is empty; stop with one sentence
    when a process of the stack stops, or after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while lack := missing():
        if (stopped := stack.stopped()) is not None:
            raise _fail(f"waiting for {what}: {stopped}")
        if time.monotonic() > deadline:
            raise _fail(f"no {what} within {timeout_s:g} s: {lack} (logs in {stack.workdir / 'logs'})")
        time.sleep(0.1)


def _until_accepted(stack: Stack, link: GroundLink, title: str, ids: list[int], command, timeout_s: float) -> None:
    """``command(drone)`` -> (command, params) or None (nothing to do) for every drone, asked again of
    those that refuse until ``timeout_s``: a flight controller refuses while its pre-arm checks fail
    (an EKF still converging); then one sentence with the reason it gave."""
    deadline = time.monotonic() + timeout_s
    todo = [i for i in ids if command(i) is not None]
    while todo:
        outcomes = for_each(todo, lambda i: result_text(*link.command(i, COMP_AUTOPILOT, command(i)[0], list(command(i)[1]))))
        todo = [i for i, (ok, _) in outcomes.items() if not ok]
        if not todo:
            break
        if (stopped := stack.stopped()) is not None:
            raise _fail(f"{title}: {stopped}")
        if time.monotonic() > deadline:
            raise _fail(f"{title} refused for {timeout_s:g} s: {({i: outcomes[i][1] for i in todo})}")
        time.sleep(2.0)
    console.print(f"{title}: [green]all drones[/]")


def _flight_problem(stack: Stack, link: GroundLink, ids: list[int], silent_s: float = FC_SILENT_S) -> str | None:
    """Why a flight cannot go on, in one sentence: a process of the stack stopped, or flight
    controllers unheard for ``silent_s`` [s, wall] (gone, though the processes run: a firmware
    that died); None while it can."""
    if (stopped := stack.stopped()) is not None:
        return stopped
    if silent := [i for i in ids if time.time() - link.autopilot(i).heartbeat_at > silent_s]:
        return f"the flight controllers of {_which(silent, f'unheard for {silent_s:g} s')} (logs in {stack.workdir / 'logs'})"
    return None


def _which(ids: list[int], state: str) -> str:
    """"drones 2, 5 <state>", or "" for none."""
    return f"{'drone' if len(ids) == 1 else 'drones'} {', '.join(map(str, ids))} {state}" if ids else ""


def demo(
    plan_name: PlanArgument = DEFAULT_PLAN,
    duration_s: Annotated[float, typer.Option("--duration-s", help="Plan time to fly before landing [s].")] = 50.0,
    out: Annotated[Optional[Path], typer.Option(help="Run folder (default runs/<time>).")] = None,
    lockstep: Annotated[bool, typer.Option(help="Fly on simulated time (sitl up --lockstep): as fast as this machine "
                                                "allows, the same however busy it is.")] = False,
    max_rtf: Annotated[Optional[float], typer.Option(help="With --lockstep: never faster than this many simulated "
                                                          "seconds per wall second (1: paced like real time, to "
                                                          "watch it, yet unharmed by a busy machine).")] = None,
    agents_per_process: Annotated[int, typer.Option(help="Agents per companion process (0: all in one).")] = 0,
    noise: Annotated[bool, typer.Option(help="The flight controllers' estimates with sensor noise (1 sigma: 5 mm, "
                                             "1 cm/s, 1 mrad, 5 mrad/s).")] = True,
    fc_profile: Annotated[str, typer.Option(help="The flight controllers stream to the companions as this autopilot "
                                                 "does (sitl up --fc-profile): px4 (estimator instants, position at "
                                                 "100 Hz, up to 1.5 ms late), ardupilot or triswarm.")] = "px4",
    autopilot: Annotated[str, typer.Option(help="The flight controllers: triswarm (simulated), ardupilot "
                                                "(ArduPilot's ArduCopter SITL firmware in the loop) or px4 (PX4's "
                                                "px4_sitl_zenoh firmware, flown over its Zenoh bridge); a firmware "
                                                "runs in real time and is judged on the plant's truth and on its "
                                                "telemetry.")] = "triswarm",
    firmware: Annotated[Optional[Path], typer.Option(
        help="With --autopilot ardupilot: the ArduCopter SITL binary (default $TRISWARM_ARDUCOPTER); with px4: the "
             "px4_sitl_zenoh build, its folder or .tar.gz (default $TRISWARM_PX4).")] = None,
) -> None:
    """A plan (the paper's case study by default), whole stack, on this machine: sitl, the companions, the ground station."""
    with user_errors():
        require_positive(duration_s=duration_s)
        if agents_per_process < 0:
            raise UserError(f"--agents-per-process must not be negative, got {agents_per_process}")
        if max_rtf is not None and not (lockstep and math.isfinite(max_rtf) and max_rtf > 0):
            raise UserError(f"--max-rtf must be a positive number and goes with --lockstep, got {max_rtf}"
                            + ("" if lockstep else " without --lockstep"))
        if autopilot not in ("triswarm", *FIRMWARES):
            raise UserError(f"--autopilot must be triswarm, ardupilot or px4, got {autopilot!r}")
        real = autopilot in FIRMWARES
        if real:
            from triswarm.sitl.firmware import find_firmware
            from triswarm.sitl.px4 import find_package

            if lockstep:
                raise UserError(f"--lockstep is for triswarm's flight controllers: {FIRMWARES[autopilot]}'s firmware "
                                "runs in real time")
            firmware = find_firmware(firmware) if autopilot == "ardupilot" else find_package(firmware)
        elif firmware is not None:
            raise UserError("--firmware goes with --autopilot ardupilot or px4")
        from triswarm.protocol.plan import plan_from_dict

        spec, label = read_plan_spec(plan_name)
        plan = plan_from_dict(spec, label)
        plan.check(horizon_s=duration_s)
        require_settled_window(plan, duration_s, "--duration-s")
    items = encode_plan(plan.spec)
    pid = decode_plan(items)[1]
    run = out or Path("runs") / _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    try:
        run.mkdir(parents=True, exist_ok=True)
        (run / "plan.toml").write_text(plan_text(plan_name), encoding="utf-8")
    except OSError as exc:
        err_console.print(f"triswarm: error: cannot write the run folder {run}: {exc.strerror}", markup=False,
                          soft_wrap=True)
        raise typer.Exit(code=2) from None
    n = plan.n_agents
    window = f"[{plan.settled_from_s:g} s, {duration_s:g} s]"
    console.print(f"[bold]triswarm demo[/]: {plan.name}, {n} drones, {duration_s:g} s of formation flight -> {run}")
    if real:
        console.print(f"{FIRMWARES[autopilot]}'s firmware ({firmware}) flying triswarm's plant, its EKF's estimates "
                      f"what the companions fly on; it passes if every drone stays within {FIRMWARE_TRUTH_BOUNDS[0]:g} m "
                      f"and {FIRMWARE_TRUTH_BOUNDS[1]:g} rad of its place over {window} in truth, and "
                      f"{FIRMWARE_TELEMETRY_BOUNDS[0]:g} m and {FIRMWARE_TELEMETRY_BOUNDS[1]:g} rad in its "
                      "telemetry", soft_wrap=True)
    else:
        console.print(f"flight controllers streaming as {fc_profile}, "
                      + ("with sensor noise (1 sigma: " + ", ".join(f"{k}={v:g}" for k, v in SENSOR_NOISE) + ")" if noise
                         else "without sensor noise")
                      + f"; it passes if every drone stays within 0.10 m and 0.02 rad of its place over {window}",
                      soft_wrap=True)
    with contextlib.ExitStack() as running:
        try:
            if real:
                sitl_args, stack_args = ["--seed", "1"], {"autopilot": autopilot, "firmware": firmware,
                                                          "rate_hz": FIRMWARE_RATE_HZ}
            else:
                sitl_args = ["--fc-profile", fc_profile, "--seed", "1"] + ([] if max_rtf is None else ["--max-rtf", f"{max_rtf:g}"])
                sitl_args += [a for name, value in SENSOR_NOISE if noise for a in ("--param", f"{name}={value:g}")]
                stack_args = {}
            stack = running.enter_context(Stack(None, run / "stack", n, lockstep=lockstep,
                                                agents_per_process=agents_per_process, sitl_args=sitl_args, **stack_args))
        except StackError as exc:
            raise _fail(f"the stack did not start: {exc}") from None
        try:
            link = running.enter_context(GroundLink(stack.endpoints(), tlog=run / "gcs.tlog",
                                                    fc_endpoints=stack.fc_endpoints()))
        except LinkError as exc:
            raise _fail(f"the ground station's link did not open: {exc}") from None
        ids = list(range(1, n + 1))
        console.print(f"sitl and {n} companions started (logs in {run / 'stack' / 'logs'})")

        def silent() -> str:
            quiet = [i for i in ids if not (link.companion(i).heartbeat and link.autopilot(i).heartbeat)]
            return _which(quiet, "not heard")

        _wait(stack, "heartbeat from every drone and companion", silent, STARTUP_S)
        _step("plan upload", upload_all(link, ids, items))
        kind = {i: link.autopilot(i).heartbeat.autopilot for i in ids}
        _until_accepted(stack, link, "ready to take off", ids, lambda i: launch_mode_command(kind[i]), ARM_READY_S)
        _until_accepted(stack, link, "arm", ids, lambda i: (mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (1.0,)), ARM_READY_S)
        by_companion = [i for i in ids if not flies_itself(kind[i])]
        if by_companion:  # (they take off with the entry, at the start)
            console.print(f"takeoff: by the companions' entry at the start ({_which(by_companion, 'on the ground')})")
            _step("clock (SYSTEM_TIME at 1 Hz)", command_all(link, by_companion, COMP_AUTOPILOT,
                                                             mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                                                             [float(mavlink.MAVLINK_MSG_ID_SYSTEM_TIME), 1e6]))
        if by_itself := [i for i in ids if i not in by_companion]:
            _step("takeoff", take_off_all(link, by_itself))
            _wait(stack, "hover after takeoff", lambda: _which(
                [i for i in by_itself if link.autopilot(i).landed_state != mavlink.MAV_LANDED_STATE_IN_AIR],
                "not in the air"), 30.0)
        _wait(stack, "time from the flight controllers' clock",
              lambda: "no SYSTEM_TIME heard" if math.isnan(link.fc_now()) else "", 30.0)
        _step("local origins (logged: positions are judged from the swarm's home)",
              command_all(link, ids, COMP_AUTOPILOT, mavlink.MAV_CMD_REQUEST_MESSAGE,
                          [float(mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)]))
        start = link.fc_now() + 3.0
        _step("plan start", start_all(link, ids, pid, start))
        (run / "run.json").write_text(json.dumps({"start_unix_s": start, "plan_id": pid, "drones": n,
                                                  "home": stack.manifest["home"], "endpoints": stack.endpoints()},
                                                 indent=2) + "\n", encoding="utf-8")
        with Progress(TextColumn("formation flight"), BarColumn(), TextColumn("t = {task.completed:5.1f} / {task.total:g} s"),
                      TextColumn("{task.fields[errors]}"), console=console) as bar:
            task = bar.add_task("", total=duration_s, errors="")
            while (t := link.fc_now() - start) < duration_s:
                if (problem := _flight_problem(stack, link, ids)) is not None:
                    raise _fail(f"formation flight: {problem}")
                errs = [link.companion(i).named.get("FORM_ERRM", (float("nan"),))[0] for i in ids]
                bar.update(task, completed=max(0.0, t), errors="error " + " ".join(f"{e:.2f}" for e in errs) + " m")
                time.sleep(0.25)
            bar.update(task, completed=duration_s)
        info = json.loads((run / "run.json").read_text())
        info["formation_end_s"] = link.fc_now() - start
        (run / "run.json").write_text(json.dumps(info, indent=2) + "\n", encoding="utf-8")
        if by_itself:
            _step("land", command_all(link, by_itself, COMP_AUTOPILOT, mavlink.MAV_CMD_NAV_LAND, []))
        if by_companion:  # (each lands its drone and disarms it on the ground)
            _step("land (by the companions)", command_all(link, by_companion, COMP_ONBOARD, mavlink.MAV_CMD_NAV_LAND, []))
        _wait(stack, "landing and disarm", lambda: _which(
            [i for i in ids if link.autopilot(i).heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED], "still armed"),
            COMPANION_LANDING_S if by_companion else 60.0)
        if by_itself:
            _step("disarm", command_all(link, by_itself, COMP_AUTOPILOT, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [0.0]))
    console.print("every process stopped; making the figures from the log")
    if real:
        plot(run, position_bound_m=FIRMWARE_TELEMETRY_BOUNDS[0], attitude_bound_rad=FIRMWARE_TELEMETRY_BOUNDS[1],
             truth_position_bound_m=FIRMWARE_TRUTH_BOUNDS[0], truth_attitude_bound_rad=FIRMWARE_TRUTH_BOUNDS[1])
    else:
        plot(run)
