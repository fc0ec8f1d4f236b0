"""PX4's firmware in the loop, measured (make bench): px4_sitl_zenoh (TRISWARM_PX4, or
../shared/px4/px4_sitl_zenoh.tar.gz) flying triswarm's plant, the companions on its Zenoh bridge.

Six drones fly the paper's case study from the ground (sitl up --autopilot px4, one companion
process flying all six, --autostart). Over [25, 50] s of the plan: the worst position and attitude
errors in PX4's own telemetry (EKF2, over MAVLink) and in the plant's truth; over 20 s of that
window, the CPU of each PX4 instance, of the plant and router (the sitl process) and of the
companions (share of one core), and the real-time factor of the firmwares' clock (simulated seconds
per wall second). The latency of the companions' commands, on the firmwares' clock (the simulation's),
from PX4's logs and the plant: the odometry sample a command answers (its timestamp_sample) to PX4
taking the command (actuator_motors), then to PX4's output (actuator_outputs), then to the plant
applying it (HIL_ACTUATOR_CONTROLS; the servos' own delay comes on top).

    python tests/bench/bench_px4.py
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tests.bench.bench_ardupilot import truth_clock  # noqa: E402
from tests.bench.bench_floor import cpu_seconds  # noqa: E402
from tests.firmware_helpers import SHARED_PX4  # noqa: E402
from tests.stack_helpers import judge, judge_truth  # noqa: E402
from triswarm.gcs.recorder import Recorder  # noqa: E402
from triswarm.gcs.stack import Stack  # noqa: E402
from triswarm.protocol import px4_msgs as px4  # noqa: E402
from triswarm.protocol.plan import plan_from_dict, spec_from_toml  # noqa: E402

WINDOW = (25.0, 50.0)
START_DELAY_S = 30.0


def package() -> Path:
    return Path(os.environ.get("TRISWARM_PX4", SHARED_PX4))


def case_study() -> dict:
    plan_path = ROOT / "examples" / "paper-hexagon.toml"
    plan = plan_from_dict(spec_from_toml(plan_path.read_text(), str(plan_path)), str(plan_path))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        with Stack(plan_path, tmp / "run", 6, start_delay_s=START_DELAY_S, rate_hz=100.0, agents_per_process=0,
                   autopilot="px4", firmware=package()) as stack, Recorder(stack.manifest) as rec:
            start = stack.start_at
            procs = {**{f"px4 {v['sysid']}": v["pid"] for v in stack.manifest["vehicles"]},
                     "plant and router (sitl)": stack.procs["sitl"].pid,
                     "companions (6 agents)": stack.procs["companions-1-6"].pid}
            truth = tmp / "run" / "truth.csv"
            while not rec.now() >= start + WINDOW[0]:
                time.sleep(0.2)
            cpu0, sim0, wall0 = {k: cpu_seconds(p) for k, p in procs.items()}, truth_clock(truth), time.monotonic()
            time.sleep(20.0)
            cpu1, sim1, wall1 = {k: cpu_seconds(p) for k, p in procs.items()}, truth_clock(truth), time.monotonic()
            while not rec.now() >= start + WINDOW[1]:
                time.sleep(0.2)
            _, telemetry = judge(plan, rec, start, *WINDOW, position_bound_m=0.25, attitude_bound_rad=0.05)
        _, truth_worst = judge_truth(plan, truth, rec, start, *WINDOW, position_bound_m=0.10, attitude_bound_rad=0.02)
        sitl = json.loads((tmp / "run" / "stats" / "sitl.json").read_text())
        latency = command_latency(sorted((tmp / "run" / "firmware").glob("vehicle-*/log/*/*.ulg")))
    latency["plant_takes_output_ms"] = [sitl["output_age_p50_ms"], sitl["output_age_p99_ms"]]
    wall = wall1 - wall0
    worst = lambda report: [max(p for p, _ in report.values()), max(a for _, a in report.values())]  # noqa: E731
    return {"window_s": list(WINDOW), "telemetry_worst_m_rad": worst(telemetry), "truth_worst_m_rad": worst(truth_worst),
            "telemetry": telemetry, "truth": truth_worst,
            "cpu_share": {k: round((cpu1[k] - cpu0[k]) / wall, 3) for k in procs},
            "real_time_factor": round((sim1 - sim0) / wall, 3),
            "latency_p50_p99_ms": latency}


def command_latency(logs: list[Path]) -> dict[str, list[float]]:
    """From PX4's logs (their actuator_motors and actuator_outputs, as the logger sampled them; PX4's
    clock): the odometry sample a command answers to PX4 taking it, and PX4 taking it to its output,
    median and 99th percentile [ms] over every vehicle's flight."""
    from pyulog import ULog

    taken, output = [], []
    for path in logs:
        log = ULog(str(path), ["actuator_motors", "actuator_outputs", "vehicle_status"])
        motors, outputs, status = (log.get_dataset(n).data for n in ("actuator_motors", "actuator_outputs",
                                                                      "vehicle_status"))
        # the companion's commands: those PX4 took in offboard (in its other modes they are its own)
        mode_then = np.searchsorted(status["timestamp"], motors["timestamp"], side="right") - 1
        flown = (mode_then >= 0) & (status["nav_state"][np.maximum(mode_then, 0)] == px4.NAV_STATE_OFFBOARD)
        t_motor, t_sample = motors["timestamp"][flown], motors["timestamp_sample"][flown]
        taken.append((t_motor - t_sample) / 1e3)
        t_out = outputs["timestamp"]
        first = np.searchsorted(t_out, t_motor)
        ok = first < t_out.size
        output.append((t_out[first[ok]] - t_motor[ok]) / 1e3)
    pct = lambda a: [round(float(v), 3) for v in np.percentile(np.concatenate(a), [50, 99])]  # noqa: E731
    return {"sample_to_px4_ms": pct(taken), "px4_to_output_ms": pct(output)}


def main() -> None:
    if not package().exists():
        print(f"bench_px4: no PX4 firmware at {package()} (TRISWARM_PX4): skipped")
        return
    print(json.dumps({"six_drones": case_study()}), flush=True)


if __name__ == "__main__":
    main()
