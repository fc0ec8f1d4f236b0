"""The floor of a companion (make bench): what one drone's process costs before any control.

`triswarm sitl up -n N` plus N skeleton companions. A skeleton is the companion's own I/O and
nothing else: the flight-controller link (``companion.links.MavLink``) with the telemetry at the
control rate, and on every sample an estimate published on the Zenoh bus (``companion.bus.Bus``,
the same peers on loopback, hearing three neighbours with the same doorbell) and an actuator command
packed and sent back. No observer, references, protocol, RFL, health or routing. Its CPU is the
least a Python companion of this design can cost, and N times it plus the SITL is what a swarm of N
needs of this machine before any control runs.

    python tests/bench/bench_floor.py [--sizes 6,12,24] [--duration-s 20] [--rate-hz 200] [--without-zenoh | --router]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

NEIGHBOURS = 3
ROUTER = Path(__file__).resolve().parents[1] / "zenoh_router.py"
WARM_UP_S = 8.0  # from the skeletons' start to the measurement (imports, sessions, streams)


def skeleton(agent: int, n: int, fc_url: str, zenoh_base_port: int, rate_hz: float, zenoh: bool,
             router_port: int | None) -> None:
    from triswarm.companion.bus import Bus
    from triswarm.companion.zenoh_session import default_config, peer_config
    from triswarm.companion.links import MavLink
    from triswarm.protocol.codec import AgentStatus
    from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink

    async def main() -> None:
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        link = MavLink("fc", fc_url, agent, COMP_ONBOARD)
        listen_to = frozenset((agent - 1 - k) % n + 1 for k in range(1, min(NEIGHBOURS, n - 1) + 1))
        bus = Bus("floor", n)
        xi = np.zeros(12)
        controls = [0.3, 0.3, 0.3, 0.0, 0.0, 0.0, 0.0, 0.0]
        samples = []

        def on_fc(link, msgs, t_rx) -> None:
            for m in msgs:
                if m.get_type() == "LOCAL_POSITION_NED":
                    samples.append(t_rx)
                    if zenoh:
                        bus.take_estimates()
                        bus.publish_estimate(agent, xi, m.time_boot_ms / 1000.0, AgentStatus.FLYING)
                    link.send(mavlink.MAVLink_set_actuator_control_target_message(m.time_boot_ms * 1000, 0, agent, 1,
                                                                                  controls))

        link.open(loop, on_fc)
        if zenoh:
            config = (default_config(agent, n, zenoh_base_port) if router_port is None else
                      peer_config([], [f"tcp/127.0.0.1:{router_port}", f"udp/127.0.0.1:{router_port}"], mode="client"))
            bus.open(config, loop)
            bus.join(agent, 1, listen_to)
        interval_us = 1e6 / rate_hz
        for msg_id in (mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED):
            link.send(mavlink.MAVLink_command_long_message(agent, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                           msg_id, interval_us, 0, 0, 0, 0, 0))
        try:
            await stop.wait()
        finally:
            link.close()
            if zenoh:
                bus.close()
        recent = [t for t in samples if t > time.time() - 5.0]
        print(json.dumps({"agent": agent, "sample_rate_hz": len(recent) / 5.0,
                          "estimates": bus.counters.get("estimates", 0)}), flush=True)

    asyncio.run(main())


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run(n: int, seconds: float, rate_hz: float, zenoh: bool = True, router: bool = False) -> dict:
    from triswarm.gcs.stack import Stack, free_ports, stop_in_turn

    with tempfile.TemporaryDirectory() as tmp, Stack(None, Path(tmp) / "run", n, companions=False) as stack:
        services = [stack.procs["sitl"]]
        skeletons: list[subprocess.Popen] = []
        try:
            router_port = None
            if router:
                router_port = free_ports(1)[0]
                config = Path(tmp) / "router.json5"
                config.write_text(json.dumps({"mode": "router", "scouting": {"multicast": {"enabled": False}},
                                              "listen": {"endpoints": [f"tcp/127.0.0.1:{router_port}",
                                                                       f"udp/127.0.0.1:{router_port}"]},
                                              "transport": {"unicast": {"max_links": 2}}}))
                services.append(subprocess.Popen([sys.executable, str(ROUTER), str(config)], stdout=subprocess.DEVNULL))
            skeletons = [subprocess.Popen([sys.executable, __file__, "--skeleton", str(i), "--n", str(n),
                                           "--fc", v["links"]["companion"]["pymavlink"],
                                           "--zenoh-base-port", str(stack.zenoh_base), "--rate-hz", str(rate_hz),
                                           *([] if zenoh else ["--without-zenoh"]),
                                           *([] if router_port is None else ["--router-port", str(router_port)])],
                                          stdout=subprocess.PIPE, text=True)
                         for i, v in enumerate(stack.manifest["vehicles"], start=1)]
            procs = services + skeletons
            time.sleep(WARM_UP_S)
            if any(p.poll() is not None for p in procs):
                raise RuntimeError("a process exited early")
            before = [cpu_seconds(p.pid) for p in procs]
            t0 = time.monotonic()
            time.sleep(seconds)
            wall = time.monotonic() - t0
            share = [(cpu_seconds(p.pid) - b) / wall for p, b in zip(procs, before)]
        finally:
            stop_in_turn([skeletons, services[1:]])  # (the SITL stops with the stack)
    reports = [json.loads(p.stdout.read().strip().splitlines()[-1]) for p in skeletons]
    ours = share[len(services):]
    return {"sitl": share[0], "router": share[1] if router else 0.0,
            "skeleton_mean": float(np.mean(ours)), "skeleton_max": float(np.max(ours)),
            "slowest_sample_rate_hz": min(r["sample_rate_hz"] for r in reports),
            "fewest_estimates": min(r["estimates"] for r in reports)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="6,12,24", help="swarm sizes measured")
    ap.add_argument("--duration-s", type=float, default=20.0, help="seconds measured per size")
    ap.add_argument("--rate-hz", type=float, default=200.0, help="telemetry and command rate")
    ap.add_argument("--without-zenoh", action="store_true", help="skeletons without the Zenoh bus (MAVLink alone)")
    ap.add_argument("--router", action="store_true", help="skeletons as Zenoh clients of one router (tests/zenoh_router.py)")
    ap.add_argument("--router-port", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--skeleton", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--fc", help=argparse.SUPPRESS)
    ap.add_argument("--zenoh-base-port", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.skeleton is not None:
        skeleton(args.skeleton, args.n, args.fc, args.zenoh_base_port, args.rate_hz, not args.without_zenoh,
                 args.router_port)
        return
    cores = os.cpu_count() or 1
    parts = "MAVLink link" + ("" if args.without_zenoh else ", Zenoh bus" + (" via a router" if args.router else ""))
    print(f"companion floor at {args.rate_hz:g} Hz (I/O only: {parts}, no control); {cores} cores")
    for n in [int(x) for x in args.sizes.split(",")]:
        r = run(n, args.duration_s, args.rate_hz, not args.without_zenoh, args.router)
        busy = n * r["skeleton_mean"] + r["sitl"] + r["router"]
        router = f", router {100 * r['router']:.0f} %" if args.router else ""
        line = (f"  N = {n:3d}: skeleton {100 * r['skeleton_mean']:.1f} % mean ({100 * r['skeleton_max']:.1f} % max) of a "
                f"core, sitl {100 * r['sitl']:.0f} %{router}: {busy:.2f} cores busy; ")
        if r["slowest_sample_rate_hz"] >= 0.95 * args.rate_hz:
            line += f"in real time, with no control yet ({r['fewest_estimates']} estimates taken by the slowest)"
        else:
            line += (f"NOT in real time even with no control: the slowest skeleton got "
                     f"{r['slowest_sample_rate_hz']:.0f} of {args.rate_hz:g} samples/s")
        print(line, flush=True)


if __name__ == "__main__":
    main()
