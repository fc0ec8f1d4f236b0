"""Benchmarks of the in-process batch simulation (make bench). Run on one core:
OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python tests/bench/bench_sim.py

Prints physics drone-steps per second of the whole batch simulation (physics RK4 at 1 kHz, control
at 200 Hz, every agent's observer, predictor, protocol and RFL included) for N = 6, 100, 1000, the
wall time of the 50 s paper scenario, and the design's servo-delay margins."""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from triswarm.gcs.scenarios import load_plan
from triswarm.protocol import metrics
from triswarm.sitl.physics import Plant
from triswarm.protocol.model import hover_trim
from triswarm.sitl.simulation import SimConfig, delay_margin, simulate


def batch_rate(n: int, duration_s: float) -> float:
    plan = load_plan("paper-hexagon", n)
    plan.check(horizon_s=duration_s)
    simulate(plan, SimConfig(duration_s=0.05, log_hz=10))  # warm-up (JIT, caches)
    best = 0.0
    for _ in range(3):
        r = simulate(plan, SimConfig(duration_s=duration_s, log_hz=10))
        best = max(best, n * duration_s * 1000.0 / r.wall_s)
    return best


def physics_rate(n: int, steps: int = 2000) -> float:
    plan = load_plan("paper-hexagon")
    omega, alpha = hover_trim(plan.airframe)
    plant = Plant(plan.airframe, n)
    plant.reset(np.tile([0.0, 0.0, 10.0], (n, 1)), servo_rad=alpha)
    plant.landed[:] = False
    plant.command(np.tile(omega, (n, 1)), np.tile(alpha, (n, 1)))
    plant.advance(10)
    t0 = time.perf_counter()
    plant.advance(steps)
    return n * steps / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--no-margins", action="store_true", help="skip the servo-delay margin search")
    args = ap.parse_args()
    threads = {k: os.environ.get(k, "unset") for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")}
    print(f"python {platform.python_version()} on {platform.machine()}, {os.cpu_count()} cpus, threads {threads}")
    print("\nbatch simulation (physics RK4 1 kHz + control 200 Hz), physics drone-steps per second:")
    for n, dur in ((6, 10.0), (100, 4.0), (1000, 2.0)):
        rate = batch_rate(n, dur)
        print(f"  N = {n:5d}: {rate:12,.0f} drone-steps/s   (physics alone: {physics_rate(n):12,.0f})")

    plan = load_plan("paper-hexagon")
    simulate(plan, SimConfig(duration_s=0.05))
    r = simulate(plan, SimConfig(duration_s=50.0))
    pe, ae = metrics.formation_errors(plan, r.t_s, r.position_m, r.euler_rad)
    perf = metrics.assess(r.t_s, pe, ae)
    print(f"\n50 s paper scenario (6 drones): wall time {r.wall_s:.2f} s ({50.0 / r.wall_s:.1f}x real time); "
          f"worst over [25 s, 50 s]: {perf.worst_position_m:.2e} m, {perf.worst_attitude_rad:.2e} rad")

    if not args.no_margins:
        def within(bound_m, bound_rad):
            def accept(res):
                pe, ae = metrics.formation_errors(plan, res.t_s, res.position_m, res.euler_rad)
                p = metrics.assess(res.t_s, pe, ae, position_bound_m=bound_m, attitude_bound_rad=bound_rad)
                return res.diverged_at_s is None and p.within_bounds
            return accept
        strict = delay_margin(plan, SimConfig(), within(0.10, 0.02), lo_s=0.01, hi_s=0.04, resolution_s=0.0005)
        loose = delay_margin(plan, SimConfig(), within(0.25, 0.05), lo_s=0.01, hi_s=0.04, resolution_s=0.0005)
        print(f"\nservo-delay margin (controller compensates 10 ms): within 0.10 m / 0.02 rad up to {strict * 1e3:.1f} ms; "
              f"within 0.25 m / 0.05 rad up to {loose * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
