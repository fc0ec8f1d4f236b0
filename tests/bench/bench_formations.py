"""Benchmarks of large formations (make bench). Run on one core:
OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python tests/bench/bench_formations.py

Prints the wall time of the in-process simulation (physics 1 kHz, control 200 Hz) of 60 s of flight
at N = 100 and N = 1000 (the case study resized with --drones N: ring trees, the circle grown to keep
neighbours 2.76 m apart), and the time `triswarm plan check` takes, as a user runs it, for the case
study (N = 6) and for the same plan at N = 100. Each benchmark runs to its end or says what failed."""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import tomli_w

from triswarm.gcs.scenarios import load_plan
from triswarm.protocol import metrics
from triswarm.sitl.simulation import SimConfig, simulate


def sim_wall(n: int, duration_s: float) -> str:
    plan = load_plan("paper-hexagon", n)
    simulate(load_plan("paper-hexagon", 6), SimConfig(duration_s=0.05))  # warm-up (JIT, caches)
    r = simulate(plan, SimConfig(duration_s=duration_s, log_hz=10))
    if r.diverged_at_s is not None:
        return f"FAILED: drone {r.diverged_drone} diverged at {r.diverged_at_s:.2f} s"
    out = f"{r.wall_s:6.1f} s ({duration_s / r.wall_s:5.1f}x real time); circle of {plan.formation.radius_m:.0f} m"
    if plan.settled_from_s >= duration_s:
        return out + f", still entering it (the settled window starts at {plan.settled_from_s:.0f} s)"
    pe, ae = metrics.formation_errors(plan, r.t_s, r.position_m, r.euler_rad)
    perf = metrics.assess(r.t_s, pe, ae, window_start_s=plan.settled_from_s)
    return out + (f"; worst over [{perf.window_start_s:.0f} s, {duration_s:g} s]: {perf.worst_position_m:.1e} m, "
                  f"{perf.worst_attitude_rad:.1e} rad")


def plan_check_wall(plan_file: str) -> str:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "triswarm.gcs.cli", "plan", "check", plan_file], capture_output=True,
                       text=True, timeout=900)
    wall = time.perf_counter() - t0
    if r.returncode != 0 or "plan OK" not in r.stdout:
        return f"FAILED (exit {r.returncode}): {r.stderr.strip() or r.stdout.strip()[-300:]}"
    return f"{wall:6.1f} s (plan OK: checked, certified and flown)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--duration-s", type=float, default=60.0, help="flight time of the simulation benchmarks")
    args = ap.parse_args()
    threads = {k: os.environ.get(k, "unset") for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")}
    print(f"python {platform.python_version()} on {platform.machine()}, {os.cpu_count()} cpus, threads {threads}")
    print(f"\nin-process simulation, {args.duration_s:g} s of flight (`triswarm sim --drones N`):")
    for n in (100, 1000):
        print(f"  N = {n:4d}: {sim_wall(n, args.duration_s)}", flush=True)

    print("\n`triswarm plan check` (a fresh process: import, design, certificate, separation, 60 s flight):")
    with tempfile.TemporaryDirectory() as tmp:
        big = Path(tmp) / "paper-hexagon-100.toml"
        big.write_text(tomli_w.dumps(load_plan("paper-hexagon", 100).spec))
        for n, plan_file in ((6, "paper-hexagon"), (100, str(big))):
            print(f"  N = {n:4d}: {plan_check_wall(plan_file)}", flush=True)


if __name__ == "__main__":
    main()
