"""`triswarm sim`: a plan flown in-process, N simulated tri-rotors and their controllers in one process."""

from __future__ import annotations

import datetime as _dt
import math
import tempfile
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from .errors import UserError, console, err_console, finite_option, short_number, user_errors
from .scenarios import DEFAULT_PLAN, PlanArgument
from .wind_options import Gusts, Turbulence, WindFrom, WindSpeed, wind_from_options


def _writable_folder(path: Path) -> None:
    """Make the output folder ``path`` (--out) and check that files can be written in it; UserError if not."""
    if path.exists() and not path.is_dir():
        raise UserError(f"--out {path}: not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        raise UserError(f"--out {path}: cannot write in this folder ({exc.strerror})") from None


def _default_out(name: str) -> Path:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"sim-{name}-{stamp}"


def sim(
    plan_name: PlanArgument = DEFAULT_PLAN,
    duration_s: Annotated[Optional[float], typer.Option("--duration-s", help="Simulated time [s] (default: the plan's "
                                                                             "duration_s, 60 s unless the plan says).")] = None,
    out: Annotated[Optional[Path], typer.Option(help="Output folder (default runs/sim-<plan name>-<time>).")] = None,
    drones: Annotated[Optional[int], typer.Option(help="Number of drones (rotating-polygon plans only; the circle grows "
                                                       "to keep neighbours apart, see docs/formations.md).")] = None,
    servo_delay_s: Annotated[Optional[float], typer.Option("--servo-delay-s", help="Simulated servo delay [s] (default: the plan airframe's, 0.01).")] = None,
    max_rpm: Annotated[Optional[float], typer.Option(help="Simulated motor limit [RPM] (default: the plan airframe's).")] = None,
    servo_rate_deg_s: Annotated[Optional[float], typer.Option(
        "--servo-rate-deg-s", help="Simulated servo speed [deg/s]: a servo turns towards its delayed command at most "
                                   "this fast (600 is 0.1 s per 60 deg; 0: at once; default: the plan airframe's, "
                                   "at once).")] = None,
    latency_s: Annotated[Optional[float], typer.Option(
        "--latency-s", help="Simulated latency [s]: how long after a measurement's stamp the command that answers "
                            "it reaches the plant (default: the plan's [controller] latency_s, which the "
                            "controllers compensate).")] = None,
    noise: Annotated[bool, typer.Option(help="Sensor noise: position 0.02 m, attitude 0.005 rad (1 sigma).")] = False,
    estimator: Annotated[Optional[str], typer.Option(
        metavar="PROFILE", help="What the controllers measure, as an autopilot's estimator with this positioning "
                                "reports it (lag, wandering bias, noise): truth, mocap, rtk or gps "
                                "(docs/wind.md#estimates-as-autopilots-give-them).")] = None,
    mismatch: Annotated[float, typer.Option(help="Plant mass/inertia +PCT %, k_f -PCT/2 % against the controller's model.")] = 0.0,
    seed: Annotated[int, typer.Option(help="Seed for start positions, noise and turbulence.")] = 0,
    wind_m_s: WindSpeed = None,
    wind_from_deg: WindFrom = None,
    turbulence: Turbulence = None,
    gust: Gusts = None,
    physics_hz: Annotated[float, typer.Option(help="Physics (RK4) rate [Hz].")] = 1000.0,
    log_hz: Annotated[float, typer.Option(help="Telemetry rows per second per drone.")] = 50.0,
    position_bound_m: Annotated[float, typer.Option(help="Position bound for the verdict [m].")] = 0.10,
    attitude_bound_rad: Annotated[float, typer.Option(help="Attitude bound for the verdict [rad].")] = 0.02,
    strict: Annotated[bool, typer.Option(help="Exit 1 if the formation misses the bounds over the settled window "
                                              "(from the entry's end + check.settle_s, 25 s for the case study; the "
                                              "second half of a flight that ends before that).")] = False,
    force: Annotated[bool, typer.Option(help="Fly even a plan that plan check refuses for its switching certificate or "
                                             "its separation (to see what would happen).")] = False,
    figures: Annotated[bool, typer.Option(help="Write the PNG figures.")] = True,
) -> None:
    """Fly a plan in-process: N simulated tri-rotors and their controllers in one process."""
    from .scenarios import load_plan

    with user_errors():
        finite_option("duration-s", duration_s, positive=True)
        finite_option("servo-delay-s", servo_delay_s, non_negative=True)
        finite_option("max-rpm", max_rpm, positive=True)
        finite_option("servo-rate-deg-s", servo_rate_deg_s, non_negative=True)
        finite_option("latency-s", latency_s, non_negative=True)
        from triswarm.protocol.plan import MAX_LATENCY_S

        if latency_s is not None and latency_s > MAX_LATENCY_S:
            raise UserError(f"--latency-s must be at most {MAX_LATENCY_S:g} s, got {latency_s:g}")
        if not (math.isfinite(mismatch) and -50 < mismatch < 100):
            raise UserError(f"--mismatch must be a percentage above -50 and below 100, got {mismatch}")
        finite_option("physics-hz", physics_hz, positive=True)
        finite_option("log-hz", log_hz, positive=True)
        finite_option("position-bound-m", position_bound_m, positive=True)
        finite_option("attitude-bound-rad", attitude_bound_rad, positive=True)
        if drones is not None and drones < 1:
            raise UserError(f"--drones must be at least 1, got {drones}")
        from triswarm.sitl.estimator import profile

        try:
            est = None if estimator is None else profile(estimator)
        except ValueError as exc:
            raise UserError(f"--estimator: {exc}") from None
        if est is not None and noise:
            raise UserError("--noise and --estimator both say what the controllers measure: give one")
        plan = load_plan(plan_name, drones)
        wind = wind_from_options(plan.wind, wind_m_s, wind_from_deg, turbulence, gust)
        rate = plan.controller.rate_hz
        steps = round(physics_hz / rate)
        if steps < 1 or abs(steps * rate - physics_hz) > 1e-6 * physics_hz:
            raise UserError(f"--physics-hz {physics_hz:g} must be a whole multiple of the plan's control rate {rate:g} Hz")
        duration = plan.duration_s if duration_s is None else duration_s
        # (the flight's modules once the flags are known good: a mistake is said in half the time)
        from triswarm.protocol import metrics
        from triswarm.sitl.simulation import SensorNoise, SimConfig, command_latency_s, simulate

        from . import plots, report

        config = SimConfig(duration_s=duration, physics_hz=physics_hz, log_hz=log_hz, servo_delay_s=servo_delay_s,
                           max_rpm=max_rpm, servo_rate_deg_s=servo_rate_deg_s, noise=SensorNoise() if noise else None,
                           mismatch_pct=mismatch, seed=seed, wind=wind, estimator=est, latency_s=latency_s)
        design = plan.check_formation(horizon_s=duration)
        problems = plan.safety_problems(horizon_s=duration)
        if problems and not force:
            raise UserError(f"{plan.source}: {problems[0]} (--force flies it anyway)")
        out_dir = out or _default_out(plan.name)
        _writable_folder(out_dir)  # before the flight, not after it

    for problem in problems:
        err_console.print(f"triswarm: warning: {plan.source}: {problem}; flying it anyway (--force)", soft_wrap=True)
    told_deg_s = math.degrees(plan.airframe.servo_rate_rad_s)
    if servo_rate_deg_s and not math.isclose(servo_rate_deg_s, told_deg_s, rel_tol=1e-9):
        told = f"{told_deg_s:g} deg/s" if told_deg_s else "at once"
        err_console.print(f"triswarm: note: the simulated servos turn at {servo_rate_deg_s:g} deg/s and the controllers "
                          f"fly them as the plan's airframe says ({told}); [airframe] servo_rate_rad_s tells them "
                          "(docs/wind.md#servos-of-finite-speed)", soft_wrap=True, markup=False)
    console.print(f"[bold]{plan.name}[/]: {plan.n_agents} drones, {duration:g} s, c = {design.c:.3g}, "
                  f"lambda_R = {design.lambda_R:.3g}, topologies {', '.join(design.topology_names)}")
    with Progress(TextColumn("simulating"), BarColumn(), TextColumn("{task.fields[t]:6.1f} / {task.total:g} s"),
                  TimeElapsedColumn(), console=console, transient=False) as bar:
        task = bar.add_task("sim", total=duration, t=0.0)
        result = simulate(plan, config, progress=lambda t: bar.update(task, completed=t, t=t))

    perf, per_drone = metrics.judge(plan, result.t_s, result.position_m, result.euler_rad,
                                    metrics.settled_window_start_s(plan, duration),  # (a diverged flight ends early)
                                    position_bound_m, attitude_bound_rad)
    for i, row in enumerate(per_drone):
        row.update(thrust_scale_estimate=float(result.thrust_scale[i]),
                   max_servo_angle_deg=float(math.degrees(abs(result.alpha_rad[:, i]).max())),
                   max_rotor_speed_rpm=float(result.omega_rad_s[:, i].max() * 60 / (2 * math.pi)))
    run = {
        "duration_s": duration, "physics_hz": physics_hz, "control_hz": plan.controller.rate_hz, "log_hz": log_hz,
        "servo_delay_s": result.plant_airframe.servo_delay_s,
        "servo_rate_deg_s": math.degrees(result.plant_airframe.servo_rate_rad_s), "max_rpm": result.plant_airframe.max_rotor_speed_rad_s * 60 / (2 * math.pi),
        "controller_servo_delay_s": plan.airframe.servo_delay_s, "latency_s": command_latency_s(plan, config),
        "controller_latency_s": plan.controller.latency_s,
        "noise": None if config.noise is None else {"position_m": config.noise.position_m, "attitude_rad": config.noise.attitude_rad},
        "mismatch_pct": mismatch, "seed": seed, "wind": None if wind is None else wind.describe(), "wall_time_s": result.wall_s, "diverged_at_s": result.diverged_at_s,
        "start_position_m": result.start_position_m.tolist(),
    }
    with user_errors():
        try:
            report.write_summary(out_dir / "summary.json", plan=plan, design=design, performance=perf, run=run,
                                 per_drone=per_drone)
            report.write_telemetry(out_dir / "telemetry.csv", result.t_s, result.position_m, result.euler_rad)
            fig_paths = plots.make_figures(out_dir, plan, result.t_s, result.position_m, result.euler_rad, perf) \
                if figures else []
        except OSError as exc:
            raise UserError(f"{out_dir}: cannot write the outputs ({exc.strerror})") from None

    _print_result(plan, perf, per_drone, result, out_dir, fig_paths)
    if strict and not perf.within_bounds:
        raise typer.Exit(code=1)


def _print_result(plan, perf, per_drone, result, out_dir: Path, fig_paths: list[Path]) -> None:
    table = Table(title=f"{plan.name}: worst errors over [{perf.window_start_s:g} s, end]")
    table.add_column("drone", justify="right")
    table.add_column("pos [m]", justify="right")
    table.add_column("att [rad]", justify="right")
    table.add_column("servo max [deg]", justify="right")
    table.add_column("rotor max [RPM]", justify="right")
    shown = per_drone if len(per_drone) <= 20 else per_drone[:10] + per_drone[-5:]
    for row in shown:
        table.add_row(str(row["drone"]), short_number(row["worst_position_error_m"]),
                      short_number(row["worst_attitude_error_rad"]),
                      f"{row['max_servo_angle_deg']:.1f}", f"{row['max_rotor_speed_rpm']:.0f}")
    console.print(table)
    verdict = "[green]within[/]" if perf.within_bounds else "[red]outside[/]"
    conv = ("did not settle within them" if perf.convergence_time_s is None
            else f"within them from {perf.convergence_time_s:.2f} s")
    console.print(f"formation {verdict} {perf.position_bound_m:g} m / {perf.attitude_bound_rad:g} rad "
                  f"(worst {short_number(perf.worst_position_m)} m, drone {perf.worst_position_drone}; "
                  f"{short_number(perf.worst_attitude_rad)} rad, drone {perf.worst_attitude_drone}); {conv}; "
                  f"wall time {result.wall_s:.1f} s")
    if result.diverged_at_s is not None:
        console.print(f"[red]the simulation stopped at t = {result.diverged_at_s:.2f} s: a drone's state left the valid range[/]")
    console.print(f"outputs in {out_dir}/: summary.json, telemetry.csv" +
                  ("".join(f", {p.name}" for p in fig_paths)))


