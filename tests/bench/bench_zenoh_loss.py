"""The companions' Zenoh bus on a lossy network (make bench): for each link layout, do the peers hear
each other, and how far apart do the estimates come?

In a network namespace of its own (root), ``--peers`` processes each open the companion's own bus
(``companion.bus.Bus``, copies or not as the companion decides from its endpoints), join as one
agent listening to all the others, and publish an estimate every 10 ms and a status every second.
All their traffic crosses ``tests.netem.DelayRelay`` (``--delay-ms`` each way), and iptables drops
``--drop`` of it, UDP and TCP alike. At one instant, the same for all, each peer reports per
neighbour whether it has its liveliness token, a status within 2.5 s and an estimate within 1 s,
and the largest gap between two of its estimates after ``WARM_UP_S``. A run is deaf when some peer
lacks one of these for some neighbour.

    python tests/bench/bench_zenoh_loss.py [--layouts tcp+udp,quic,quic-with-copies] [--runs 4]
        [--peers 6] [--duration-s 20] [--drop 0.2] [--delay-ms 20]

Layouts: ``tcp+udp`` (a TCP and a UDP link per peer, as in the client configuration), ``quic`` (one
reliable UDP link per peer, the shipped peer configuration's), ``quic-with-copies`` (the same with
the reliable copies of the estimates forced on).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

ZENOH_BASE = 17447   # peer i listens on base + i: the namespace is ours alone
RELAY_BASE = 18447   # and is reached through the relay at relay base + i
PLAN = 0x5EED
WARM_UP_S = 5.0      # estimate gaps are counted from this long after a peer's start
LAYOUTS = {"tcp+udp": ("tcp+udp", None), "quic": ("shipped", None), "quic-with-copies": ("shipped", True)}
"""Layout -> (its endpoints: a TCP and a UDP one, or the shipped peer configuration's; the reliable
copies forced on, or None: as the companion decides)."""


def endpoints(layout: str, port: int) -> list[str]:
    from tests.netem import at_loopback, shipped_peer_endpoints

    return at_loopback(["tcp/", "udp/"], port) if LAYOUTS[layout][0] == "tcp+udp" else shipped_peer_endpoints(port)


def peer(i: int, n: int, layout: str, snapshot_at: float, out: Path) -> None:
    """One peer, until two seconds after ``snapshot_at`` (Unix time); writes what it heard to ``out``."""
    import numpy as np

    from triswarm.companion.bus import Bus
    from triswarm.companion.zenoh_session import copies_backup, peer_config
    from triswarm.protocol.codec import AgentStatus, agent_of_key

    copies = LAYOUTS[layout][1]
    config = peer_config(endpoints(layout, ZENOH_BASE + i),
                         [e for j in range(1, n + 1) if j != i for e in endpoints(layout, RELAY_BASE + j)])
    others = [j for j in range(1, n + 1) if j != i]
    xi = np.linspace(-1.0, 1.0, 12)

    async def run() -> dict:
        bus = Bus("loss", n, copies=copies_backup(config) if copies is None else copies)
        bus.open(config, asyncio.get_running_loop())
        bus.join(i, PLAN, frozenset(others))
        t0 = time.monotonic()
        seq = dict.fromkeys(others, -1)
        last_estimate, last_status, gap = {}, {}, dict.fromkeys(others, 0.0)
        take_status = bus._status

        def status(key: str, data: bytes) -> None:  # (when each agent's status came, beside the bus's own handling)
            take_status(key, data)
            j = agent_of_key(key)
            if j is not None:
                last_status[j] = time.monotonic() - t0

        bus._status = status
        report, k = None, 0
        try:
            while time.time() < snapshot_at + 2.0:
                now = time.monotonic() - t0
                bus.publish_estimate(i, xi, now, AgentStatus.FLYING)
                if k % 100 == 0:
                    bus.publish_status(i, AgentStatus.FLYING)
                bus.drain()
                for j in others:
                    nb = bus.estimates[j]
                    if nb.seq != seq[j]:
                        seq[j] = nb.seq
                        if j in last_estimate and now > WARM_UP_S and report is None:
                            gap[j] = max(gap[j], now - last_estimate[j])
                        last_estimate[j] = now
                if report is None and time.time() >= snapshot_at:
                    report = {"deaf": {j: [what for what, ok in (
                        ("token", j in bus.alive), ("status", now - last_status.get(j, -99.0) < 2.5),
                        ("estimate", now - last_estimate.get(j, -99.0) < 1.0)) if not ok] for j in others},
                        "gap_s": gap, "copies": bus.copies}
                k += 1
                await asyncio.sleep(max(0.0, t0 + k * 0.01 - time.monotonic()))
        finally:
            bus.close()
        return report

    out.write_text(json.dumps(asyncio.run(run())))
    os._exit(0)  # (a session's close under loss may wait for peers that are gone)


def one_run(layout: str, n: int, duration_s: float, delay_ms: float, workdir: Path) -> dict:
    """Inside the namespace: the relay and the peers; what each heard."""
    from tests.netem import DelayRelay

    routes = {RELAY_BASE + i: ZENOH_BASE + i for i in range(1, n + 1)}
    snapshot_at = time.time() + duration_s
    outs = {i: workdir / f"peer-{i}.json" for i in range(1, n + 1)}
    with DelayRelay(routes, delay_ms / 1000.0):
        procs = [subprocess.Popen([sys.executable, __file__, "--peer", str(i), str(n), layout, str(snapshot_at), str(outs[i])],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for i in range(1, n + 1)]
        for p in procs:
            try:
                p.wait(timeout=duration_s + 60.0)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    return {i: json.loads(f.read_text()) if f.exists() else None for i, f in outs.items()}


def summary(reports: dict) -> dict:
    deaf = sorted((int(j), i, what) for i, r in reports.items() if r for j, w in r["deaf"].items() for what in w)
    gaps = [g for r in reports.values() if r for g in r["gap_s"].values()]
    return {"peers_missing": [i for i, r in reports.items() if r is None], "deaf (from, at, what)": deaf,
            "worst_gap_s": round(max(gaps), 3) if gaps else None, "gaps_over_0.2_s": None if not gaps else sum(g > 0.2 for g in gaps),
            "copies": sorted({r["copies"] for r in reports.values() if r})}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--layouts", default="tcp+udp,quic,quic-with-copies")
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--peers", type=int, default=6)
    ap.add_argument("--duration-s", type=float, default=20.0)
    ap.add_argument("--drop", type=float, default=0.2)
    ap.add_argument("--delay-ms", type=float, default=20.0)
    ap.add_argument("--inside", nargs=2, metavar=("LAYOUT", "WORKDIR"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.inside:
        print(json.dumps(one_run(a.inside[0], a.peers, a.duration_s, a.delay_ms, Path(a.inside[1]))))
        return
    from tests.netem import NetNamespace

    problem = NetNamespace.problem()
    if problem:
        raise SystemExit(f"bench_zenoh_loss: {problem}")
    n = a.peers
    for layout in a.layouts.split(","):
        if layout not in LAYOUTS:
            raise SystemExit(f"bench_zenoh_loss: no layout {layout!r} (one of {', '.join(LAYOUTS)})")
        deaf_runs, worst = 0, 0.0
        for run in range(a.runs):
            with NetNamespace(f"triswarm-bench-loss-{os.getpid()}") as ns, tempfile.TemporaryDirectory() as tmp:
                for protocol in ("udp", "tcp"):
                    for match in (["--dports", f"{ZENOH_BASE + 1}:{ZENOH_BASE + n}"], ["--sports", f"{RELAY_BASE + 1}:{RELAY_BASE + n}"]):
                        ns.iptables("-A", "OUTPUT", "-p", protocol, "-m", "multiport", *match, "-m", "statistic",
                                    "--mode", "random", "--probability", str(a.drop), "-j", "DROP")
                done = subprocess.run(ns.exec_prefix() + [sys.executable, __file__, "--inside", layout, tmp, "--peers", str(n),
                                                          "--duration-s", str(a.duration_s), "--delay-ms", str(a.delay_ms)],
                                      capture_output=True, text=True, timeout=a.duration_s + 180.0)
            if done.returncode != 0:
                raise SystemExit(f"bench_zenoh_loss: run failed: {done.stderr[-2000:]}")
            s = summary({int(i): r for i, r in json.loads(done.stdout.strip().splitlines()[-1]).items()})
            deaf_runs += bool(s["deaf (from, at, what)"] or s["peers_missing"])
            worst = max(worst, s["worst_gap_s"] or 0.0)
            print(f"{layout:17s} run {run + 1}: {json.dumps(s)}", flush=True)
        print(f"{layout:17s} {n} peers, {a.drop:.0%} loss, {a.delay_ms:g} ms each way: {deaf_runs} of {a.runs} runs deaf, "
              f"worst estimate gap {worst:.3f} s", flush=True)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--peer":
        peer(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], float(sys.argv[5]), Path(sys.argv[6]))
    else:
        main()
