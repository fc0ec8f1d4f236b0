"""Cut UDP under a flowing estimate stream (run inside a network namespace of the test's, as root:
it adds the iptables rule itself). Agent 1 publishes through the companion's ``Bus``; an independent
Zenoh session, agent 2's peer, records the sequence number of every estimate it gets. Writes JSON:

    python tests/udp_cut.py OUT.json PORT_BASE

Everything is counted, nothing timed: ``before`` estimates are published with UDP up (the stream
must be flowing on it), then UDP is dropped and ``after`` more are published into the dead UDP link
(its lease, a minute here, outlasts the test); the listener is then given up to 10 s to take the
last reliable copy.
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from triswarm.companion.bus import COPY_EVERY, Bus  # noqa: E402
from triswarm.companion.zenoh_session import close_session, default_config  # noqa: E402
from triswarm.protocol.codec import AgentStatus, decode_header, estimate_key  # noqa: E402

PLAN, RATE_HZ, BEFORE, AFTER = 0x5EED, 200.0, 200, 400
LEASE_S = 60
TCP_AND_UDP = ("tcp", "udp")  # the layout with reliable copies (``copies_backup``)


def unhurried(cfg):
    """The companions' settings but a lease no stall of a busy machine outlasts: a starved process
    whose TCP link expired would lose the copies in flight, which is the machine, not the copies."""
    cfg.insert_json5("transport/link/tx/lease", str(LEASE_S * 1000))
    return cfg


def udp_packets() -> int:
    """UDP packets this namespace has sent (the counting rule's, the chain's first)."""
    out = subprocess.run(["iptables", "-w", "-L", "OUTPUT", "-v", "-x", "-n"], capture_output=True, text=True,
                         check=True).stdout
    return int(out.splitlines()[2].split()[0])


async def main(out: Path, base: int) -> tuple:
    swarm = f"cut-{uuid.uuid4().hex[:8]}"
    subprocess.run(["iptables", "-w", "-A", "OUTPUT", "-p", "udp"], check=True)  # counts every UDP packet
    got: list[int] = []
    lock = threading.Lock()

    def take(sample) -> None:
        seq = decode_header(sample.payload.to_bytes())[3]
        with lock:
            got.append(seq)

    listener = zenoh.open(unhurried(default_config(2, 2, base, protocols=TCP_AND_UDP)))
    sub = listener.declare_subscriber(estimate_key(swarm, 1), take)
    bus = Bus(swarm, 2)
    bus.open(unhurried(default_config(1, 2, base, protocols=TCP_AND_UDP)), asyncio.get_running_loop())
    bus.join(1, PLAN, frozenset())
    try:
        xi = np.zeros(12)
        for _ in range(100):  # both links up: a status comes reliably once the session is there
            bus.publish_estimate(1, xi, 0.0, AgentStatus.FLYING)
            await asyncio.sleep(0.05)
            with lock:
                if got:
                    break
        for _ in range(BEFORE):
            bus.publish_estimate(1, xi, 0.0, AgentStatus.FLYING)
            await asyncio.sleep(1.0 / RATE_HZ)
        await asyncio.sleep(0.5)
        udp_before = udp_packets()
        cut_after_seq = bus.members[1].seq
        # (dropped on the way in: a sender dropping on its way out would hear of it, EPERM, and close the link)
        subprocess.run(["iptables", "-w", "-A", "INPUT", "-p", "udp", "-j", "DROP"], check=True)
        for _ in range(AFTER):
            bus.publish_estimate(1, xi, 0.0, AgentStatus.FLYING)
            await asyncio.sleep(1.0 / RATE_HZ)
        last_seq = bus.members[1].seq
        last_copy = last_seq - last_seq % COPY_EVERY  # (TCP keeps their order: once it is in, all of them are)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            with lock:
                if got and max(got) >= last_copy:
                    break
            await asyncio.sleep(0.05)
        with lock:
            received = sorted(set(got))
        after = [s for s in received if s > cut_after_seq]
        out.write_text(json.dumps({
            "udp_packets_before_cut": udp_before, "cut_after_seq": cut_after_seq, "last_seq": last_seq,
            "received_before_cut": sum(1 for s in received if s <= cut_after_seq), "received_after_cut": len(after),
            "missing_after_cut": [s for s in range(cut_after_seq + 1, last_seq + 1) if s not in set(after)],
        }))
    except BaseException:
        sub.undeclare()
        close_session(listener)
        bus.close()
        raise
    # Measured, done: the sessions are left open to the process's end (closing them, or dropping
    # them, takes about 9 s after the cut, UDP restored or not: the test's time, not what it judges)
    return bus, listener, sub


if __name__ == "__main__":
    kept = asyncio.run(main(Path(sys.argv[1]), int(sys.argv[2])))
    os._exit(0)
