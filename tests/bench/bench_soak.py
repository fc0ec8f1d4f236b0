"""A long flight of the whole stack on simulated time (make bench): `triswarm sitl up --lockstep` and
the companions fly the paper's case study for ``--minutes`` of plan time (default 30), while the
leader is moved now and then by leader commands over MAVLink, as an operator would.

Every ``--sample-s`` of simulated time it reads each process's resident memory (RSS, /proc) and CPU
time (user + system): the SITL's and each companion process's. At the end it reports, per process:

- RSS after the entry, after the warm-up (``--warmup-min``: numba's compiled code, Zenoh's buffers,
  the allocator's arenas fill up), and at the end; the memory growth per 10 minutes, the slope of a
  least-squares line through the RSS samples after the warm-up, as a share of the RSS at its start;
- CPU per simulated second over the first and the last 10 minutes of the flight, and its change
  per 10 minutes between the two;
- how much each log and state file grew per simulated minute.

The target is growth under 1 % per 10 minutes for both. It exits 1 when a process misses it or the
formation misses its bounds (0.10 m, 0.02 rad) over the last 20 s, with the leader back where the
plan has it; 0 otherwise.

Leader commands: every ``--move-every-s`` a `leader goto`, alternately 3 m north of the plan's
leader and back, at 1 m/s; every third one is braked 2 s after its start by a `leader hold`, and
the next goto starts from wherever the hold left the leader. The last goto, 60 s before the end,
takes the leader back to the plan's x0.

    python tests/bench/bench_soak.py [--minutes 30] [--plan examples/paper-hexagon.toml]
                                     [--agents-per-process 0] [--sample-s 30] [--csv FILE]
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tests.bench.bench_lockstep import cpu_s  # noqa: E402
from tests.stack_helpers import judge, wait_sim  # noqa: E402
from triswarm.gcs.link import GroundLink  # noqa: E402
from triswarm.gcs.recorder import Recorder  # noqa: E402
from triswarm.gcs.scenarios import load_plan  # noqa: E402
from triswarm.gcs.stack import Stack  # noqa: E402
from triswarm.protocol.frames import flip  # noqa: E402
from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink  # noqa: E402

TARGET_PCT_PER_10_MIN = 1.0
LEAD_S = 3.0  # a leader command is timed this far ahead in plan time (sent to every drone meanwhile)
FIRST_SAMPLE_S = 30.0  # plan time of the first sample: the entry (15 s) is over


def rss_kib(pid: int) -> int:
    """Resident set size of a process [KiB]."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError(f"process {pid} has no VmRSS (gone?)")


def schedule(plan, end_s: float, every_s: float) -> list[tuple[float, str, tuple | None]]:
    """(plan time [s], "goto" or "hold", target in the plan's frame or None), in time order."""
    home = tuple(float(v) for v in plan.leader.kinematics(0.0).p[0])
    away = (home[0] + 3.0, home[1], home[2])
    out: list[tuple[float, str, tuple | None]] = []
    k = 1
    while k * every_s <= end_s - 60.0 - every_s / 2:
        out.append((k * every_s, "goto", away if k % 2 else home))
        if k % 3 == 0:
            out.append((k * every_s + 2.0, "hold", None))
        k += 1
    out.append((end_s - 60.0, "goto", home))
    return out


def command(link: GroundLink, n: int, kind: str, target, at_s: float) -> list[str]:
    """One leader command to every companion, for plan time at_s; the refusals, with their reasons."""
    if kind == "goto":
        north, east, down = (float(v) for v in flip(np.asarray(target)))
        cmd, params = mavlink.MAV_CMD_TRISWARM_LEADER_GOTO, [1.0, float("nan"), at_s, 0.0, north, east, down]
    else:
        cmd, params = mavlink.MAV_CMD_TRISWARM_LEADER_HOLD, [0.0, 0.0, at_s]
    refused = []
    for i in range(1, n + 1):
        result, why = link.command(i, COMP_ONBOARD, cmd, params)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            refused.append(f"drone {i}: {kind} at {at_s:.1f} s: result {result} {why}")
    return refused


def growth_pct_per_10_min(t_s: np.ndarray, values: np.ndarray) -> float:
    """Slope of the least-squares line through (t, value), per 10 minutes, as a percentage of the
    line's value at the first instant."""
    slope, intercept = np.polyfit(t_s, values, 1)
    return 100.0 * slope * 600.0 / (slope * t_s[0] + intercept)


def cpu_per_sim_s(t_s: np.ndarray, cpu: np.ndarray, lo: float, hi: float) -> float:
    """CPU seconds per simulated second between the samples nearest lo and hi."""
    a, b = int(np.argmin(abs(t_s - lo))), int(np.argmin(abs(t_s - hi)))
    return float((cpu[b] - cpu[a]) / (t_s[b] - t_s[a]))


def sizes(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_size for p in sorted(folder.rglob("*")) if p.is_file()}


def run(a) -> int:
    end_s = 60.0 * a.minutes
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(a.keep) if a.keep else Path(tmp)
        plan = load_plan(str(a.plan))
        t_wall0 = time.monotonic()
        with Stack(a.plan, tmp / "run", plan.n_agents, start_delay_s=5.0, lockstep=True,
                   agents_per_process=a.agents_per_process) as stack, \
                Recorder(stack.manifest) as rec, GroundLink(stack.endpoints()) as link:
            pids = {name: p.pid for name, p in stack.procs.items()}
            events = schedule(plan, end_s, a.move_every_s)
            samples: list[tuple[float, str, int, float]] = []  # (plan time, process, RSS KiB, CPU s)
            refusals: list[str] = []
            due_samples = [float(t) for t in np.arange(FIRST_SAMPLE_S, end_s, a.sample_s)] + [end_s]
            files0 = None
            while due_samples:
                due = min(due_samples[:1] + [e[0] - LEAD_S for e in events[:1]])
                wait_sim(rec.now, stack.start_at + due, stack, wall_timeout_s=600.0, poll_s=0.02)
                if events and due == events[0][0] - LEAD_S:
                    at_s, kind, target = events.pop(0)
                    refusals += command(link, plan.n_agents, kind, target, at_s)
                    continue
                t_plan = rec.now() - stack.start_at
                for name, pid in pids.items():
                    samples.append((t_plan, name, rss_kib(pid), cpu_s(pid)))
                if files0 is None:
                    files0 = (t_plan, sizes(tmp / "run"))
                print(f"t {t_plan:7.1f} s (wall {time.monotonic() - t_wall0:6.0f} s): " + ", ".join(
                    f"{name} {rss / 1024:.1f} MiB" for _, name, rss, _ in samples[-len(pids):]), flush=True)
                due_samples.pop(0)
            files1 = (rec.now() - stack.start_at, sizes(tmp / "run"))
            wait_sim(rec.now, stack.start_at + end_s + 0.5, stack)  # (the recorder's tracks reach the end)
            ok, worst = judge(plan, rec, stack.start_at, end_s - 20.0, end_s)
        wall_s = time.monotonic() - t_wall0

    if a.csv:
        with open(a.csv, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t_plan_s", "process", "rss_kib", "cpu_s"])
            w.writerows(samples)

    print(f"\n{a.minutes:g} simulated minutes of {a.plan.name} ({plan.n_agents} drones, {len(pids) - 1} companion "
          f"process(es)) in {wall_s:.0f} s of wall time: {end_s / wall_s:.2f} simulated seconds per wall second")
    warm_s = min(60.0 * a.warmup_min, end_s / 3)
    window = min(600.0, (end_s - 2 * FIRST_SAMPLE_S) / 2)
    failed = []
    for name in pids:
        t = np.array([s[0] for s in samples if s[1] == name])
        rss = np.array([s[2] for s in samples if s[1] == name], dtype=float)
        cpu = np.array([s[3] for s in samples if s[1] == name])
        after = t >= warm_s
        mem_growth = growth_pct_per_10_min(t[after], rss[after])
        first = cpu_per_sim_s(t, cpu, 2 * FIRST_SAMPLE_S, 2 * FIRST_SAMPLE_S + window)
        last = cpu_per_sim_s(t, cpu, end_s - window, end_s)
        apart_10_min = (end_s - window - 2 * FIRST_SAMPLE_S) / 600.0
        cpu_growth = 100.0 * (last / first - 1.0) / apart_10_min
        rss_warm = rss[np.argmin(abs(t - warm_s))]
        print(f"{name:>16}: RSS {rss[0] / 1024:.1f} MiB at {t[0]:.0f} s, {rss_warm / 1024:.1f} MiB at {warm_s:.0f} s, "
              f"{rss[-1] / 1024:.1f} MiB at {t[-1]:.0f} s: {mem_growth:+.2f} % per 10 min after the warm-up; CPU per "
              f"simulated second {first:.4f} s (first {window / 60:g} min) -> {last:.4f} s (last {window / 60:g} min): "
              f"{cpu_growth:+.2f} % per 10 min")
        if not (abs(mem_growth) < TARGET_PCT_PER_10_MIN and cpu_growth < TARGET_PCT_PER_10_MIN):
            failed.append(name)
    per_min = (files1[0] - files0[0]) / 60.0
    grown = {k: (files1[1].get(k, 0) - v) / per_min for k, v in files0[1].items()}
    grown.update({k: v / per_min for k, v in files1[1].items() if k not in files0[1]})
    print("files, bytes per simulated minute: " + ", ".join(f"{k} {v:.0f}" for k, v in sorted(grown.items())))
    print(f"formation over the last 20 s: worst {max(p for p, _ in worst.values()):.4f} m / "
          f"{max(q for _, q in worst.values()):.4f} rad ({'within' if ok else 'OUTSIDE'} 0.10 m / 0.02 rad)")
    for r in refusals:
        print(f"REFUSED: {r}")
    if failed:
        print(f"growth of {TARGET_PCT_PER_10_MIN:g} % per 10 min or more: {', '.join(failed)}")
    return 0 if ok and not failed and not refusals else 1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=30.0, help="plan time flown [simulated minutes]")
    ap.add_argument("--plan", type=Path, default=ROOT / "examples" / "paper-hexagon.toml")
    ap.add_argument("--agents-per-process", type=int, default=0, help="agents per companion process (0: all in one)")
    ap.add_argument("--sample-s", type=float, default=30.0, help="simulated seconds between samples")
    ap.add_argument("--warmup-min", type=float, default=5.0, help="memory growth is judged after this [simulated min]")
    ap.add_argument("--move-every-s", type=float, default=120.0, help="a leader command this often [simulated s]")
    ap.add_argument("--csv", type=Path, help="write every sample here (t_plan_s, process, rss_kib, cpu_s)")
    ap.add_argument("--keep", type=Path, help="run in this folder and keep it (logs, state, statistics)")
    a = ap.parse_args()
    if a.minutes < 3:
        ap.error("--minutes must be at least 3 (a warm-up, and a first and a last window)")
    sys.exit(run(a))


if __name__ == "__main__":
    main()
