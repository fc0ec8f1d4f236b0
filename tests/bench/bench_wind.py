"""What the formation control holds in wind (make bench). Run on one core:
OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python tests/bench/bench_wind.py

For each scenario (the paper's case study, its 24-drone resize, and the same hexagon held still) and
each case (steady wind; with moderate turbulence; with a 1-cosine gust in the settled window), flies
the plan for its full length with the in-process simulation at steady wind speeds 0, 2, ... 12 m/s
(on past 12 m/s while a bound still holds) and prints the worst position and attitude error over the
settled window, as `triswarm sim` judges them, in a markdown table with the command line of each
row; then the speed where the paper's bounds (0.10 m, 0.02 rad) and the wider ones (0.25 m, 0.05 rad)
break, refined by bisection to --resolution (assuming the error grows with the speed).
Each scenario is flown with the controllers' drag term on (the default: the RFL cancels the drag of
still air at the plan's air density) and off ([controller] air_density_kg_m3 = 0, the paper's law).
No sensor noise, no model mismatch, seed 0: the table is deterministic."""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time
from pathlib import Path

from triswarm.gcs.scenarios import load_plan
from triswarm.protocol import metrics
from triswarm.protocol.wind import TURBULENCE_SIGMA_W_M_S, Gust, Wind
from triswarm.sitl.simulation import SimConfig, simulate

ROOT = Path(__file__).resolve().parents[2]
BOUNDS = {"paper": (0.10, 0.02), "wide": (0.25, 0.05)}
SCENARIOS = {"paper-hexagon": ("paper-hexagon", None), "paper-hexagon-24": ("paper-hexagon", 24),
             "still-hexagon": ("examples/still-hexagon.toml", None)}


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    turbulence: str = "none"
    gust: tuple[float, float, float] | None = None  # peak [m/s], duration [s], start [s]

    def wind(self, speed_m_s: float) -> Wind:
        gusts = () if self.gust is None else (Gust(*self.gust),)
        return Wind(speed_m_s=speed_m_s, turbulence_sigma_w_m_s=TURBULENCE_SIGMA_W_M_S[self.turbulence], gusts=gusts)

    def flags(self, speed_m_s: float) -> str:
        text = f"--wind-m-s {speed_m_s:g}"
        if self.turbulence != "none":
            text += f" --turbulence {self.turbulence}"
        if self.gust is not None:
            text += " --gust " + ",".join(f"{v:g}" for v in self.gust)
        return text


def fly(plan, wind: Wind | None, seed: int) -> tuple[float, float, float | None]:
    """Worst position [m] and attitude [rad] error over the settled window, and when it diverged."""
    r = simulate(plan, SimConfig(duration_s=plan.duration_s, wind=wind, seed=seed))
    pe, ae = metrics.formation_errors(plan, r.t_s, r.position_m, r.euler_rad)
    window = plan.settled_from_s if plan.settled_from_s < plan.duration_s else 0.5 * plan.duration_s
    perf = metrics.assess(r.t_s, pe, ae, window_start_s=window)
    return perf.worst_position_m, perf.worst_attitude_rad, r.diverged_at_s


def with_drag_term(plan, on: bool):
    """The plan with the controllers' drag term as it is (on), or off: air_density_kg_m3 = 0."""
    if on:
        return plan
    return dataclasses.replace(plan, controller=dataclasses.replace(plan.controller, air_density_kg_m3=0.0))


def with_accelerometer(plan, on: bool):
    """The plan with the controllers taking the accelerometer (on) or not."""
    return dataclasses.replace(plan, controller=dataclasses.replace(plan.controller, accelerometer=on))


def within(result, bound: str) -> bool:
    pos, att, diverged = result
    return diverged is None and pos <= BOUNDS[bound][0] and att <= BOUNDS[bound][1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma-separated, of: " + ", ".join(SCENARIOS))
    ap.add_argument("--step-m-s", type=float, default=2.0, help="speed step of the sweep [m/s]")
    ap.add_argument("--min-top-m-s", type=float, default=12.0, help="sweep at least up to this speed [m/s]")
    ap.add_argument("--max-m-s", type=float, default=40.0, help="never beyond this speed [m/s]")
    ap.add_argument("--gust", default="6,2,40", help="the gust case's SPEED_M_S,DURATION_S,START_S")
    ap.add_argument("--resolution-m-s", type=float, default=0.5, help="bisection resolution of the break speeds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--drag-term", default="on,off", help="comma-separated, of: on, off (the controllers' drag term)")
    ap.add_argument("--accelerometer", choices=("on", "off"), default="on",
                    help="the controllers' accelerometer ([controller] accelerometer)")
    args = ap.parse_args()
    threads = {k: os.environ.get(k, "unset") for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")}
    print(f"python {platform.python_version()} on {platform.machine()}, {os.cpu_count()} cpus, threads {threads}")
    gust = tuple(float(v) for v in args.gust.split(","))
    cases = [Case("steady"), Case("moderate turbulence", turbulence="moderate"), Case("gust", gust=gust)]
    wall0 = time.perf_counter()
    summary = []
    runs = [(label.strip(), term.strip()) for label in args.scenarios.split(",") for term in args.drag_term.split(",")]
    for scenario_label, term in runs:
        if term not in ("on", "off"):
            raise SystemExit(f"--drag-term takes on and off, got {term!r}")
        source, drones = SCENARIOS[scenario_label]
        plan = with_drag_term(load_plan(str(ROOT / source) if source.endswith(".toml") else source, drones), term == "on")
        plan = with_accelerometer(plan, args.accelerometer == "on")
        label = f"{scenario_label}, drag term {term}"
        scenario = f"{source}" + (f" --drones {drones}" if drones else "")
        if term == "off":
            scenario += " (plan with [controller] air_density_kg_m3 = 0)"
        print(f"\n### {label}: {plan.n_agents} drones, settled window from {plan.settled_from_s:g} s to "
              f"{plan.duration_s:g} s\n")
        print("| wind [m/s] | turbulence | gust | worst position [m] | worst attitude [rad] | command |")
        print("|---|---|---|---|---|---|")
        pos, att, div = fly(plan, None, args.seed)
        print(f"| no air | | | {pos:.3g} | {att:.3g} | `triswarm sim {scenario}` |")
        for case in cases:
            results, speed = {}, 0.0
            while speed <= args.max_m_s + 1e-9:
                results[speed] = fly(plan, case.wind(speed), args.seed)
                pos, att, div = results[speed]
                shown = f"diverged at {div:.1f} s" if div is not None else f"{pos:.3g} | {att:.3g}"
                if div is not None:
                    shown = f"{shown} | {shown}"
                print(f"| {speed:g} | {case.turbulence} | {args.gust if case.gust else ''} | {shown} | "
                      f"`triswarm sim {scenario} {case.flags(speed)}` |", flush=True)
                if speed >= args.min_top_m_s and not any(within(results[speed], b) for b in BOUNDS):
                    break
                speed += args.step_m_s
            for bound in BOUNDS:
                summary.append((label, case.name, bound, break_speed(plan, case, results, bound, args)))
    print("\n| scenario | case | bounds | holds up to [m/s] | breaks at [m/s] |")
    print("|---|---|---|---|---|")
    for label, case, bound, (holds, breaks) in summary:
        p, a = BOUNDS[bound]
        print(f"| {label} | {case} | {p:g} m / {a:g} rad | {'-' if holds is None else f'{holds:g}'} | "
              f"{'not within ' + f'{args.max_m_s:g}' if breaks is None else f'{breaks:g}'} |")
    print(f"\nwall time {time.perf_counter() - wall0:.0f} s")


def break_speed(plan, case: Case, results: dict, bound: str, args) -> tuple[float | None, float | None]:
    """(last speed within the bounds, first speed past them), the gap closed to the resolution."""
    speeds = sorted(results)
    first_bad = next((s for s in speeds if not within(results[s], bound)), None)
    if first_bad is None:
        return speeds[-1], None
    good = [s for s in speeds if s < first_bad]
    if not good:
        return None, first_bad
    lo, hi = good[-1], first_bad
    while hi - lo > args.resolution_m_s + 1e-9:
        mid = 0.5 * (lo + hi)
        if within(fly(plan, case.wind(mid), args.seed), bound):
            lo = mid
        else:
            hi = mid
    return lo, hi


if __name__ == "__main__":
    main()
