"""The formation on each estimator profile (``sitl.estimator``), in-process (make bench): the case
study resized to N drones, in still air and in the goal's air (8 m/s steady with moderate
turbulence), three seeds each; the worst position and attitude errors over the settled window
across the seeds, or the first divergence. Prints the markdown table of docs/wind.md's section
"Estimates as autopilots give them".

    python tests/bench/bench_estimators.py [--sizes 6,24,50] [--seeds 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from triswarm.gcs.scenarios import load_plan  # noqa: E402
from triswarm.protocol import metrics  # noqa: E402
from triswarm.protocol.wind import Wind, turbulence_sigma_w  # noqa: E402
from triswarm.sitl.estimator import PROFILES  # noqa: E402
from triswarm.sitl.simulation import SimConfig, simulate  # noqa: E402

AIRS = {"still air": None,
        "8 m/s + moderate": Wind(speed_m_s=8.0, turbulence_sigma_w_m_s=turbulence_sigma_w("moderate", "turbulence"))}


def worst(n: int, prof, wind, seeds: int, accelerometer: bool | None) -> str:
    plan = load_plan(str(ROOT / "examples" / "paper-hexagon.toml"), n)
    if accelerometer is not None:
        plan = dataclasses.replace(plan, controller=dataclasses.replace(plan.controller, accelerometer=accelerometer))
    pos = att = 0.0
    for seed in range(seeds):
        r = simulate(plan, SimConfig(duration_s=60.0, estimator=prof, wind=wind, seed=seed))
        if r.diverged_at_s is not None:
            return f"diverged (seed {seed}, {r.diverged_at_s:.0f} s)"
        perf, _ = metrics.judge(plan, r.t_s, r.position_m, r.euler_rad)
        pos, att = max(pos, perf.worst_position_m), max(att, perf.worst_attitude_rad)
    return f"{pos:.3g} m, {att:.3g} rad"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="6,24,50")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--accelerometer", choices=("on", "off"), default=None,
                    help="the controllers' accelerometer ([controller] accelerometer; default: the plan's, on in air)")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    print("| drones | air | " + " | ".join(PROFILES) + " |")
    print("|---|---|" + "---|" * len(PROFILES))
    for n in sizes:
        for air, wind in AIRS.items():
            on = None if args.accelerometer is None else args.accelerometer == "on"
            cells = [worst(n, prof, wind, args.seeds, on) for prof in PROFILES.values()]
            print(f"| {n} | {air} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
