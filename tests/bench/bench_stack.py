"""Benchmarks of the whole stack on this machine (make bench): `triswarm sitl up` plus one
`triswarm-companion` per drone flying the paper's plan (resized for N drones), real processes on
loopback, 200 Hz control (`--rate-hz` for another rate).

For the six-drone stack it reports, from arming to the end of the run, the worst companion's
control-loop jitter p99 (|interval between consecutive commands - the period|), telemetry-to-command
latency p50/p99 (the kernel's receive time of the telemetry datagram -> command handed to the
kernel), neighbour estimate age p50/p99 (published -> used), CPU (all threads, share of one core
since its first tick) and deadline misses (a command later than one period after its telemetry, or
a sample never acted on because the loop was late). Samples the flight controller sent late and
together ("superseded") are counted apart: that is the SITL's lag, not the loop's. Then it looks
for the largest swarm the machine runs with no more than 0.1 % deadline misses.
"""

from __future__ import annotations

import argparse
import copy
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

from triswarm.gcs.stack import Stack

ROOT = Path(__file__).resolve().parents[2]


def plan_for(n: int, folder: Path) -> Path:
    spec = tomllib.loads((ROOT / "examples" / "paper-hexagon.toml").read_text())
    spec = copy.deepcopy(spec)
    spec["drones"] = n
    spec["name"] = f"bench-{n}"
    path = folder / f"plan-{n}.toml"
    lines = [f'name = "{spec["name"]}"', f"drones = {n}"]
    for section in ("leader", "formation", "entry", "topology", "design", "controller"):
        lines.append(f"[{section}]")
        for k, v in spec[section].items():
            lines.append(f"{k} = {_toml(v)}")
    path.write_text("\n".join(lines) + "\n")
    return path


def _toml(v) -> str:
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return repr(v)


def run(n: int, seconds: float, rate_hz: float = 200.0, per_process: int = 1) -> list[dict]:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        with Stack(plan_for(n, tmp), tmp / "run", n, start_delay_s=10.0 + 0.5 * n, rate_hz=rate_hz,
                   agents_per_process=per_process) as stack:
            time.sleep(max(0.0, stack.start_at - time.time()) + seconds)
        return [stack.stats(str(i)) for i in range(1, n + 1)]


def summary(stats: list[dict], sharing: int = 1) -> dict:
    """``sharing``: agents per process (a process's CPU, which each of its agents reports, is theirs together)."""
    loops = [dict(s["loop"], cpu_fraction=s["loop"]["cpu_fraction"] / sharing) for s in stats]
    ticks = sum(lp["ticks"] for lp in loops)
    misses = sum(lp["deadline_misses"] for lp in loops)

    def worst(key):
        vals = [lp[key] for lp in loops if lp.get(key) is not None]
        return max(vals) if vals else float("nan")

    superseded = sum(lp.get("superseded_samples", 0) for lp in loops)
    return {"ticks": ticks, "miss_fraction": misses / max(ticks + misses, 1),
            "superseded_fraction": superseded / max(ticks + superseded, 1),
            "jitter_p99_ms": worst("jitter_p99_ms"), "latency_p50_ms": worst("latency_p50_ms"),
            "latency_p99_ms": worst("latency_p99_ms"), "nb_age_p50_ms": worst("neighbour_age_p50_ms"),
            "nb_age_p99_ms": worst("neighbour_age_p99_ms"), "cpu_max": worst("cpu_fraction"),
            "cpu_mean": float(np.mean([lp["cpu_fraction"] for lp in loops]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--duration-s", type=float, default=30.0, help="seconds of flight measured per run")
    ap.add_argument("--sizes", default="2,4,6,8,12,18,24", help="swarm sizes tried, in order, for the largest real-time swarm")
    ap.add_argument("--rate-hz", type=float, default=200.0, help="control rate of every companion (the targets are for 200 Hz)")
    ap.add_argument("--agents-per-process", type=int, default=1, help="agents per companion process (0: all in one)")
    args = ap.parse_args()
    rate, per = args.rate_hz, args.agents_per_process
    how = "one agent per companion process" if per == 1 else \
        "every agent in one companion process" if per == 0 else f"{per} agents per companion process"
    six = s = summary(run(6, args.duration_s, rate, per), 6 if per == 0 else per)
    print(f"six-drone stack at {rate:g} Hz, {how} (worst agent; a process's CPU shared by its agents):")
    print(f"  control loop jitter p99      {s['jitter_p99_ms']:.3f} ms   (target < 1 ms at 200 Hz)")
    print(f"  telemetry-to-command latency p50 {s['latency_p50_ms']:.3f} ms, p99 {s['latency_p99_ms']:.3f} ms   (target p99 < 2 ms)")
    print(f"  neighbour estimate age       p50 {s['nb_age_p50_ms']:.3f} ms, p99 {s['nb_age_p99_ms']:.3f} ms   (target p99 < 5 ms)")
    print(f"  CPU per agent                {100 * s['cpu_mean']:.1f} % mean, {100 * s['cpu_max']:.1f} % max of one core   (target < 10 % at 200 Hz)")
    print(f"  deadline misses              {100 * s['miss_fraction']:.3f} % of {s['ticks']} ticks "
          f"(and {100 * s['superseded_fraction']:.3f} % of samples superseded: the SITL late)")
    largest = 0
    for n in [int(x) for x in args.sizes.split(",")]:
        s = six if n == 6 else summary(run(n, args.duration_s, rate, per), n if per == 0 else per)
        ok = s["miss_fraction"] <= 0.001
        print(f"  N = {n:3d}: deadline misses {100 * s['miss_fraction']:.3f} %, CPU {100 * s['cpu_mean']:.1f} % mean, "
              f"latency p99 {s['latency_p99_ms']:.2f} ms -> {'real time' if ok else 'too many misses'}", flush=True)
        if not ok:
            break
        largest = n
    print(f"largest swarm in real time at {rate:g} Hz, {how} (<= 0.1 % deadline misses): {largest}")


if __name__ == "__main__":
    main()
