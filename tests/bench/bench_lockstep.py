"""The whole stack on simulated time (make bench): `triswarm sitl up -n N --lockstep` and the
companions flying a plan, as fast as this machine allows.

For each run it reports the real-time factor the SITL achieved once every companion answered
(simulated seconds per wall second), the CPU of every process per simulated second (the SITL's, and
the companions' per agent), and the formation's worst error over the plan's settled window, judged
from the flight controllers' own telemetry. Several agents per companion process (one loop, one
Zenoh session) is the default; ``--agents-per-process 1`` gives each agent a process of its own.

    python tests/bench/bench_lockstep.py [PLAN (examples/paper-hexagon.toml)] [--sizes 6] [--duration-s 50]
                                         [--agents-per-process 0] [--judge-from 25]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import tomli_w

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tests.stack_helpers import judge, wait_sim  # noqa: E402
from triswarm.gcs.recorder import Recorder  # noqa: E402
from triswarm.gcs.scenarios import load_plan  # noqa: E402
from triswarm.gcs.stack import Stack  # noqa: E402

TICK_S = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    """User + system CPU time of a process so far [s]."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK_S


def plan_for(plan_path: Path, n: int, folder: Path) -> Path:
    """The plan file for n drones (``Plan.with_agents``'s spec when n differs)."""
    spec = tomllib.loads(plan_path.read_text())
    if spec["drones"] != n:
        spec = load_plan(str(plan_path), n).spec
    out = folder / f"plan-{n}.toml"
    out.write_text(tomli_w.dumps(spec))
    return out


def run(plan_path: Path, n: int, seconds: float, per_process: int, judge_from: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = plan_for(plan_path, n, tmp)
        plan = load_plan(str(path))
        t0 = time.monotonic()
        with Stack(path, tmp / "run", n, start_delay_s=5.0, lockstep=True, agents_per_process=per_process) as stack, \
                Recorder(stack.manifest) as rec:
            wait_sim(rec.now, stack.start_at, stack, wall_timeout_s=600.0)
            pids = {name: p.pid for name, p in stack.procs.items()}
            cpu0, wall0, sim0 = {name: cpu_s(pid) for name, pid in pids.items()}, time.monotonic(), rec.now()
            wait_sim(rec.now, stack.start_at + seconds, stack, wall_timeout_s=max(600.0, 40.0 * seconds))
            cpu1, wall1, sim1 = {name: cpu_s(pid) for name, pid in pids.items()}, time.monotonic(), rec.now()
        total_wall = time.monotonic() - t0
        ok, worst = judge(plan, rec, stack.start_at, min(judge_from, seconds - 1.0), seconds)
        sim = sim1 - sim0
        companions = sum(cpu1[k] - cpu0[k] for k in pids if k != "sitl")
        return {"n": n, "rtf": sim / (wall1 - wall0), "sitl_cpu_per_sim_s": (cpu1["sitl"] - cpu0["sitl"]) / sim,
                "agent_cpu_per_sim_s": companions / sim / n, "processes": len(pids) - 1, "ok": ok,
                "worst_m": max(p for p, _ in worst.values()), "worst_rad": max(a for _, a in worst.values()),
                "wall_s": total_wall, "stats": stack.stats("sitl").get("lockstep")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("plan", type=Path, nargs="?", default=ROOT / "examples" / "paper-hexagon.toml", help="plan file")
    ap.add_argument("--sizes", default="6", help="swarm sizes, comma-separated (the plan resized)")
    ap.add_argument("--duration-s", type=float, default=50.0, help="plan time flown [s]")
    ap.add_argument("--agents-per-process", type=int, default=0, help="agents per companion process (0: all in one)")
    ap.add_argument("--judge-from", type=float, default=25.0, help="the settled window starts here [s of plan time]")
    a = ap.parse_args()
    for n in [int(x) for x in a.sizes.split(",")]:
        try:
            r = run(a.plan, n, a.duration_s, a.agents_per_process, a.judge_from)
        except Exception as exc:  # name what failed, go on with the next size
            print(f"N = {n:4d}: FAILED: {exc.__class__.__name__}: {exc}", flush=True)
            continue
        print(f"N = {n:4d}, {r['processes']} companion process(es): real-time factor {r['rtf']:.2f}; CPU per simulated "
              f"second: SITL {r['sitl_cpu_per_sim_s']:.3f} s, {r['agent_cpu_per_sim_s']:.3f} s per agent; worst "
              f"{r['worst_m']:.4f} m / {r['worst_rad']:.4f} rad over [{min(a.judge_from, a.duration_s - 1):g}, {a.duration_s:g}] s "
              f"({'within' if r['ok'] else 'OUTSIDE'} 0.10 m / 0.02 rad); {r['wall_s']:.0f} s in all", flush=True)


if __name__ == "__main__":
    main()
