"""Benchmarks of `triswarm sitl up` (make bench):

* the largest N that one SITL process keeps in real time (physics 1 kHz, every companion link
  streaming its defaults, ATTITUDE and LOCAL_POSITION_NED at 100 Hz), each vehicle's streams
  received by a separate receiver process;
* the speedup it reaches for N = 6 when asked to run as fast as it can.

"Keeps real time" means: simulated time advanced at >= 0.995 x wall time, the scheduler never fell
more than 50 ms behind (a sixth of the 0.3 s actuator failsafe timeout), and every vehicle's ATTITUDE
and LOCAL_POSITION_NED arrived at >= 98 Hz.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ATTITUDE, LPOS = 30, 32


def receiver(manifest: dict, seconds: float, out: "mp.Queue") -> None:
    """Say hello on every companion link, then count MAVLink 2 frames by message id per vehicle."""
    socks = {}
    for v in manifest["vehicles"]:
        link = v["links"]["companion"]
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        s.connect((link["host"], link["port"]))
        s.setblocking(False)
        socks[s] = v["sysid"]
    from triswarm.protocol.mavlink import mavlink, new_codec

    codec = new_codec(255, 190)
    hello = codec.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0).pack(codec)
    counts = {sid: {ATTITUDE: 0, LPOS: 0} for sid in socks.values()}
    t_start = time.monotonic()
    next_hello = 0.0
    counting_from = t_start + 1.0  # let the streams settle
    while True:
        now = time.monotonic()
        if now - t_start > seconds + 1.0:
            break
        if now >= next_hello:
            for s in socks:
                try:
                    s.send(hello)
                except OSError:
                    pass
            next_hello = now + 1.0
        ready, _, _ = select.select(list(socks), [], [], 0.05)
        for s in ready:
            while True:
                try:
                    data = s.recv(65535)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    break
                if time.monotonic() < counting_from:
                    continue
                k = 0
                while k + 12 <= len(data) and data[k] == 0xFD:
                    plen = data[k + 1]
                    msgid = data[k + 7] | (data[k + 8] << 8) | (data[k + 9] << 16)
                    if msgid in (ATTITUDE, LPOS):
                        counts[socks[s]][msgid] += 1
                    k += 12 + plen + (13 if data[k + 2] & 1 else 0)
    span = time.monotonic() - counting_from
    for s in socks:
        s.close()
    out.put({sid: {m: c / span for m, c in cs.items()} for sid, cs in counts.items()})


def run_sitl(n: int, seconds: float, speedup: float = 1.0) -> tuple[dict, dict]:
    with tempfile.TemporaryDirectory() as tmp:
        manifest_path, stats_path = Path(tmp) / "m.json", Path(tmp) / "s.json"
        cmd = [sys.executable, "-m", "triswarm.gcs.cli", "sitl", "up", "-n", str(n), "--manifest", str(manifest_path),
               "--base-port", "0", "--stats", str(stats_path), "--quiet", "--speedup", str(speedup)]
        proc = subprocess.Popen(cmd)
        try:
            deadline = time.monotonic() + 60
            while not manifest_path.exists():
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("sitl did not start")
                time.sleep(0.05)
            manifest = json.loads(manifest_path.read_text())
            q: mp.Queue = mp.Queue()
            rx = mp.Process(target=receiver, args=(manifest, seconds, q))
            rx.start()
            rates = q.get(timeout=seconds + 30)
            rx.join(timeout=10)
        finally:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=30)
        return json.loads(stats_path.read_text()), rates


def keeps_real_time(n: int, seconds: float) -> tuple[bool, str]:
    stats, rates = run_sitl(n, seconds)
    worst = min(min(r.values()) for r in rates.values())
    ok = stats["speedup_achieved"] >= 0.995 and stats["max_lag_s"] <= 0.05 and worst >= 98.0
    return ok, (f"N = {n:4d}: sim/wall {stats['speedup_achieved']:.3f}, max lag {stats['max_lag_s'] * 1000:5.1f} ms, "
                f"slowest vehicle's ATTITUDE/LOCAL_POSITION_NED {worst:6.1f} Hz -> {'real time' if ok else 'falls behind'}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--duration-s", type=float, default=8.0, help="wall seconds measured per run")
    ap.add_argument("--sizes", default="25,50,75,100,125,150,200", help="N values tried, increasing")
    args = ap.parse_args()
    print(f"sitl: {os.cpu_count()} cpus; one SITL process plus one receiver process")
    largest = 0
    for n in [int(x) for x in args.sizes.split(",")]:
        ok, line = keeps_real_time(n, args.duration_s)
        print("  " + line, flush=True)
        if not ok:
            break
        largest = n
    print(f"largest N kept in real time: {largest}")
    stats, rates = run_sitl(6, args.duration_s, speedup=1000.0)
    per_vehicle = min(min(r.values()) for r in rates.values())
    print(f"N = 6 as fast as it runs: {stats['speedup_achieved']:.1f} x real time "
          f"(ATTITUDE received at {per_vehicle:.0f} per wall second per vehicle)")


if __name__ == "__main__":
    main()
