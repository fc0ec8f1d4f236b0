"""Body rates: measured by the gyro or estimated by the observer (make bench). Run on one core:
OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python tests/bench/bench_rates.py

Flies the paper's case study (examples/paper-hexagon.toml, 50 s in-process, from rest on the ground)
with the controller's eta_dot from the observer alone and from the measured body rates, at several
sensor-noise levels (position, attitude and gyro together, 1 sigma, drawn every control tick) and
seeds, with the plan's servo delay and with a longer one than the controller compensates. Prints
the worst position and attitude error of any drone over [25 s, 50 s] on the plant's true state
(the paper's bounds: 0.10 m, 0.02 rad), the worst over the seeds and their mean."""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np

from triswarm.gcs.scenarios import load_plan
from triswarm.protocol import metrics
from triswarm.sitl.simulation import SensorNoise, SimConfig, simulate

LEVELS = {
    "none": None,
    "1x": SensorNoise(position_m=0.02, attitude_rad=0.005, gyro_rad_s=0.01),
    "2x": SensorNoise(position_m=0.04, attitude_rad=0.01, gyro_rad_s=0.02),
    "4x": SensorNoise(position_m=0.08, attitude_rad=0.02, gyro_rad_s=0.04),
}
MODES = {
    "observer": {"measured_rates": False},
    "measured": {"measured_rates": True},
}


def fly(plan, **kw) -> tuple[float, float]:
    r = simulate(plan, SimConfig(**kw))
    if r.diverged_at_s is not None:
        return float("inf"), float("inf")
    pos, att = metrics.formation_errors(plan, r.t_s, r.position_m, r.euler_rad)
    perf = metrics.assess(r.t_s, pos, att)
    return perf.worst_position_m, perf.worst_attitude_rad


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", default="1,2,3,4,5", help="comma-separated seeds (start positions and noise)")
    ap.add_argument("--levels", default=",".join(LEVELS), help=f"noise levels, of {list(LEVELS)}")
    ap.add_argument("--modes", default=",".join(MODES), help=f"where the RFL's rates come from, of {list(MODES)}")
    ap.add_argument("--servo-delays-ms", default="10,20", help="plant servo delays [ms] (the controller compensates the plan's 10)")
    ap.add_argument("--duration", type=float, default=50.0)
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    threads = {k: os.environ.get(k, "unset") for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")}
    print(f"python {platform.python_version()} on {platform.machine()}, {os.cpu_count()} cpus, threads {threads}")
    plan = load_plan("paper-hexagon")
    simulate(plan, SimConfig(duration_s=0.05))  # warm-up (JIT, caches)
    print(f"\npaper case study, {args.duration:g} s, worst error over [25 s, {args.duration:g} s], seeds {seeds}:")
    print(f"{'servo':>6} {'noise (pos m, att rad, gyro rad/s)':>36} {'rates':>9}   {'position m: worst / mean':>24}"
          f"   {'attitude rad: worst / mean':>26}")
    for delay_ms in (float(d) for d in args.servo_delays_ms.split(",")):
        for level in args.levels.split(","):
            noise = LEVELS[level]
            label = "none" if noise is None else f"{level}: {noise.position_m:g}, {noise.attitude_rad:g}, {noise.gyro_rad_s:g}"
            for mode in args.modes.split(","):
                runs = np.array([fly(plan, duration_s=args.duration, servo_delay_s=delay_ms / 1000.0, noise=noise,
                                     seed=seed, **MODES[mode]) for seed in seeds])
                print(f"{delay_ms:4g}ms {label:>36} {mode:>9}   {runs[:, 0].max():11.4f} / {runs[:, 0].mean():.4f}"
                      f"   {runs[:, 1].max():13.4f} / {runs[:, 1].mean():.4f}", flush=True)


if __name__ == "__main__":
    main()
