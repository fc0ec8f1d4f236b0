"""The formation in the goal's air and in other air, in-process (make bench): the case study resized to
N drones (`triswarm sim --drones N`), 60 s, the worst position and attitude errors over the settled
window, as `triswarm sim` judges them. Prints three markdown tables of docs/wind.md, the first two
its section "The accelerometer"'s:

- the goal's air (8 m/s steady with moderate turbulence), each seed, the controllers without the
  accelerometer and with it (the law as it ships), a flight of which outside the goal (0.25 m,
  0.05 rad) in bold;
- other air, with it: 4 m/s steady (the worst over the seeds), 12 m/s steady, severe turbulence, a
  6 m/s gust of 2 s at 40 s (seed 0), and the worst air (12 m/s, severe turbulence and the gust),
  seeds 0 and 1, without the accelerometer in brackets;
- servos of finite speed (docs/wind.md's section "Servos of finite speed"): at once (the paper's
  servos), 1200, 600 and 300 deg/s, the controllers told their speed by the plan's airframe, and
  600 deg/s not told (the plant's servos alone slow), in no air (without the accelerometer, as a plan
  flies there), 4 m/s steady, the goal's air (the worst over the seeds) and the worst air (seed 0).

Every flight is seeded: the tables are deterministic. Run on one core per job:

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 \\
        python tests/bench/bench_goal.py [--sizes 6,24,50,100,200] [--servo-sizes 6,24,50] [--seeds 3] [--jobs 1] \\
            [--tables goal,other,servos]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from triswarm.gcs.scenarios import read_plan_spec  # noqa: E402
from triswarm.protocol import metrics  # noqa: E402
from triswarm.protocol.plan import plan_from_dict  # noqa: E402
from triswarm.protocol.wind import Gust, Wind, turbulence_sigma_w  # noqa: E402
from triswarm.sitl.simulation import SimConfig, simulate  # noqa: E402

GOAL = (0.25, 0.05)  # [m], [rad]
GUST = Gust(speed_m_s=6.0, duration_s=2.0, start_s=40.0)


def _air(speed_m_s: float = 0.0, turbulence: str = "none", gust: bool = False) -> Wind:
    return Wind(speed_m_s=speed_m_s, turbulence_sigma_w_m_s=turbulence_sigma_w(turbulence, "turbulence"),
                gusts=(GUST,) if gust else ())


AIRS = {"none": None, "goal": _air(8.0, "moderate"), "4 steady": _air(4.0), "12 steady": _air(12.0),
        "severe": _air(turbulence="severe"), "gust": _air(gust=True), "worst": _air(12.0, "severe", gust=True)}
"""The air of each flight (none: the paper's model, no air at all): `--wind-m-s 8 --turbulence moderate`, `--wind-m-s 4`, `--wind-m-s 12`,
`--turbulence severe`, `--gust 6,2,40`, and all of the last three."""


@dataclasses.dataclass(frozen=True)
class Flight:
    drones: int
    air: str
    seed: int
    accelerometer: bool
    servo_deg_s: float = 0.0
    """The servos' speed [deg/s] (0: at once)."""
    told: bool = True
    """The controllers are told the servos' speed (the plan's airframe), or not (the plant's alone)."""


@functools.cache
def _plan(drones: int, accelerometer: bool, servo_deg_s: float):
    spec, label = read_plan_spec("paper-hexagon")
    if servo_deg_s:
        spec.setdefault("airframe", {})["servo_rate_rad_s"] = math.radians(servo_deg_s)
    plan = plan_from_dict(spec, label).with_agents(drones)
    return dataclasses.replace(plan, controller=dataclasses.replace(plan.controller, accelerometer=accelerometer))


def fly(f: Flight) -> tuple[float, float, float | None]:
    """The worst position [m] and attitude [rad] errors over the settled window, and when the flight
    diverged (None: it did not)."""
    plan = _plan(f.drones, f.accelerometer, f.servo_deg_s if f.told else 0.0)
    r = simulate(plan, SimConfig(duration_s=plan.duration_s, wind=AIRS[f.air], seed=f.seed,
                                 servo_rate_deg_s=f.servo_deg_s))
    perf, _ = metrics.judge(plan, r.t_s, r.position_m, r.euler_rad)
    return perf.worst_position_m, perf.worst_attitude_rad, r.diverged_at_s


def _goal_cell(result, mark_misses: bool) -> str:
    pos, att, diverged = result
    text = f"diverged at {diverged:.1f} s" if diverged is not None else f"{pos:.3f} m, {att:.3f} rad"
    missed = diverged is not None or pos > GOAL[0] or att > GOAL[1]
    return f"**{text}**" if mark_misses and missed else text


def _cell(result) -> str:
    pos, att, diverged = result
    if diverged is not None:
        return f"diverged at {diverged:.1f} s"
    return f"{pos:.3f} m, " + ("< 0.001 rad" if att < 0.0005 else f"{att:.3f} rad")


def _worst_over(results) -> tuple[float, float, float | None]:
    diverged = [d for _, _, d in results if d is not None]
    return (max(p for p, _, _ in results), max(a for _, a, _ in results), min(diverged) if diverged else None)


def _pair(a, b) -> str:
    """Two flights (seeds 0 and 1) in one cell: '0.298 / 0.588 m, 0.129 / 0.155 rad'."""
    if a[2] is not None or b[2] is not None:
        return " / ".join(_cell(r) for r in (a, b))
    return f"{a[0]:#.3g} / {b[0]:#.3g} m, {a[1]:#.3g} / {b[1]:#.3g} rad"


def _header(*columns: str) -> None:
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))


def flights(sizes: list[int], servo_sizes: list[int], seeds: int, tables: set[str]) -> list[Flight]:
    out = []
    for n in servo_sizes if "servos" in tables else ():
        for speed, told in SERVOS:
            out += [Flight(n, air, 0, air != "none", speed, told) for air in ("none", "4 steady", "worst")]
            out += [Flight(n, "goal", s, True, speed, told) for s in range(seeds)]
    for n in sizes:
        if "goal" in tables:
            out += [Flight(n, "goal", s, acc) for acc in (False, True) for s in range(seeds)]
        if "other" in tables:
            out += [Flight(n, "4 steady", s, True) for s in range(seeds)]
            out += [Flight(n, air, 0, True) for air in ("12 steady", "severe", "gust")]
            out += [Flight(n, "worst", s, acc) for acc in (True, False) for s in (0, 1)]
    return out


SERVOS = ((0.0, True), (1200.0, True), (600.0, True), (300.0, True), (600.0, False))
"""The servo speeds of the servos' table [deg/s] (0: at once), and whether the controllers are told."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="6,24,50,100,200", help="comma-separated swarm sizes")
    ap.add_argument("--servo-sizes", default="6,24,50", help="comma-separated swarm sizes of the servos' table")
    ap.add_argument("--seeds", type=int, default=3,
                    help="seeds 0 .. SEEDS-1 in the goal's air and at 4 m/s (the worst air: seeds 0 and 1)")
    ap.add_argument("--jobs", type=int, default=1, help="flights flown at once, one process each")
    ap.add_argument("--tables", default="goal,other,servos", help="comma-separated, of: goal, other, servos")
    args = ap.parse_args()
    try:
        sizes, servo_sizes = ([int(s) for s in text.split(",")] for text in (args.sizes, args.servo_sizes))
    except ValueError:
        ap.error(f"--sizes and --servo-sizes take whole numbers separated by commas, got {args.sizes!r}, "
                 f"{args.servo_sizes!r}")
    tables = set(args.tables.split(","))
    if not tables <= {"goal", "other", "servos"} or args.seeds < 1 or args.jobs < 1 or min(sizes + servo_sizes) < 1:
        ap.error("--tables takes goal, other and servos; --sizes, --servo-sizes, --seeds and --jobs at least 1")
    todo = flights(sizes, servo_sizes, args.seeds, tables)
    if args.jobs == 1:
        results = dict(zip(todo, map(fly, todo)))
    else:
        with ProcessPoolExecutor(args.jobs) as pool:
            results = dict(zip(todo, pool.map(fly, todo)))
    seeds = "seed 0" if args.seeds == 1 else f"seeds 0-{args.seeds - 1}"
    if "goal" in tables:
        _header("drones", *(f"seed {s}" for s in range(args.seeds)))
        for n in sizes:
            for acc, word in ((False, "without"), (True, "with")):
                cells = [_goal_cell(results[Flight(n, "goal", s, acc)], acc) for s in range(args.seeds)]
                print(f"| {n}, {word} | " + " | ".join(cells) + " |")
        print()
    if "other" in tables:
        _header("drones", f"4 m/s steady, {seeds}", "12 m/s steady", "severe turbulence", "gust 6 m/s, 2 s",
                "12 m/s + severe + gust, seeds 0 / 1 (without)")
        for n in sizes:
            steady = _worst_over([results[Flight(n, "4 steady", s, True)] for s in range(args.seeds)])
            alone = [_cell(results[Flight(n, air, 0, True)]) for air in ("12 steady", "severe", "gust")]
            worst = [[results[Flight(n, "worst", s, acc)] for s in (0, 1)] for acc in (True, False)]
            print(f"| {n} | {_cell(steady)} | " + " | ".join(alone) + f" | {_pair(*worst[0])} ({_pair(*worst[1])}) |")
        print()
    if "servos" in tables:
        _header("drones", "servos", "no air", "4 m/s steady", f"8 m/s + moderate turbulence, {seeds}",
                "12 m/s + severe + gust")
        for n in servo_sizes:
            for speed, told in SERVOS:
                name = "at once" if not speed else f"{speed:g} deg/s" + ("" if told else ", not told")
                one = [_cell(results[Flight(n, air, 0, air != "none", speed, told)]) for air in ("none", "4 steady")]
                goal = _worst_over([results[Flight(n, "goal", s, True, speed, told)] for s in range(args.seeds)])
                worst = _cell(results[Flight(n, "worst", 0, True, speed, told)])
                print(f"| {n} | {name} | " + " | ".join(one) + f" | {_cell(goal)} | {worst} |")


if __name__ == "__main__":
    main()
