"""`triswarm plot RUN`: the figures and data of a whole-stack run, from its ground station's MAVLink log."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer
from rich.table import Table

from .errors import UserError, console, require_positive, short_number, user_errors
from .scenarios import load_plan

if TYPE_CHECKING:
    from triswarm.protocol import metrics

    from .runlog import RunLog

RUN_FILES = ("gcs.tlog", "plan.toml", "run.json")
TRUTH_FILES = ("truth.csv", "stack/truth.csv")
"""Where a run keeps its plant's truth, when its flight controllers were a firmware (the demo's stack folder)."""
LOG_HZ = 50.0


def plot(
    run: Annotated[Path, typer.Argument(help="Run folder with gcs.tlog, plan.toml and run.json.")],
    window_start_s: Annotated[Optional[float], typer.Option(
        "--window-start-s", help="Judge the formation over [S, end] of plan time [s] (default: the plan's settled "
                                 "window, from its entry's end plus check.settle_s).")] = None,
    end_s: Annotated[Optional[float], typer.Option("--end-s", help="End of the formation flight in plan time [s] "
                                                   "(default: run.json's formation_end_s, else the end of the log).")] = None,
    position_bound_m: Annotated[float, typer.Option("--position-bound-m", help="Position bound for the verdict [m].")] = 0.10,
    attitude_bound_rad: Annotated[float, typer.Option("--attitude-bound-rad", help="Attitude bound for the verdict [rad].")] = 0.02,
    truth_position_bound_m: Annotated[Optional[float], typer.Option(
        help="With the plant's truth (RUN/truth.csv or RUN/stack/truth.csv, from a firmware in the loop): its "
             "position bound [m] (default: --position-bound-m).")] = None,
    truth_attitude_bound_rad: Annotated[Optional[float], typer.Option(
        help="The truth's attitude bound [rad] (default: --attitude-bound-rad).")] = None,
) -> None:
    """Write RUN/telemetry.csv, RUN/summary.json and the figures from RUN/gcs.tlog; exit 1 if the
    formation missed the bounds (in the flight controllers' telemetry, and in the plant's truth
    where the run has one)."""
    from triswarm.protocol import metrics

    from . import plots, report
    from .runlog import read_run_log
    from .tracks import on_grid
    from .truth import read_truth

    with user_errors():
        if window_start_s is not None and not math.isfinite(window_start_s):
            raise UserError(f"--window-start-s must be a finite number, got {window_start_s}")
        require_positive(position_bound_m=position_bound_m, attitude_bound_rad=attitude_bound_rad)
        truth_bounds = (truth_position_bound_m or position_bound_m, truth_attitude_bound_rad or attitude_bound_rad)
        require_positive(truth_position_bound_m=truth_bounds[0], truth_attitude_bound_rad=truth_bounds[1])
        if not run.is_dir():
            raise UserError(f"{run}: no such run folder")
        for name in RUN_FILES:
            if not (run / name).is_file():
                raise UserError(f"{run}: not a run folder: it has no {name}")
        start_unix_s, formation_end_s, home_lla = _run_info(run / "run.json")
        if end_s is None:
            end_s = formation_end_s
        elif not math.isfinite(end_s):
            raise UserError(f"--end-s must be a finite number, got {end_s}")
        plan = load_plan(str(run / "plan.toml"))
        design = plan.design
        try:
            log = read_run_log(run / "gcs.tlog", plan.n_agents, start_unix_s, LOG_HZ, home_lla)
        except OSError as exc:
            raise UserError(f"{run / 'gcs.tlog'}: cannot read it ({exc.strerror})") from None

    if end_s is not None:  # the landing is not formation flight
        keep = log.t_s <= end_s
        log = dataclasses.replace(log, t_s=log.t_s[keep], position_m=log.position_m[keep], euler_rad=log.euler_rad[keep])
    if window_start_s is None:
        window_start_s = metrics.settled_window_start_s(plan, float(log.t_s[-1]))
    perf, per_drone = metrics.judge(plan, log.t_s, log.position_m, log.euler_rad, window_start_s, position_bound_m,
                                    attitude_bound_rad)
    _add_log_columns(per_drone, log)
    truth = None
    truth_path = next((run / name for name in TRUTH_FILES if (run / name).is_file()), None)
    if truth_path is not None:
        with user_errors():
            tracks = read_truth(truth_path, [d.boot_offset_s for d in log.drones], start_unix_s)
        position_t, euler_t = on_grid(tracks, log.t_s)
        perf_t, per_drone_t = metrics.judge(plan, log.t_s, position_t, euler_t, window_start_s, *truth_bounds)
        _add_log_columns(per_drone_t, log)
        truth = {"source": str(truth_path.relative_to(run)), "performance": perf_t.as_dict(),
                 "per_drone": per_drone_t, "perf": perf_t}
    run_entry = {
        "source": "tlog", "tlog": "gcs.tlog", "start_unix_s": start_unix_s, "log_hz": LOG_HZ,
        "span_s": [float(log.t_s[0]), float(log.t_s[-1])], "frames": log.tlog.frames,
        "skipped_bytes": log.tlog.skipped_bytes, "skipped_runs": log.tlog.skipped_runs, "unknown_messages": log.tlog.unknown,
    }
    with user_errors():
        try:
            report.write_summary(run / "summary.json", plan=plan, design=design, performance=perf, run=run_entry,
                                 per_drone=per_drone,
                                 truth=None if truth is None else {k: v for k, v in truth.items() if k != "perf"})
            report.write_telemetry(run / "telemetry.csv", log.t_s, log.position_m, log.euler_rad)
            fig_paths = plots.make_figures(run, plan, log.t_s, log.position_m, log.euler_rad, perf)
        except OSError as exc:
            raise UserError(f"{run}: cannot write the outputs ({exc.strerror})") from None

    _print_result(plan.name, perf, per_drone, log, run, fig_paths, "the flight controllers' telemetry")
    if truth is not None:
        _print_result(plan.name, truth["perf"], truth["per_drone"], log, run, [], f"the plant's truth ({truth['source']})")
    if not perf.within_bounds or (truth is not None and not truth["perf"].within_bounds):
        raise typer.Exit(code=1)


def _run_info(path: Path) -> tuple[float, float | None, tuple[float, float, float] | None]:
    """run.json's start_unix_s (the plan's start, Unix seconds), formation_end_s (plan time, or None)
    and home (the swarm's: lat_deg, lon_deg, alt_m; or None)."""
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        info = None
    if not isinstance(info, dict):
        raise UserError(f"{path}: cannot be read as a JSON object")
    start, end = info.get("start_unix_s"), info.get("formation_end_s")
    if not _number(start):
        raise UserError(f"{path}: start_unix_s must be the plan's start as a number of Unix seconds, got {start!r}")
    if end is not None and not _number(end):
        raise UserError(f"{path}: formation_end_s must be a number of seconds of plan time, got {end!r}")
    home = info.get("home")
    if home is None:
        return float(start), None if end is None else float(end), None
    from triswarm.protocol.frames import LocalProjection

    try:
        home_lla = tuple(home[k] for k in ("lat_deg", "lon_deg", "alt_m"))
        if not all(map(_number, home_lla)):
            raise ValueError
        LocalProjection(*home_lla)
    except (TypeError, KeyError, ValueError):  # not an object of three numbers, or no place on Earth
        raise UserError(f"{path}: home must be {{lat_deg, lon_deg, alt_m}}, a place on Earth, got {home!r}") from None
    return float(start), None if end is None else float(end), home_lla


def _number(x: object) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x)


def _add_log_columns(per_drone: list[dict], log: RunLog) -> None:
    """What the log says of each drone's telemetry, beside its verdict."""
    for row, drone in zip(per_drone, log.drones):
        row.update(attitude_samples=drone.attitude_samples, position_samples=drone.position_samples,
                   largest_gap_s=drone.largest_gap_s, clock=drone.clock)


def _print_result(name: str, perf: metrics.Performance, per_drone: list[dict], log: RunLog, run: Path,
                  fig_paths: list[Path], source: str) -> None:
    judged = bool((log.t_s >= perf.window_start_s).any())
    table = Table(title=f"{name}: worst errors over [{perf.window_start_s:g} s, {log.t_s[-1]:.1f} s] of {source}"
                  if judged else f"{name}: {source}, to {log.t_s[-1]:.1f} s")
    table.add_column("drone", justify="right")
    table.add_column("pos [m]", justify="right")
    table.add_column("att [rad]", justify="right")
    table.add_column("largest gap [s]", justify="right")
    table.add_column("verdict")
    for row in per_drone:
        table.add_row(str(row["drone"]), short_number(row["worst_position_error_m"]),
                      short_number(row["worst_attitude_error_rad"]),
                      f"{row['largest_gap_s']:.2f}", "[green]within[/]" if row["within_bounds"] else
                      "[red]outside[/]" if judged else "[red]not judged[/]")
    console.print(table)
    if not judged:
        console.print(f"formation [red]not judged[/]: the telemetry ends at {log.t_s[-1]:.1f} s of plan time, before "
                      f"the settled window starts at {perf.window_start_s:g} s (fly longer, or judge from earlier: "
                      f"triswarm plot {run} --window-start-s S)")
    else:
        verdict = "[green]within[/]" if perf.within_bounds else "[red]outside[/]"
        console.print(f"formation ({source}) {verdict} {perf.position_bound_m:g} m / {perf.attitude_bound_rad:g} rad "
                      f"(worst {short_number(perf.worst_position_m)} m, drone {perf.worst_position_drone}; "
                      f"{short_number(perf.worst_attitude_rad)} rad, drone {perf.worst_attitude_drone})")
    if log.tlog.skipped_bytes:
        console.print(f"gcs.tlog: {log.tlog.frames} frames read; {log.tlog.skipped_bytes} bytes skipped "
                      f"in {log.tlog.skipped_runs} places (garbage or broken frames)")
    if fig_paths:
        console.print(f"outputs in {run}/: summary.json, telemetry.csv" + "".join(f", {p.name}" for p in fig_paths))
