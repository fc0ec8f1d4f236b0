"""The operator CLI, run as a real process: outputs of `triswarm sim`, and bad input ends with one
sentence and exit status 2, never a traceback."""

import csv
import json
import subprocess
import sys

import pytest

from .conftest import paper_plan_variant


def triswarm(*args, cwd=None, timeout=120):
    return subprocess.run([sys.executable, "-m", "triswarm.gcs.cli", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout)


@pytest.mark.slow
def test_short_sim_writes_summary_telemetry_and_figures(tmp_path):
    out = tmp_path / "run"
    r = triswarm("sim", "paper-hexagon", "--duration-s", "4", "--out", str(out), "--seed", "3")
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["drones"] == 6 and summary["design"]["c"] > 0
    assert set(summary["design"]["eigenvalues_L_plus_G"]) == {"two-chain", "triangles", "reverse-two-chain"}
    assert len(summary["design"]["K"]) == 6 and len(summary["design"]["K"][0]) == 12
    assert len(summary["design"]["F"]) == 12 and len(summary["design"]["F"][0]) == 6
    with (out / "telemetry.csv").open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["t_s", "drone", "x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad"]
    drones = {int(r[1]) for r in rows[1:]}
    assert drones == set(range(1, 7))
    times = sorted({float(r[0]) for r in rows[1:]})
    assert times[0] == 0.0 and times[-1] == pytest.approx(4.0)
    assert (len(rows) - 1) / 6 / 4.0 >= 20  # at least 20 rows per second per drone
    for name in ("fig7_trajectories_3d.png", "fig9_attitude.png", "fig10_position.png", "formation_error.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # a flight that ends before the settled window (25 s for the case study) is judged over its second half
    assert summary["performance"]["window_start_s"] == pytest.approx(2.0)


def test_sim_judges_over_the_settled_window_its_strict_help_names(tmp_path):
    """--strict's help: the window starts at the entry's end + check.settle_s. A plan whose entry ends at
    2 s and settles for 1 s, flown 4 s: judged over [3 s, end], and --strict's exit status says the verdict."""
    from triswarm.gcs.scenarios import plan_text

    text = plan_text("paper-hexagon").replace("climb_s = 3.0", "climb_s = 1.0").replace("blend_s = 12.0", "blend_s = 1.0")
    plan = tmp_path / "quick.toml"
    plan.write_text("duration_s = 4.0\n" + text + "\n[check]\nsettle_s = 1.0\n")
    help_text = triswarm("sim", "--help").stdout
    assert "from the entry's end + check.settle_s" in " ".join(help_text.split())
    for bound_m, status in ((0.10, None), (1e-9, 1)):
        out = tmp_path / f"run-{bound_m}"
        r = triswarm("sim", str(plan), "--out", str(out), "--no-figures", "--strict", "--position-bound-m", str(bound_m))
        perf = json.loads((out / "summary.json").read_text())["performance"]
        assert perf["window_start_s"] == pytest.approx(3.0), perf
        within = perf["worst_position_error_m"] <= bound_m and perf["worst_attitude_error_rad"] <= 0.02
        assert r.returncode == (0 if within else 1), (r.returncode, perf, r.stderr)
        assert status is None or r.returncode == status
        assert "worst errors over [3 s, end]" in r.stdout


def bad(tmp_path, *args):
    r = triswarm(*args, cwd=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr and "Traceback" not in r.stdout
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, r.stderr
    return lines[0]


def test_nan_parameter(tmp_path):
    assert "--duration-s must be a finite number" in bad(tmp_path, "sim", "--duration-s", "nan")
    assert "--servo-delay-s must not be negative" in bad(tmp_path, "sim", "--servo-delay-s", "-0.01")
    assert "--latency-s must be at most 1 s, got 5" in bad(tmp_path, "sim", "--latency-s", "5")


def test_negative_mass_in_a_scenario_file(tmp_path):
    path = paper_plan_variant(tmp_path, [("[leader]", "[airframe]\nmass_kg = -0.5\n\n[leader]")])
    line = bad(tmp_path, "sim", str(path), "--duration-s", "2")
    assert "plan.toml" in line and "mass_kg must be positive" in line


def test_nan_in_a_scenario_file(tmp_path):
    path = paper_plan_variant(tmp_path, [("radius_m = 10.0", "radius_m = nan")])
    assert "formation.radius_m must be a finite number" in bad(tmp_path, "sim", str(path))


def test_infeasible_formation_in_a_scenario_file(tmp_path):
    offsets = ", ".join(f"[{'1.0' if i == 2 else '0.0'}, 0, 0, 0, 0, 0, 0, 0, 0, {i}.0, 0, 10]" for i in range(6))
    path = paper_plan_variant(tmp_path, [('type = "rotating-polygon"', f'type = "constant"\noffsets = [{offsets}]'),
                                 ("radius_m = 10.0\n", ""), ("altitude_m = 20.0\n", ""), ("rate_rad_s = 1.0\n", ""),
                                 ('attitude_rad = "paper-alternating"\n', "")])
    line = bad(tmp_path, "sim", str(path), "--duration-s", "2")
    assert "fails the feasibility condition (76): drone 3 position rows 10-12" in line


@pytest.mark.slow
def test_wind_flags_and_wind_tables_bad_input(tmp_path):
    for cmd in (("sim", "--duration-s", "2"), ("sitl", "up", "-n", "1")):
        assert "--wind-m-s must be a finite number (not negative), got -3.0" in bad(tmp_path, *cmd, "--wind-m-s", "-3")
        assert "--turbulence must be none, light, moderate, severe" in bad(tmp_path, *cmd, "--turbulence", "gale")
        assert "--gust must be SPEED_M_S,DURATION_S,START_S[,FROM_DEG] (three or four numbers), got '5,2'" in \
            bad(tmp_path, *cmd, "--gust", "5,2")
        assert "--gust: wind.gusts[1].duration_s must be positive, got -2.0" in \
            bad(tmp_path, *cmd, "--gust", "5,2,10", "--gust", "5,-2,10")
    path = paper_plan_variant(tmp_path, [("[leader]", "[wind]\nspeed_m_s = 4\nfrom = 90\n\n[leader]")])
    assert "plan.toml: wind.from is not a known field" in bad(tmp_path, "sim", str(path))


def test_unknown_scenario_and_unreadable_files(tmp_path):
    assert "not a plan file and not a built-in scenario" in bad(tmp_path, "sim", "no-such")
    assert "no such plan file" in bad(tmp_path, "sim", "missing.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("name = \n")
    assert "not valid TOML" in bad(tmp_path, "sim", str(broken))


def test_sitl_up_bad_input(tmp_path):
    import socket

    assert "--home must be LAT,LON,ALT_M" in bad(tmp_path, "sitl", "up", "-n", "2", "--home", "53.4,abc,10")
    assert "home latitude must be a number between -90 and 90" in bad(tmp_path, "sitl", "up", "--home", "nan,0,0")
    assert "--speedup must be positive" in bad(tmp_path, "sitl", "up", "--speedup", "0")
    taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    taken.bind(("127.0.0.1", 0))
    port = taken.getsockname()[1]
    try:
        line = bad(tmp_path, "sitl", "up", "-n", "1", "--base-port", str(port), "--manifest", str(tmp_path / "m.json"))
        assert f"cannot open UDP 127.0.0.1:{port} for vehicle 1 (companion link)" in line
    finally:
        taken.close()


def test_demo_bad_input(tmp_path):
    """The demo refuses what it cannot fly or judge, before it starts anything."""
    assert "--max-rtf must be a positive number and goes with --lockstep, got 2.0 without --lockstep" in \
        bad(tmp_path, "demo", "--max-rtf", "2")
    assert "--autopilot must be triswarm, ardupilot or px4, got 'betaflight'" in bad(tmp_path, "demo", "--autopilot", "betaflight")
    # the case study's entry ends at 15 s; its flight is judged from 10 s later: a shorter flight is refused
    line = bad(tmp_path, "demo", "--duration-s", "20")
    assert "--duration-s 20 ends before the settled window the formation is judged over begins (25 s: the entry's " \
           "end plus 10 s)" in line, line
    assert not (tmp_path / "runs").exists()


def test_sitl_up_stops_cleanly_on_sigint(tmp_path):
    import signal
    import time

    manifest = tmp_path / "m.json"
    proc = subprocess.Popen([sys.executable, "-m", "triswarm.gcs.cli", "sitl", "up", "-n", "3", "--base-port", "0",
                             "--manifest", str(manifest)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not manifest.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert manifest.exists()
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "sysid" in out and "udpout:127.0.0.1:" in out and "stopped after" in out
    assert "Traceback" not in err


def test_leader_goto_takes_negative_coordinates(tmp_path):
    """y is west in the plan's frame: `leader goto 8 -5 0` must read -5 as a number, not an option."""
    r = subprocess.run([sys.executable, "-m", "triswarm.gcs.cli", "leader", "goto", "8", "-5", "0", "--speed", "3",
                        "--manifest", str(tmp_path / "none.json"), "--tlog", str(tmp_path / "g.tlog")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "no such swarm manifest" in r.stderr, r.stderr


@pytest.mark.slow
def test_sim_refuses_an_uncertified_schedule_unless_forced(tmp_path):
    """`sim --drones 30` of a plan that names the paper's families: refused like plan check would;
    --force flies it anyway, with the reason as a warning."""
    path = paper_plan_variant(tmp_path, [("switch_period_s = 5.0\n", 'switch_period_s = 5.0\n'
                                          'families = ["two-chain", "triangles", "reverse-two-chain"]\n')])
    line = bad(tmp_path, "sim", str(path), "--drones", "30", "--duration-s", "1")
    assert "topology schedule cannot be certified" in line and line.endswith("(--force flies it anyway)")
    r = triswarm("sim", str(path), "--drones", "30", "--duration-s", "1", "--force", "--no-figures",
                 "--out", str(tmp_path / "run"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stderr.startswith("triswarm: warning: ") and "topology schedule cannot be certified" in r.stderr
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["drones"] == 30


def test_sim_says_when_its_servos_are_slower_than_the_controllers_are_told(tmp_path):
    """`sim --servo-rate-deg-s 600` of a plan whose airframe's servos turn at once: one note on
    stderr naming both speeds and how to tell the controllers; the plan that tells them (the same
    speed in [airframe]) flies without it."""
    r = triswarm("sim", "--servo-rate-deg-s", "600", "--duration-s", "0.5", "--no-figures", "--out",
                 str(tmp_path / "a"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stderr.startswith("triswarm: note: the simulated servos turn at 600 deg/s") and "(at once)" in r.stderr
    assert "[airframe] servo_rate_rad_s" in r.stderr
    told = paper_plan_variant(tmp_path, [("[controller]\n", "[airframe]\nservo_rate_rad_s = 10.471975511965978\n\n"
                                                           "[controller]\n")])
    r = triswarm("sim", str(told), "--servo-rate-deg-s", "600", "--duration-s", "0.5", "--no-figures", "--out",
                 str(tmp_path / "b"), cwd=tmp_path)
    assert r.returncode == 0 and "note" not in r.stderr, r.stderr
    assert json.loads((tmp_path / "b" / "summary.json").read_text())["run"]["servo_rate_deg_s"] == pytest.approx(600.0)


def test_the_cli_reference_is_the_clis_own_help():
    """docs/cli.md is generated from the CLI (make docs): it must say what --help says today."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    r = subprocess.run([sys.executable, str(root / "tools" / "gen_cli_docs.py"), "--check"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


def test_a_bug_is_not_called_a_user_error(monkeypatch, capsys):
    """A ValueError or OSError from inside (not from reading what the user wrote) is shown as a bug: its
    traceback and exit status 1, never "error:" and exit status 2."""
    from triswarm.gcs import cli, scenarios

    for exc in (ValueError("a bug inside"), OSError(5, "a fault inside")):
        def broken(*args, _exc=exc, **kwargs):
            raise _exc

        monkeypatch.setattr(scenarios, "load_plan", broken)
        monkeypatch.setattr(sys, "argv", ["triswarm", "sim", "--duration-s", "1"])
        with pytest.raises(SystemExit) as got:
            cli.main()
        err = capsys.readouterr().err
        assert got.value.code == 1 and "Traceback" in err and str(exc) in err, err
        assert "triswarm: internal error: a bug in triswarm" in err and "triswarm: error:" not in err, err


def test_a_command_imports_only_what_it_needs():
    """A command's help, or its refusal of a mistyped option, comes before numba's kernels, SciPy,
    matplotlib or the MAVLink dialect are imported (seconds of CPU on a slow machine); a command
    that designs imports them."""
    heavy = ("numpy", "numba", "scipy", "matplotlib", "control", "zenoh", "pymavlink",
             "triswarm.protocol.dialect.triswarm_v20")
    probe = ("import sys\nfrom triswarm.gcs import cli\nsys.argv = ['triswarm', *sys.argv[1:]]\ncode = 0\n"
             "try:\n    cli.main()\nexcept SystemExit as e:\n    code = e.code\n"
             f"print(code, *(m for m in {heavy!r} if m in sys.modules))")

    def imported(*args: str) -> list[str]:
        r = subprocess.run([sys.executable, "-c", probe, *args], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        return r.stdout.strip().splitlines()[-1].split()

    assert imported("sim", "--duration-s", "nan") == ["2"]
    for command in (["sim"], ["plot"], ["deploy"], ["pki", "init"]):
        assert imported(*command, "--help") == ["0"], command
    designed = imported("plan", "check", "paper-hexagon", "--no-simulate", "--json")
    assert designed[0] == "0" and {"numpy", "numba", "scipy"} <= set(designed), designed
