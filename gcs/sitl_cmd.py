"""`triswarm sitl up`: simulated flight controllers that speak MAVLink (triswarm's own, or ArduPilot's
firmware flying triswarm's plant)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from triswarm.protocol.frames import DEFAULT_HOME, parse_home

from .errors import UserError, console, finite_option, user_errors
from .stack import fc_link
from .wind_options import Gusts, Turbulence, WindFrom, WindSpeed, wind_from_options


sitl_app = typer.Typer(no_args_is_help=True, add_completion=False, rich_markup_mode=None,
                       help="Simulated tri-rotor flight controllers that speak MAVLink.")


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
    estimator: Annotated[Optional[str], typer.Option(
        metavar="PROFILE", help="What the flight controllers' estimators report: truth, mocap, rtk or gps (lag, "
                                "wandering bias, noise; docs/wind.md#estimates-as-autopilots-give-them), before "
                                "any NOISE_* parameter's white noise.")] = None,
    quiet: Annotated[bool, typer.Option(help="Print only errors.")] = False,
    autopilot: Annotated[str, typer.Option(help="The flight controllers: triswarm (simulated here), ardupilot "
                                                "(ArduPilot's own ArduCopter SITL firmware, with deploy/ardupilot/) "
                                                "or px4 (PX4's own px4_sitl_zenoh firmware, with deploy/px4/), "
                                                "flying this plant.")] = "triswarm",
    firmware: Annotated[Optional[Path], typer.Option(
        help="With --autopilot ardupilot: the ArduCopter SITL binary (bin/arducopter of a SITL build; default "
             "$TRISWARM_ARDUCOPTER). With --autopilot px4: the px4_sitl_zenoh build, its folder or its .tar.gz "
             "(default $TRISWARM_PX4).")] = None,
    run_dir: Annotated[Optional[Path], typer.Option(help="With --autopilot ardupilot or px4: the firmwares' run "
                                                         "folders (default: sitl-runs/ beside the manifest).")] = None,
    truth: Annotated[Optional[Path], typer.Option(help="With --autopilot ardupilot or px4: log every vehicle's true "
                                                       "position and attitude here (CSV, 50 Hz of simulated time).")] = None,
) -> None:
    """Start N simulated flight controllers; run until SIGINT/SIGTERM (or --duration-s)."""
    import asyncio

    from triswarm.companion.state import write_json_atomically
    from triswarm.sitl.launcher import SitlOptions, run_sitl
    from triswarm.sitl.lockstep import LockstepOptions
    from triswarm.sitl.estimator import profile as estimator_profile
    from triswarm.sitl.profiles import profile as sitl_profile

    def write(option: str, path: Path, data: dict) -> None:
        try:
            write_json_atomically(path, data)
        except OSError as exc:
            raise UserError(f"{option} {path}: cannot write it ({exc.strerror})") from None

    if autopilot in ("ardupilot", "px4"):
        if estimator is not None:
            with user_errors():
                raise UserError("--estimator goes with --autopilot triswarm: a firmware's estimates are its own EKF's")
        return _firmware_up(autopilot, n, first_id, manifest, home, physics_hz, spacing_m, stats, duration_s, param, seed,
                             wind_from_options(None, wind_m_s, wind_from_deg, turbulence, gust), firmware, run_dir,
                             truth, quiet, speedup=speedup, lockstep=lockstep, fc_profile=fc_profile, rate_hz=rate_hz,
                             clock_drift_ppm=clock_drift_ppm)
    with user_errors():
        if autopilot != "triswarm":
            raise UserError(f"--autopilot must be triswarm, ardupilot or px4, got {autopilot!r}")
        for option, value in (("--firmware", firmware), ("--run-dir", run_dir), ("--truth", truth)):
            if value is not None:
                raise UserError(f"{option} goes with --autopilot ardupilot or px4")
        try:
            if estimator is not None:
                estimator_profile(estimator)
        except ValueError as exc:
            raise UserError(f"--estimator: {exc}") from None
        if n < 1:
            raise UserError(f"-n must be at least 1, got {n}")
        finite_option("speedup", speedup, positive=True)
        try:
            sitl_profile(fc_profile)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        finite_option("rate-hz", rate_hz, non_negative=True)
        finite_option("physics-hz", physics_hz, positive=True)
        finite_option("spacing-m", spacing_m, positive=True)
        finite_option("duration-s", duration_s, positive=True)
        finite_option("lockstep-timeout-s", lockstep_timeout_s, positive=True)
        finite_option("max-rtf", max_rtf, positive=True)
        finite_option("clock-drift-ppm", clock_drift_ppm)
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
        params = _params(param)
        home_lla = _home(home)
        opts = SitlOptions(n=n, home=home_lla, speedup=speedup, rate_hz=rate_hz, fc_profile=fc_profile,
                           physics_hz=physics_hz,
                           base_port=base_port, bind=bind, spacing_m=spacing_m, duration_s=duration_s, first_id=first_id,
                           params=tuple(params), lockstep=LockstepOptions(timeout_s=lockstep_timeout_s, max_rtf=max_rtf or math.inf) if lockstep else None,
                           seed=seed, wind=wind_from_options(None, wind_m_s, wind_from_deg, turbulence, gust),
                           clock_drift_ppm=clock_drift_ppm, estimator=estimator)

        def ready(m: dict) -> None:
            write("--manifest", manifest, m)
            if quiet:
                return
            _table(m, f"{n} simulated tri-rotors, home {opts.home[0]:.6f}, {opts.home[1]:.6f}, {opts.home[2]:g} m; "
                      f"manifest {manifest}")
            console.print("pymavlink: mavutil.mavlink_connection(<link>); MAVSDK: the same with udpout://. "
                          "Ctrl-C stops.", soft_wrap=True)

        # (a --rate-hz or --param the vehicles refuse: ParameterError; a port that cannot be opened: LinkOpenError)
        result = asyncio.run(run_sitl(opts, on_ready=ready, say=lambda text, warning=False: (warning or not quiet) and console.print(text, soft_wrap=True, markup=False)))
        if stats is not None:
            write("--stats", stats, result)
    if not quiet:
        dropped = [f"{v['sysid']}: {v['drops']}" for v in result["vehicles"] if v["drops"]]
        rtf = (result.get("lockstep") or {}).get("real_time_factor") or result["speedup_achieved"] or 0.0
        console.print(f"stopped after {result['sim_time_s']:.1f} s simulated in {result['wall_time_s']:.1f} s "
                      f"(real-time factor {rtf:.2f}); dropped frames per vehicle: "
                      f"{', '.join(dropped) if dropped else 'none'}", soft_wrap=True)




def _params(param: list[str] | None) -> list[tuple[str, float]]:
    params = []
    for item in param or []:
        name, _, value = item.partition("=")
        try:
            params.append((name.strip().upper(), float(value)))
        except ValueError:
            raise UserError(f"--param must be NAME=VALUE with a number, got {item!r}") from None
    return params


def _home(home: str) -> tuple[float, float, float]:
    try:
        return parse_home(home)
    except ValueError as exc:  # not three numbers, or not a place on Earth
        raise UserError(str(exc) if str(exc).startswith("--home") else f"--home {home}: {exc}") from None


def _firmware_up(kind, n, first_id, manifest, home, physics_hz, spacing_m, stats, duration_s, param, seed, wind,
                 firmware, run_dir, truth, quiet, **triswarm_only) -> None:
    """``sitl up --autopilot ardupilot|px4``: N SITL firmwares of that autopilot, this process their plant."""
    import asyncio

    from triswarm.companion.state import write_json_atomically
    from triswarm.sitl.ardupilot import ArduPilotOptions, run_ardupilot
    from triswarm.sitl.firmware import find_firmware
    from triswarm.sitl.px4 import Px4Options, find_package, run_px4

    name = {"ardupilot": "ArduPilot", "px4": "PX4"}[kind]

    with user_errors():
        defaults = {"speedup": 1.0, "lockstep": False, "fc_profile": "triswarm", "rate_hz": None, "clock_drift_ppm": 0.0}
        for option, value in triswarm_only.items():
            if value != defaults[option]:
                raise UserError(f"--{option.replace('_', '-')} is for triswarm's flight controllers: {name}'s firmware "
                                "runs in real time, in lockstep with its plant, and streams at its own rates or what "
                                "its companion asks for")
        if n < 1:
            raise UserError(f"-n must be at least 1, got {n}")
        if not 1 <= first_id <= 256 - n:
            raise UserError(f"--first-id {first_id} with {n} vehicles leaves system ids outside 1..255")
        finite_option("physics-hz", physics_hz, positive=True)
        finite_option("spacing-m", spacing_m, positive=True)
        finite_option("duration-s", duration_s, positive=True)
        binary = find_firmware(firmware) if kind == "ardupilot" else find_package(firmware)
        options, run = (ArduPilotOptions, run_ardupilot) if kind == "ardupilot" else (Px4Options, run_px4)
        opts = options(n=n, firmware=binary, run_dir=run_dir or manifest.resolve().parent / "sitl-runs",
                       home=_home(home), first_id=first_id, spacing_m=spacing_m, physics_hz=physics_hz,
                       wind=wind, seed=seed, params=tuple(_params(param)), duration_s=duration_s, truth_path=truth)

        def ready(m: dict) -> None:
            try:
                write_json_atomically(manifest, m)
            except OSError as exc:
                raise UserError(f"--manifest {manifest}: cannot write it ({exc.strerror})") from None
            if not quiet:
                _table(m, f"{n} {name} SITL firmwares flying triswarm's plant; run folders in {opts.run_dir}; "
                          f"manifest {manifest}")
                console.print("pymavlink: mavutil.mavlink_connection(<gcs link>); a triswarm companion: --fc "
                              "<companion link>. Ctrl-C stops.", soft_wrap=True)

        say = (lambda text, warning=False: (warning or not quiet) and console.print(text, soft_wrap=True, markup=False))
        result = asyncio.run(run(opts, on_ready=ready, say=say))
        if stats is not None:
            try:
                write_json_atomically(stats, result)
            except OSError as exc:
                raise UserError(f"--stats {stats}: cannot write it ({exc.strerror})") from None
    if not quiet:
        console.print(f"stopped after {result['sim_time_s']:.1f} s simulated in {result['wall_time_s']:.1f} s "
                      f"(real-time factor {result['real_time_factor'] or 0:.2f})", soft_wrap=True)


def _table(m: dict, title: str) -> None:
    table = Table(title=title)
    table.add_column("sysid", justify="right")
    table.add_column("start N,E [m]", justify="right")
    table.add_column("companion link")
    table.add_column("gcs link")
    for v in m["vehicles"]:
        ned = v["start_ned_m"]
        table.add_row(str(v["sysid"]), f"{ned[0]:.1f}, {ned[1]:.1f}", fc_link(v["links"]["companion"]),
                      v["links"]["gcs"]["pymavlink"])
    console.print(table)
