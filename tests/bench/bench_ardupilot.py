"""ArduPilot's firmware in the loop, measured (make bench): ArduCopter SITL (TRISWARM_ARDUCOPTER, or
../shared/ardupilot/bin/arducopter) flying triswarm's plant.

1. Six drones fly the paper's case study (sitl up --autopilot ardupilot, one companion process
   flying all six at 100 Hz, --autostart): over 20 s of formation flight, the CPU of each firmware,
   of the plant (the sitl process) and of the companions (share of one core), and the real-time
   factor the firmwares' clock keeps (simulated seconds per wall second).
2. One drone, this benchmark its companion: armed in GUIDED on the ground, it answers every ATTITUDE
   at once with a command whose first tilt servo's value names it (the rotors slow: it stays down). The
   latency from the telemetry a command answers to the PWM that reaches the physics is read on the
   firmware's own clock (SERVO_OUTPUT_RAW, which is what its next frame sends the plant, against the
   ATTITUDE's stamp); the rate delivered is the script's own count (TSW_HZ), at 100 and 200 Hz.

    python tests/bench/bench_ardupilot.py [--seconds 20]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tests.bench.bench_floor import cpu_seconds  # noqa: E402
from tests.firmware_helpers import SHARED_ARDUCOPTER, Peer  # noqa: E402
from triswarm.gcs.stack import Stack  # noqa: E402
from triswarm.protocol.autopilots import ARDUCOPTER_GUIDED  # noqa: E402
from triswarm.protocol.mavlink import mavlink  # noqa: E402

READY_S = 150.0


def firmware() -> Path:
    return Path(os.environ.get("TRISWARM_ARDUCOPTER", SHARED_ARDUCOPTER))


def truth_clock(path: Path) -> float:
    """The firmwares' clock [s] as the truth log last says."""
    with path.open("rb") as f:
        f.seek(max(0, path.stat().st_size - 400))
        last = [line for line in f.read().decode(errors="replace").splitlines() if line.count(",") == 7][-1]
    return float(last.split(",")[1])


def six_drones(seconds: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        with Stack(ROOT / "examples" / "paper-hexagon.toml", tmp / "run", 6, start_delay_s=80.0, rate_hz=100.0,
                   agents_per_process=0, autopilot="ardupilot", firmware=firmware()) as stack:
            time.sleep(max(0.0, stack.start_at - time.time()) + 25.0)  # (into the formation)
            pids = {fw["sysid"]: fw["pid"] for fw in stack.manifest["vehicles"]}
            procs = {**{f"firmware {s}": p for s, p in pids.items()}, "plant (sitl)": stack.procs["sitl"].pid,
                     "companions (6 agents)": stack.procs["companions-1-6"].pid}
            truth = tmp / "run" / "truth.csv"
            cpu0, sim0, wall0 = {k: cpu_seconds(p) for k, p in procs.items()}, truth_clock(truth), time.monotonic()
            time.sleep(seconds)
            cpu1, sim1, wall1 = {k: cpu_seconds(p) for k, p in procs.items()}, truth_clock(truth), time.monotonic()
    wall = wall1 - wall0
    return {"cpu_share": {k: round((cpu1[k] - cpu0[k]) / wall, 3) for k in procs},
            "real_time_factor": round((sim1 - sim0) / wall, 3), "wall_s": round(wall, 1)}


def latency(rate_hz: float, seconds: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        with Stack(None, Path(tmp), 1, companions=False, autopilot="ardupilot", firmware=firmware()) as stack:
            links = stack.manifest["vehicles"][0]["links"]
            with Peer(links["companion"]["pymavlink"], 1, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER) as comp, \
                    Peer(links["gcs"]["pymavlink"], 255, 190) as gcs:
                deadline = time.monotonic() + 30
                while not comp.heard("HEARTBEAT") and time.monotonic() < deadline:
                    time.sleep(0.1)
                comp.interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, rate_hz)
                comp.interval(mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, 200.0)
                gcs.set_mode(ARDUCOPTER_GUIDED, timeout_s=READY_S)
                gcs.until_accepted(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, timeout_s=READY_S)
                stamps: dict[int, list[int]] = {}  # PWM of tilt 1 -> the ATTITUDE stamps [us] its commands answered
                stop = threading.Event()

                def answer() -> None:
                    seen = len(comp.heard("ATTITUDE"))
                    k = 0
                    while not stop.is_set():
                        atts = comp.heard("ATTITUDE")
                        for att in atts[seen:]:
                            k += 1
                            pwm = 1001 + k % 999  # (every value once in 10 s at 100 Hz)
                            stamps.setdefault(pwm, []).append(att.time_boot_ms * 1000)
                            controls = [0.1] * 3 + [(pwm - 1500) / 500.0] + [0.0] * 4
                            comp.send(comp.conn.mav.set_actuator_control_target_encode(att.time_boot_ms * 1000, 0, 1, 1,
                                                                                         controls))
                        seen = len(atts)
                        time.sleep(0.0005)

                mark = len(comp.heard("SERVO_OUTPUT_RAW"))
                thread = threading.Thread(target=answer, daemon=True)
                thread.start()
                time.sleep(seconds)
                stop.set()
                thread.join()
                lat, last = [], None
                outputs = comp.heard("SERVO_OUTPUT_RAW")[mark:]
                for m in outputs:
                    if m.servo4_raw != last and m.servo4_raw in stamps:
                        answered = [b for b in stamps[m.servo4_raw] if b <= m.time_usec]
                        if answered:
                            lat.append((m.time_usec - answered[-1]) / 1e3)
                    last = m.servo4_raw
                hz = [m.value for m in gcs.heard("NAMED_VALUE_FLOAT") if m.name.rstrip("\x00") == "TSW_HZ"]
                gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)
    if not lat:
        raise RuntimeError(f"no command reached the outputs: {len(stamps)} sent, {len(outputs)} SERVO_OUTPUT_RAW; "
                           f"{gcs.texts()[-5:]}")
    lat = np.array([x for x in lat if 0 <= x < 1000])
    return {"rate_hz": rate_hz, "latency_ms_p50": round(float(np.percentile(lat, 50)), 1),
            "latency_ms_p99": round(float(np.percentile(lat, 99)), 1), "samples": int(lat.size),
            "delivered_hz_median": float(np.median(hz[-int(seconds) + 2:])) if hz else None}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=20.0)
    args = ap.parse_args()
    if not firmware().is_file():
        print(f"bench_ardupilot: no ArduCopter SITL binary at {firmware()} (TRISWARM_ARDUCOPTER): skipped")
        return
    print(json.dumps({"six_drones": six_drones(args.seconds)}), flush=True)
    for rate in (100.0, 200.0):
        print(json.dumps({"one_drone": latency(rate, args.seconds)}), flush=True)


if __name__ == "__main__":
    main()
