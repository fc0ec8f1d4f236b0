"""Fly the paper's plan with the whole stack with every companion's Zenoh traffic through a delay
relay (run inside the network namespace of tests/test_stack_lossy.py, whose iptables rules drop at
random). Writes what happened as JSON for the test to judge.

    python tests/lossy_flight.py OUT.json WORKDIR --delay-ms 20
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.conftest import PAPER_PLAN_FILE  # noqa: E402
from tests.netem import DelayRelay  # noqa: E402
from tests.stack_helpers import judge  # noqa: E402
from triswarm.gcs.recorder import Recorder  # noqa: E402
from triswarm.gcs.scenarios import load_plan  # noqa: E402
from triswarm.gcs.stack import Stack  # noqa: E402

N = 6
ZENOH_BASE = 17447   # agent i listens on base + i (TCP and UDP): the namespace is ours alone
RELAY_BASE = 18447   # agent i is reached through the relay at relay base + i


def zenoh_args(i: int) -> list[str]:
    args = [f"--zenoh-listen=tcp/127.0.0.1:{ZENOH_BASE + i}", f"--zenoh-listen=udp/127.0.0.1:{ZENOH_BASE + i}"]
    for j in range(1, N + 1):
        if j != i:
            args += [f"--zenoh-connect=tcp/127.0.0.1:{RELAY_BASE + j}", f"--zenoh-connect=udp/127.0.0.1:{RELAY_BASE + j}"]
    return args


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--delay-ms", type=float, default=20.0)
    ap.add_argument("--until-s", type=float, default=50.0)
    ap.add_argument("--bound-m", type=float, default=0.5)
    a = ap.parse_args()
    plan = load_plan(str(PAPER_PLAN_FILE))
    routes = {RELAY_BASE + i: ZENOH_BASE + i for i in range(1, N + 1)}
    with DelayRelay(routes, a.delay_ms / 1000.0) as relay:
        with Stack(PAPER_PLAN_FILE, a.workdir, N, start_delay_s=12.0,
                   companion_args={i: zenoh_args(i) for i in range(1, N + 1)}) as stack, Recorder(stack.manifest) as rec:
            start = stack.start_at
            while time.time() < start + a.until_s:
                time.sleep(0.5)
            alive = stack.alive()
    ok, worst = judge(plan, rec, start, 25.0, a.until_s, position_bound_m=a.bound_m, attitude_bound_rad=float("inf"))
    result = {"ok": ok, "worst": worst, "alive": alive, "relay": dict(relay.counters),
              "companions": {i: stack.stats(str(i)) for i in range(1, N + 1)}}
    a.out.write_text(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main()
