"""Fly the paper's plan with the whole stack, in real time, with every companion's Zenoh traffic
through a delay relay (run inside the network namespace of tests/test_stack_lossy.py, whose
iptables rules drop at random). Writes what happened as JSON for the test to judge.

    python tests/lossy_flight.py OUT.json WORKDIR --delay-ms 20

The companions fly at ``--rate-hz`` (100), one per process so that all their traffic crosses the
relay. They are started with the plan scheduled an hour ahead; once every one of them says it is
ready (its heartbeat: phase "scheduled"), the ground station starts the plan a few seconds later
with MAV_CMD_TRISWARM_PLAN_START, as an operator does. So however long a loaded machine takes to
start six companions, none is late for the start.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.conftest import PAPER_PLAN_FILE  # noqa: E402
from tests.netem import DelayRelay, shipped_peer_endpoints  # noqa: E402
from tests.priority import prioritise  # noqa: E402
from tests.stack_helpers import judge  # noqa: E402
from triswarm.gcs.link import GroundLink  # noqa: E402
from triswarm.gcs.recorder import Recorder  # noqa: E402
from triswarm.gcs.scenarios import load_plan  # noqa: E402
from triswarm.gcs.stack import Stack  # noqa: E402
from triswarm.gcs.swarm_cmd import start_all  # noqa: E402
from triswarm.protocol.codec import plan_id  # noqa: E402

N = 6
ZENOH_BASE = 17447   # agent i listens on base + i (TCP and UDP): the namespace is ours alone
RELAY_BASE = 18447   # agent i is reached through the relay at relay base + i
SCHEDULED = 1        # a companion's heartbeat custom_mode when its plan waits for its start
START_IN_S = 5.0     # from the last companion ready to the start (they arm 2 s before it)
READY_WITHIN_S = 120.0


def zenoh_args(i: int) -> list[str]:
    """Agent i's Zenoh endpoints as the shipped peer configuration makes them: it listens on its own
    port and connects to every other agent through the relay."""
    args = [f"--zenoh-listen={e}" for e in shipped_peer_endpoints(ZENOH_BASE + i)]
    for j in range(1, N + 1):
        if j != i:
            args += [f"--zenoh-connect={e}" for e in shipped_peer_endpoints(RELAY_BASE + j)]
    return args


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--delay-ms", type=float, default=20.0)
    ap.add_argument("--rate-hz", type=float, default=100.0)
    ap.add_argument("--from-s", type=float, default=20.0, help="judged from this plan time")
    ap.add_argument("--until-s", type=float, default=40.0, help="flown and judged until this plan time")
    ap.add_argument("--nice", type=int, default=0, help="run the stack at this niceness (see prioritise)")
    ap.add_argument("--speedup", type=float, default=1.0, help="the SITL's simulated seconds per wall second (sitl up --speedup)")
    a = ap.parse_args()
    scheduling = prioritise(a.nice)
    plan = load_plan(str(PAPER_PLAN_FILE))
    routes = {RELAY_BASE + i: ZENOH_BASE + i for i in range(1, N + 1)}
    t0 = time.monotonic()
    times = {}
    with DelayRelay(routes, a.delay_ms / 1000.0) as relay:
        with Stack(PAPER_PLAN_FILE, a.workdir, N, start_delay_s=3600.0, rate_hz=a.rate_hz, sitl_args=["--speedup", str(a.speedup)],
                   companion_args={i: zenoh_args(i) for i in range(1, N + 1)}) as stack, \
                Recorder(stack.manifest) as rec, GroundLink(stack.endpoints(), tlog=a.workdir / "gcs.tlog") as link:
            deadline = time.monotonic() + READY_WITHIN_S
            while not all((hb := link.companion(i).heartbeat) is not None and hb.custom_mode == SCHEDULED
                          for i in range(1, N + 1)):
                dead = [name for name, up in stack.alive().items() if not up]
                if dead or time.monotonic() > deadline:
                    raise SystemExit(f"companions not ready within {READY_WITHIN_S:.0f} s (dead: {dead})")
                time.sleep(0.1)
            times["ready_s"] = time.monotonic() - t0
            # a whole second of the flight controllers' clock (PLAN_START carries seconds and milliseconds)
            start = float(math.ceil((link.fc_now() if math.isfinite(link.fc_now()) else time.time()) + START_IN_S))
            started = start_all(link, list(range(1, N + 1)), plan_id(plan.spec), start)
            if not all(ok for ok, _ in started.values()):
                raise SystemExit(f"the plan did not start: {started}")
            deadline = time.monotonic() + a.until_s + START_IN_S + 60.0
            lag = []  # (plan time, how far the flight controllers' clock is behind the wall's [s])
            while not rec.now() >= start + a.until_s:
                lag.append((rec.now() - start, time.time() - rec.now()))
                dead = [name for name, up in stack.alive().items() if not up]
                if dead or time.monotonic() > deadline:
                    raise SystemExit(f"the flight did not reach plan time {a.until_s} s (dead: {dead})")
                time.sleep(0.1)
            alive = stack.alive()
            flown_s = rec.now() - start + START_IN_S
    times["wall_s"] = time.monotonic() - t0
    cpu = {who: round(u.ru_utime + u.ru_stime, 1) for who, u in (("stack", resource.getrusage(resource.RUSAGE_CHILDREN)),
                                                                 ("relay_and_recorder", resource.getrusage(resource.RUSAGE_SELF)))}
    ok, worst = judge(plan, rec, start, a.from_s, a.until_s, position_bound_m=float("inf"), attitude_bound_rad=float("inf"))
    from triswarm.protocol import metrics
    t, pos, eta = rec.arrays(start, t_from=a.from_s, t_to=a.until_s)
    pe, ae = metrics.formation_errors(plan, t, pos, eta)
    series = {int(k): [(round(float(t[j]), 2), round(float(pe[j, k]), 3), round(float(ae[j, k].max()), 3)) for j in range(0, len(t)) if ae[j, k].max() > 0.02 or pe[j, k] > 0.05] for k in range(plan.n_agents)}
    lag_ms = along_track_lag_ms(plan, rec, start, a.from_s - 5.0, a.from_s)
    holds = {i: [line.split("companion ", 1)[1] for line in stack.log(f"companion-{i}").splitlines() if "hold at t_plan" in line]
             for i in range(1, N + 1)}
    sitl = stack.stats("sitl")
    # the flight controllers' own word: any mode but EXTERNAL once the plan flies (HOLD: the failsafe
    # of a companion silent for 0.3 s)
    modes = {i: [(round(t - start, 2), mode) for t, mode, armed in rec.modes.get(i, []) if start + 1.0 < t < start + a.until_s]
             for i in range(1, N + 1)}
    result = {"series": series, "worst": worst, "alive": alive, "relay": dict(relay.counters), "times": times, "holds": holds, "modes": modes,
              "late": [line for i in range(1, N + 1) for line in stack.log(f"companion-{i}").splitlines() if "late for the start" in line],
              "cpu_s": cpu, "flown_s": round(flown_s, 1), "along_track_lag_ms": lag_ms, "scheduling": scheduling,
              "clock_behind_wall_s": _spread([b for t, b in lag if t > 0.0]),
              "sitl": {"wall_time_s": sitl["wall_time_s"], "max_lag_s": sitl["max_lag_s"], "overruns": sitl["overruns"]},
              "companions": {i: stack.stats(str(i)) for i in range(1, N + 1)}}
    a.out.write_text(json.dumps(result, indent=1, default=float))


def along_track_lag_ms(plan, rec, start: float, t_from: float, t_to: float) -> dict[int, float]:
    """Per drone, how late it flies its place on the circle (its mean position error along its
    place's velocity, over that speed) [ms]: a clock or a loop running late shows here."""
    import numpy as np

    t, pos, _ = rec.arrays(start, t_from=t_from, t_to=t_to)
    out = {}
    for i in range(plan.n_agents):
        lags = []
        for k, tk in enumerate(t):
            h, h_dot = plan.formation.offsets(tk)
            x0, _ = plan.leader.offsets(tk)
            v = h_dot[i, 9:12]
            lags.append(-float((pos[k, i] - h[i, 9:12] - x0[0, 9:12]) @ v) / float(v @ v))
        out[i + 1] = round(1000.0 * float(np.mean(lags)), 2)
    return out


def _spread(values: list[float]) -> dict:
    """How far behind the wall the flight controllers' clock was in flight, as heard here (the
    recorder's own delay included): least, median, most [s]."""
    if not values:
        return {}
    v = sorted(values)
    return {"min": round(v[0], 3), "p50": round(v[len(v) // 2], 3), "max": round(v[-1], 3)}


if __name__ == "__main__":
    main()
