"""`triswarm plot RUN` on a ground-station log synthesized from a known trajectory.

The truth is the plan's own reference x0 + h_i(t), sent as three flight controllers would: NED and
FRD (protocol/frames), stamped with each one's boot clock, ATTITUDE and LOCAL_POSITION_NED at 20 Hz
on different instants, SYSTEM_TIME at 1 Hz, a companion's chatter, and the whole packed by pymavlink's
stock MAVLink 2 module into a .tlog with garbage, a truncated and a corrupt frame in it."""

import csv
import json
import os
import re
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from triswarm.gcs.scenarios import load_plan
from triswarm.protocol import frames

from .conftest import PAPER_PLAN_FILE

START_UNIX_S = 1_700_000_000.0
FIRST_S, END_S = -1.0, 32.0  # plan times the log covers
STREAM_PERIOD_MS = 50  # 20 Hz per stream
LATENCY_S = 0.030  # receive time - sample time, for drones with SYSTEM_TIME; 0.3 m at 10 m/s if misused
FIRST_SYSTEM_TIME_S = 0.5  # samples before it are timed by the first SYSTEM_TIME
DRONES = 3
NO_SYSTEM_TIME = 3  # this drone is timed by the tlog's receive times (sent without latency)
RATE_HZ = 50.0
POSITION_SLACK_M = 2e-5  # float32 on the wire (1.5e-6 m at 25 m) and 5 decimals in the CSV
ATTITUDE_SLACK_RAD = 2e-6  # float32 and 6 decimals
TLOG_TIME = struct.Struct(">Q")


def truth(plan, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position [m], velocity [m/s] and Euler angles [rad] of every drone, paper frame, (N, 3) each."""
    ref = plan.reference(t_s)[0]
    return ref[:, 9:12], ref[:, 0:3], ref[:, 6:9]


def interpolation_bounds(plan) -> tuple[float, float]:
    """Linear interpolation between samples dt apart errs by at most dt^2/8 max|f''|; f'' by central
    differences of the truth."""
    dt_s, h_s = STREAM_PERIOD_MS / 1000.0, 1e-3
    worst = np.zeros(2)
    for t in np.arange(0.0, END_S, 0.01):
        (p0, _, e0), (p1, _, e1), (p2, _, e2) = (truth(plan, t + k * h_s) for k in (-1, 0, 1))
        worst = np.maximum(worst, [np.abs(p0 - 2 * p1 + p2).max(), np.abs(e0 - 2 * e1 + e2).max()])
    pos_bound, att_bound = dt_s**2 / 8 * worst / h_s**2
    return pos_bound + POSITION_SLACK_M, att_bound + ATTITUDE_SLACK_RAD


def synthesize_tlog(path: Path, plan, offset_m: dict[int, np.ndarray]) -> int:
    """Write the log; offset_m moves a drone (numbered from 1) away from its place. Returns the
    number of bytes that are not good records."""
    records: list[tuple[float, bytes]] = []  # (receive time [Unix s], frame)

    def send(sysid: int, compid: int, receive_unix_s: float, msg) -> None:
        records.append((receive_unix_s, msg.pack(mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid))))

    for sysid in range(1, DRONES + 1):
        boot_unix_s = START_UNIX_S - 60.0 - 7.0 * sysid  # each flight controller booted at its own time
        latency_s = 0.0 if sysid == NO_SYSTEM_TIME else LATENCY_S
        phase_ms = {"attitude": 3 + 11 * sysid, "position": 26 + 11 * sysid}  # never the same instants
        for kind, phase in phase_ms.items():
            first_ms = round((START_UNIX_S + FIRST_S - boot_unix_s) * 1000)
            for boot_ms in range(first_ms + phase, round((START_UNIX_S + END_S - boot_unix_s) * 1000), STREAM_PERIOD_MS):
                t_s = boot_unix_s + boot_ms / 1000 - START_UNIX_S
                position_m, velocity_m_s, euler_rad = (a[sysid - 1] for a in truth(plan, t_s))
                if kind == "attitude":
                    roll, pitch, yaw = frames.euler_flip(euler_rad)
                    msg = mavlink.MAVLink_attitude_message(boot_ms, roll, pitch, yaw, 0.0, 0.0, 0.0)
                else:
                    ned = frames.flip(position_m + offset_m.get(sysid, 0.0))
                    msg = mavlink.MAVLink_local_position_ned_message(boot_ms, *ned, *frames.flip(velocity_m_s))
                send(sysid, 1, START_UNIX_S + t_s + latency_s, msg)
        for t_s in np.arange(FIRST_S, END_S, 1.0):
            receive_unix_s = START_UNIX_S + t_s + 0.01
            boot_ms = round((START_UNIX_S + t_s - boot_unix_s) * 1000)
            if sysid != NO_SYSTEM_TIME and t_s >= FIRST_SYSTEM_TIME_S:
                send(sysid, 1, receive_unix_s, mavlink.MAVLink_system_time_message(round((boot_unix_s + boot_ms / 1000) * 1e6), boot_ms))
            send(sysid, 1, receive_unix_s, mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_TRICOPTER, 0, 1, 1, 4, 3))
            send(sysid, 191, receive_unix_s, mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 2, 4, 3))
            send(sysid, 191, receive_unix_s, mavlink.MAVLink_named_value_float_message(boot_ms, b"FORM_ERRM", 0.01))
        send(sysid, 191, START_UNIX_S, mavlink.MAVLink_statustext_message(6, f"companion {sysid}: flying".encode()))
        # Not the flight controller: must be ignored.
        boot_ms = round((START_UNIX_S + 30.0 - boot_unix_s) * 1000)
        send(sysid, 191, START_UNIX_S + 30.0, mavlink.MAVLink_local_position_ned_message(boot_ms, 999.0, 999.0, 999.0, 0, 0, 0))

    records.sort(key=lambda r: r[0])
    data = [TLOG_TIME.pack(round(t * 1e6)) + frame for t, frame in records]
    rng = np.random.default_rng(7)
    garbage = bytes(rng.integers(0, 256, 40, dtype=np.uint8)) + b"\xfd\x09\x00\x00"
    truncated = data[500][:15]
    corrupt = bytearray(data[900])
    corrupt[-1] ^= 0xFF  # its CRC no longer checks
    data[300:300] = [garbage]
    data[501:501] = [truncated]
    data[902] = bytes(corrupt)
    # messages the dialect does not know (an autopilot's own): whole records, passed over, not garbage
    unknown = bytes([0xFD, 4, 0, 0, 0, 1, 1]) + (60000).to_bytes(3, "little") + b"\x01\x02\x03\x04" + b"\x00\x00"
    for at in (2000, 1500, 1000):
        data[at:at] = [TLOG_TIME.pack(round(records[at][0] * 1e6)) + unknown]
    data.append(data[-1][:20])  # cut off mid-frame
    path.write_bytes(b"".join(data))
    return len(garbage) + len(truncated) + len(corrupt) + 20


def make_run(run_dir: Path, offset_m: dict[int, np.ndarray]) -> int:
    run_dir.mkdir()
    plan_text = PAPER_PLAN_FILE.read_text().replace("drones = 6", f"drones = {DRONES}")
    (run_dir / "plan.toml").write_text(plan_text)
    (run_dir / "run.json").write_text(json.dumps({"start_unix_s": START_UNIX_S, "drones": DRONES,
                                                  "home": {"lat_deg": 53.4668, "lon_deg": -2.2339, "alt_m": 60.0}}))
    return synthesize_tlog(run_dir / "gcs.tlog", load_plan(str(run_dir / "plan.toml")), offset_m)


def triswarm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "triswarm.gcs.cli", *args], capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def plan():
    return load_plan(str(PAPER_PLAN_FILE), DRONES)


@pytest.fixture(scope="module")
def bounds(plan):
    return interpolation_bounds(plan)


@pytest.fixture(scope="module")
def good_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("plot") / "good"
    skipped_bytes = make_run(run_dir, {})
    return run_dir, skipped_bytes, triswarm("plot", str(run_dir))


def read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with path.open() as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array(rows[1:], dtype=float)


def test_bounds_are_tight_enough_to_mean_something(bounds):
    pos_bound_m, att_bound_rad = bounds
    assert pos_bound_m < 0.005 and att_bound_rad < 1e-4  # 10 m/s^2 centripetal: 3.1 mm


def test_telemetry_is_the_known_trajectory(good_run, plan, bounds):
    run_dir, _, result = good_run
    assert result.returncode == 0, result.stdout + result.stderr
    header, rows = read_csv(run_dir / "telemetry.csv")
    assert header == ["t_s", "drone", "x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad"]
    t_s = np.unique(rows[:, 0])
    assert t_s[0] == 0.0 and END_S - 0.1 < t_s[-1] < END_S
    np.testing.assert_allclose(np.diff(t_s), 1 / RATE_HZ, atol=1e-4)
    assert sorted(set(rows[:, 1].astype(int))) == [1, 2, 3] and len(rows) == DRONES * t_s.size
    pos_bound_m, att_bound_rad = bounds
    for t, drone, *values in rows:
        position_m, _, euler_rad = (a[int(drone) - 1] for a in truth(plan, t))
        assert np.abs(np.array(values[:3]) - position_m).max() <= pos_bound_m, (t, drone)
        assert np.abs(np.array(values[3:]) - euler_rad).max() <= att_bound_rad, (t, drone)


def test_summary_says_within_bounds(good_run, bounds):
    run_dir, skipped_bytes, result = good_run
    summary = json.loads((run_dir / "summary.json").read_text())
    perf = summary["performance"]
    assert perf["within_bounds"] and perf["window_start_s"] == 25.0
    assert perf["worst_position_error_m"] <= bounds[0] and perf["worst_attitude_error_rad"] <= bounds[1]
    assert summary["run"]["source"] == "tlog" and summary["run"]["start_unix_s"] == START_UNIX_S
    assert summary["run"]["skipped_bytes"] == skipped_bytes and summary["run"]["skipped_runs"] == 4
    assert summary["run"]["unknown_messages"] == 3
    assert summary["drones"] == DRONES and len(summary["design"]["K"]) == 6
    assert [d["clock"] for d in summary["per_drone"]] == ["SYSTEM_TIME", "SYSTEM_TIME", "tlog"]
    assert all(d["within_bounds"] and d["largest_gap_s"] < 0.11 for d in summary["per_drone"])
    assert "within" in result.stdout and "outside" not in result.stdout


def test_figures_are_written(good_run):
    run_dir, _, _ = good_run
    for name in ("fig7_trajectories_3d.png", "fig9_attitude.png", "fig10_position.png", "formation_error.png"):
        assert (run_dir / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_pymavlink_mavlogdump_reads_the_log(good_run):
    run_dir, _, _ = good_run
    tool = Path(sys.executable).with_name("mavlogdump.py")
    r = subprocess.run([sys.executable, str(tool), "--types", "ATTITUDE", "--format", "json", str(run_dir / "gcs.tlog")],
                       capture_output=True, text=True, timeout=60, env={**os.environ, "MAVLINK20": "1"})
    assert r.returncode == 0, r.stderr
    messages = [json.loads(line) for line in r.stdout.splitlines() if line.startswith("{")]
    expected = DRONES * (END_S - FIRST_S) * 1000 / STREAM_PERIOD_MS
    assert 0.99 * expected <= len(messages) <= expected
    first = messages[0]
    assert first["meta"]["type"] == "ATTITUDE" and abs(first["data"]["roll"]) == pytest.approx(0.5)


def test_a_drone_off_its_place_fails(tmp_path, bounds):
    run_dir = tmp_path / "off"
    make_run(run_dir, {2: np.array([0.5, 0.0, 0.0])})
    result = triswarm("plot", str(run_dir))
    assert result.returncode == 1, result.stdout + result.stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    worst_m = [d["worst_position_error_m"] for d in summary["per_drone"]]
    assert worst_m[1] == pytest.approx(0.5, abs=bounds[0])
    assert worst_m[0] <= bounds[0] and worst_m[2] <= bounds[0]
    assert summary["performance"]["worst_position_error_drone"] == 2 and not summary["performance"]["within_bounds"]
    assert [d["within_bounds"] for d in summary["per_drone"]] == [True, False, True]
    assert "outside" in result.stdout


def test_a_window_after_the_telemetry_is_not_judged(good_run):
    """A flight shorter than the settled window is neither within nor outside the bounds: it is said
    to be not judged, with what to do, and the exit status is not a pass."""
    run_dir = good_run[0]
    result = triswarm("plot", str(run_dir), "--window-start-s", "40")
    assert result.returncode == 1, result.stdout + result.stderr
    out = " ".join(result.stdout.split())
    assert re.search(r"formation not judged: the telemetry ends at 3[12]\.\d s of plan time, before the settled "
                     r"window starts at 40 s \(fly longer, or judge from earlier: triswarm plot ", out), out
    assert "outside" not in out and "within" not in out


@pytest.mark.parametrize("breakage, message", [
    ("no folder", "no such run folder"),
    ("no run.json", "it has no run.json"),
    ("bad run.json", "start_unix_s must be"),
    ("home off the Earth", "home must be {lat_deg, lon_deg, alt_m}, a place on Earth"),
    ("garbage tlog", "no ATTITUDE from drone 1"),
])
def test_broken_run_folder_is_one_sentence(tmp_path, breakage, message):
    run_dir = tmp_path / "run"
    if breakage != "no folder":
        run_dir.mkdir()
        (run_dir / "plan.toml").write_text(PAPER_PLAN_FILE.read_text())
        (run_dir / "run.json").write_text(json.dumps({"start_unix_s": START_UNIX_S}))
        (run_dir / "gcs.tlog").write_bytes(bytes(range(256)) * 4)
    if breakage == "no run.json":
        (run_dir / "run.json").unlink()
    if breakage == "bad run.json":
        (run_dir / "run.json").write_text(json.dumps({"start_unix_s": "soon"}))
    if breakage == "home off the Earth":
        (run_dir / "run.json").write_text(json.dumps({"start_unix_s": START_UNIX_S,
                                                      "home": {"lat_deg": 95.0, "lon_deg": 0.0, "alt_m": 0.0}}))
    result = triswarm("plot", str(run_dir))
    assert result.returncode == 2, result.stdout + result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0] and "Traceback" not in result.stderr
