"""triswarm: the operator's command line."""

from __future__ import annotations

import datetime as _dt
import math
import sys
import tempfile
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from triswarm.protocol.frames import DEFAULT_HOME

from .errors import UserError, console, err_console, short_number, user_errors
from .plan_cmd import plan_app
from .scenarios import DEFAULT_PLAN, PlanArgument
from .wind_options import Gusts, Turbulence, WindFrom, WindSpeed, wind_from_options

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


def _finite(name: str, value: float | None, *, positive: bool = False, non_negative: bool = False) -> None:
    if value is None:
        return
    if not math.isfinite(value):
        raise UserError(f"--{name} must be a finite number, got {value}")
    if positive and value <= 0:
        raise UserError(f"--{name} must be positive, got {value}")
    if non_negative and value < 0:
        raise UserError(f"--{name} must not be negative, got {value}")


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


@app.command()
def sim(
    plan_name: PlanArgument = DEFAULT_PLAN,
    duration_s: Annotated[Optional[float], typer.Option("--duration-s", help="Simulated time [s] (default: the plan's "
                                                                             "duration_s, 60 s unless the plan says).")] = None,
    out: Annotated[Optional[Path], typer.Option(help="Output folder (default runs/sim-<plan name>-<time>).")] = None,
    drones: Annotated[Optional[int], typer.Option(help="Number of drones (rotating-polygon plans only; the circle grows "
                                                       "to keep neighbours apart, see docs/formations.md).")] = None,
    servo_delay_s: Annotated[Optional[float], typer.Option("--servo-delay-s", help="Simulated servo delay [s] (default: the plan airframe's, 0.01).")] = None,
    max_rpm: Annotated[Optional[float], typer.Option(help="Simulated motor limit [RPM] (default: the plan airframe's).")] = None,
    noise: Annotated[bool, typer.Option(help="Sensor noise: position 0.02 m, attitude 0.005 rad (1 sigma).")] = False,
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
        _finite("duration-s", duration_s, positive=True)
        _finite("servo-delay-s", servo_delay_s, non_negative=True)
        _finite("max-rpm", max_rpm, positive=True)
        if not (math.isfinite(mismatch) and -50 < mismatch < 100):
            raise UserError(f"--mismatch must be a percentage above -50 and below 100, got {mismatch}")
        _finite("physics-hz", physics_hz, positive=True)
        _finite("log-hz", log_hz, positive=True)
        _finite("position-bound-m", position_bound_m, positive=True)
        _finite("attitude-bound-rad", attitude_bound_rad, positive=True)
        if drones is not None and drones < 1:
            raise UserError(f"--drones must be at least 1, got {drones}")
        plan = load_plan(plan_name, drones)
        wind = wind_from_options(plan.wind, wind_m_s, wind_from_deg, turbulence, gust)
        rate = plan.controller.rate_hz
        steps = round(physics_hz / rate)
        if steps < 1 or abs(steps * rate - physics_hz) > 1e-6 * physics_hz:
            raise UserError(f"--physics-hz {physics_hz:g} must be a whole multiple of the plan's control rate {rate:g} Hz")
        duration = plan.duration_s if duration_s is None else duration_s
        # (the flight's modules once the flags are known good: a mistake is said in half the time)
        from triswarm.protocol import metrics
        from triswarm.sitl.simulation import SensorNoise, SimConfig, simulate

        from . import plots, report

        config = SimConfig(duration_s=duration, physics_hz=physics_hz, log_hz=log_hz, servo_delay_s=servo_delay_s,
                           max_rpm=max_rpm, noise=SensorNoise() if noise else None, mismatch_pct=mismatch, seed=seed,
                           wind=wind)
        design = plan.check_formation(horizon_s=duration)
        problems = plan.safety_problems(horizon_s=duration)
        if problems and not force:
            raise UserError(f"{plan.source}: {problems[0]} (--force flies it anyway)")
        out_dir = out or _default_out(plan.name)
        _writable_folder(out_dir)  # before the flight, not after it

    for problem in problems:
        err_console.print(f"triswarm: warning: {plan.source}: {problem}; flying it anyway (--force)", soft_wrap=True)
    console.print(f"[bold]{plan.name}[/]: {plan.n_agents} drones, {duration:g} s, c = {design.c:.3g}, "
                  f"lambda_R = {design.lambda_R:.3g}, topologies {', '.join(design.topology_names)}")
    with Progress(TextColumn("simulating"), BarColumn(), TextColumn("{task.fields[t]:6.1f} / {task.total:g} s"),
                  TimeElapsedColumn(), console=console, transient=False) as bar:
        task = bar.add_task("sim", total=duration, t=0.0)
        result = simulate(plan, config, progress=lambda t: bar.update(task, completed=t, t=t))

    pos_err, att_err = metrics.formation_errors(plan, result.t_s, result.position_m, result.euler_rad)
    window = plan.settled_from_s if plan.settled_from_s < duration else 0.5 * duration
    perf = metrics.assess(result.t_s, pos_err, att_err, window_start_s=window, position_bound_m=position_bound_m,
                          attitude_bound_rad=attitude_bound_rad)
    per_drone = []
    in_window = result.t_s >= window
    for i in range(plan.n_agents):
        per_drone.append({
            "drone": i + 1,
            "worst_position_error_m": float(pos_err[in_window, i].max()) if in_window.any() else None,
            "worst_attitude_error_rad": float(att_err[in_window, i].max()) if in_window.any() else None,
            "thrust_scale_estimate": float(result.thrust_scale[i]),
            "max_servo_angle_deg": float(math.degrees(abs(result.alpha_rad[:, i]).max())),
            "max_rotor_speed_rpm": float(result.omega_rad_s[:, i].max() * 60 / (2 * math.pi)),
        })
    run = {
        "duration_s": duration, "physics_hz": physics_hz, "control_hz": plan.controller.rate_hz, "log_hz": log_hz,
        "servo_delay_s": result.plant_airframe.servo_delay_s, "max_rpm": result.plant_airframe.max_rotor_speed_rad_s * 60 / (2 * math.pi),
        "controller_servo_delay_s": plan.airframe.servo_delay_s,
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


sitl_app = typer.Typer(no_args_is_help=True, add_completion=False, rich_markup_mode=None,
                       help="Simulated tri-rotor flight controllers that speak MAVLink.")
app.add_typer(sitl_app, name="sitl")


@sitl_app.command("up")
def sitl_up(
    n: Annotated[int, typer.Option("-n", "--vehicles", help="Number of vehicles (sysid K..K+N-1, K = --first-id).")] = 1,
    first_id: Annotated[int, typer.Option("--first-id", help="System id of the first vehicle (a swarm split over "
                                                             "several hosts).")] = 1,
    manifest: Annotated[Path, typer.Option(help="Where to write the manifest JSON.")] = Path("sitl-manifest.json"),
    home: Annotated[str, typer.Option(help="Swarm home LAT,LON,ALT_M (the local origin, on the ground).")] = ",".join(f"{x:g}" for x in DEFAULT_HOME),
    speedup: Annotated[float, typer.Option(help="Run physics and streams K times faster than real time.")] = 1.0,
    rate_hz: Annotated[Optional[float], typer.Option(help="ATTITUDE and LOCAL_POSITION_NED rate on companion links [Hz] "
                                                          "(default: the profile's).")] = None,
    fc_profile: Annotated[str, typer.Option(help="Stream on the companion links as this autopilot does: triswarm, px4 "
                                                 "(Onboard mode) or ardupilot (Copter): messages, default rates, "
                                                 "stamps, delays, SET_MESSAGE_INTERVAL limits.")] = "triswarm",
    physics_hz: Annotated[float, typer.Option(help="Physics (RK4) rate [Hz].")] = 1000.0,
    base_port: Annotated[int, typer.Option(help="UDP port of vehicle 1's companion link; vehicle i uses base+2(i-1) "
                                                "(companion) and base+2(i-1)+1 (gcs). 0: any free ports.")] = 14600,
    bind: Annotated[str, typer.Option(help="Address to bind the UDP links to.")] = "127.0.0.1",
    spacing_m: Annotated[float, typer.Option(help="Distance between vehicles on the ground [m].")] = 2.5,
    stats: Annotated[Optional[Path], typer.Option(help="Write link and drop counters here at exit (JSON).")] = None,
    duration_s: Annotated[Optional[float], typer.Option("--duration-s", help="Stop by itself after this simulated time [s].")] = None,
    param: Annotated[Optional[list[str]], typer.Option("--param", metavar="NAME=VALUE",
                                                       help="A parameter every vehicle starts with, e.g. "
                                                            "NOISE_POS_M=0.02 (repeat).")] = None,
    lockstep: Annotated[bool, typer.Option(help="Step the clock when every vehicle's companion has answered, not with "
                                                "the wall clock: as fast as the machine allows, the same however busy "
                                                "it is. The clock starts when every companion answers.")] = False,
    lockstep_timeout_s: Annotated[float, typer.Option(help="With --lockstep: a companion silent this long (wall "
                                                           "time) has died; its vehicle flies on without it [s].")] = 10.0,
    max_rtf: Annotated[Optional[float], typer.Option(help="With --lockstep: never faster than this many simulated "
                                                          "seconds per wall second (1: at most real time, to watch "
                                                          "a run or drive it with tools on the wall clock).")] = None,
    wind_m_s: WindSpeed = None,
    wind_from_deg: WindFrom = None,
    turbulence: Turbulence = None,
    gust: Gusts = None,
    seed: Annotated[int, typer.Option(help="Seed for sensor noise and turbulence.")] = 0,
    clock_drift_ppm: Annotated[float, typer.Option(help="The flight controllers' clocks run this much faster than "
                                                        "simulated time (a crystal's error): every stamp they send, "
                                                        "TIMESYNC's too [ppm].")] = 0.0,
    quiet: Annotated[bool, typer.Option(help="Print only errors.")] = False,
) -> None:
    """Start N simulated flight controllers; run until SIGINT/SIGTERM (or --duration-s)."""
    import asyncio

    from triswarm.companion.state import write_json_atomically
    from triswarm.sitl.launcher import SitlOptions, parse_home, run_sitl
    from triswarm.sitl.lockstep import LockstepOptions
    from triswarm.sitl.server import LinkOpenError
    from triswarm.sitl.profiles import profile as sitl_profile

    def write(option: str, path: Path, data: dict) -> None:
        try:
            write_json_atomically(path, data)
        except OSError as exc:
            raise UserError(f"{option} {path}: cannot write it ({exc.strerror})") from None

    with user_errors(LinkOpenError):
        if n < 1:
            raise UserError(f"-n must be at least 1, got {n}")
        _finite("speedup", speedup, positive=True)
        try:
            sitl_profile(fc_profile)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        _finite("rate-hz", rate_hz, non_negative=True)
        _finite("physics-hz", physics_hz, positive=True)
        _finite("spacing-m", spacing_m, positive=True)
        _finite("duration-s", duration_s, positive=True)
        _finite("lockstep-timeout-s", lockstep_timeout_s, positive=True)
        _finite("max-rtf", max_rtf, positive=True)
        _finite("clock-drift-ppm", clock_drift_ppm)
        if abs(clock_drift_ppm) > 1000.0:
            raise UserError(f"--clock-drift-ppm must be within +-1000 (a crystal's error), got {clock_drift_ppm:g}")
        if max_rtf is not None and not lockstep:
            raise UserError("--max-rtf goes with --lockstep (in real time the clock is the wall's)")
        if lockstep and speedup != 1.0:
            raise UserError("--speedup and --lockstep exclude each other: in lockstep the companions set the pace")
        if not 1 <= first_id <= 256 - n:
            raise UserError(f"--first-id {first_id} with {n} vehicles leaves system ids outside 1..255")
        if not 0 <= base_port <= 65535 - 2 * n:
            raise UserError(f"--base-port {base_port} leaves no room for {n} vehicles (two ports each)")
        params = []
        for item in param or []:
            name, _, value = item.partition("=")
            try:
                params.append((name.strip().upper(), float(value)))
            except ValueError:
                raise UserError(f"--param must be NAME=VALUE with a number, got {item!r}") from None
        try:
            home_lla = parse_home(home)
        except ValueError as exc:  # not three numbers, or not a place on Earth
            raise UserError(str(exc) if str(exc).startswith("--home") else f"--home {home}: {exc}") from None
        opts = SitlOptions(n=n, home=home_lla, speedup=speedup, rate_hz=rate_hz, fc_profile=fc_profile,
                           physics_hz=physics_hz,
                           base_port=base_port, bind=bind, spacing_m=spacing_m, duration_s=duration_s, first_id=first_id,
                           params=tuple(params), lockstep=LockstepOptions(timeout_s=lockstep_timeout_s, max_rtf=max_rtf or math.inf) if lockstep else None,
                           seed=seed, wind=wind_from_options(None, wind_m_s, wind_from_deg, turbulence, gust),
                           clock_drift_ppm=clock_drift_ppm)

        def ready(m: dict) -> None:
            write("--manifest", manifest, m)
            if quiet:
                return
            table = Table(title=f"{n} simulated tri-rotors, home {opts.home[0]:.6f}, {opts.home[1]:.6f}, "
                                f"{opts.home[2]:g} m; manifest {manifest}")
            table.add_column("sysid", justify="right")
            table.add_column("start N,E [m]", justify="right")
            table.add_column("companion link")
            table.add_column("gcs link")
            for v in m["vehicles"]:
                ned = v["start_ned_m"]
                table.add_row(str(v["sysid"]), f"{ned[0]:.1f}, {ned[1]:.1f}", v["links"]["companion"]["pymavlink"],
                              v["links"]["gcs"]["pymavlink"])
            console.print(table)
            console.print("pymavlink: mavutil.mavlink_connection(<link>); MAVSDK: the same with udpout://. "
                          "Ctrl-C stops.", soft_wrap=True)

        # (a --rate-hz or --param the vehicles refuse: ParameterError; a port that cannot be opened: LinkOpenError)
        result = asyncio.run(run_sitl(opts, on_ready=ready, say=lambda text, warning=False: (warning or not quiet) and console.print(text, soft_wrap=True)))
        if stats is not None:
            write("--stats", stats, result)
    if not quiet:
        dropped = [f"{v['sysid']}: {v['drops']}" for v in result["vehicles"] if v["drops"]]
        rtf = (result.get("lockstep") or {}).get("real_time_factor") or result["speedup_achieved"] or 0.0
        console.print(f"stopped after {result['sim_time_s']:.1f} s simulated in {result['wall_time_s']:.1f} s "
                      f"(real-time factor {rtf:.2f}); dropped frames per vehicle: "
                      f"{', '.join(dropped) if dropped else 'none'}", soft_wrap=True)


from .plot_cmd import plot  # noqa: E402
from .swarm_cmd import register  # noqa: E402
from .demo import demo  # noqa: E402
from .monitor import monitor  # noqa: E402
from .pki_cmd import pki_app  # noqa: E402
from .deploy_cmd import deploy  # noqa: E402

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
