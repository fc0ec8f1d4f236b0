"""The Zenoh side of a companion: its estimate out, its neighbours' in, liveliness and status.

Transport: every session has a TCP and a UDP link to each peer (``transport/unicast/max_links`` 2).
Estimates are published best effort (express, dropped under congestion) and so ride UDP: a lost
estimate is replaced by the next one 5 ms later, and nothing waits for a retransmission.
Declarations, liveliness, status and health are reliable and ride TCP.

Samples are handed over without Python ever running on a Zenoh thread: every subscriber uses a
Zenoh ring channel (Rust side, the newest samples kept, older ones dropped), and the loop drains
the channels with ``try_recv`` at every tick. Decoding, validation and counting happen in the loop.
No callback, no cross-thread wake-up, no contention for the interpreter lock on the hot path.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import time
from collections import Counter
from dataclasses import dataclass, field

# One Zenoh worker thread for everything (accept, rx, tx, network): at a few hundred samples per
# second, a multi-threaded runtime only spends the CPU on waking its own threads. Read when the
# first session opens; a deployment can set its own ZENOH_RUNTIME.
os.environ.setdefault("ZENOH_RUNTIME", "(app: (worker_threads: 1), acc: (handover: app), tx: (handover: app), "
                                       "rx: (handover: app), net: (handover: app))")

import zenoh  # noqa: E402

from triswarm.protocol.codec import (AgentStatus, CodecError, Estimate, agent_of_key, alive_key, decode_header,
                                     decode_xi, encode_estimate, estimate_key, health_key, status_key)

DEFAULT_ZENOH_BASE_PORT = 17447


def default_config(agent: int, n_agents: int, base_port: int = DEFAULT_ZENOH_BASE_PORT,
                   host: str = "127.0.0.1") -> zenoh.Config:
    """Peers on one machine, no router, no multicast: agent i listens on TCP and UDP port
    base + i and connects to every other agent's."""
    listen = [f"tcp/{host}:{base_port + agent}", f"udp/{host}:{base_port + agent}"]
    connect = [f"{proto}/{host}:{base_port + j}" for j in range(1, n_agents + 1) if j != agent
               for proto in ("tcp", "udp")]
    return peer_config(listen, connect)


def peer_config(listen: list[str], connect: list[str], mode: str = "peer") -> zenoh.Config:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("listen/endpoints", json.dumps(listen))
    cfg.insert_json5("connect/endpoints", json.dumps(connect))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    tune(cfg)
    return cfg


def tune(cfg: zenoh.Config) -> zenoh.Config:
    """Settings triswarm needs whatever the deployment: two links per peer (reliable + best
    effort), and a lease short enough that a dead peer's liveliness goes within a second."""
    cfg.insert_json5("transport/unicast/max_links", "2")
    cfg.insert_json5("transport/link/tx/lease", "1000")
    cfg.insert_json5("transport/link/tx/keep_alive", "4")
    return cfg


class Neighbour:
    """The newest valid estimate from one agent, kept as received; xi is unpacked on first use."""

    __slots__ = ("seq", "stamp_s", "t_plan_s", "status", "received_at", "_payload", "_xi")

    def __init__(self) -> None:
        self.seq = -1
        self.stamp_s = -math.inf
        self.t_plan_s = -math.inf
        self.status = AgentStatus.IDLE
        self.received_at = -math.inf
        self._payload: bytes | None = None
        self._xi = None

    @property
    def heard(self) -> bool:
        return self._payload is not None

    @property
    def xi(self):
        return self._xi


@dataclass
class Bus:
    swarm: str
    agent: int
    plan_id: int
    listen_to: frozenset[int]
    """Agents whose estimates this agent may use: in-neighbours in some topology of the schedule."""
    n_agents: int
    counters: Counter = field(default_factory=Counter)
    neighbours: dict[int, Neighbour] = field(default_factory=dict)
    alive: set[int] = field(default_factory=set)
    statuses: dict[int, AgentStatus] = field(default_factory=dict)

    def open(self, config: zenoh.Config, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.session = zenoh.open(config)
        s = self.session
        self._pub_estimate = s.declare_publisher(estimate_key(self.swarm, self.agent), express=True,
                                                 reliability=zenoh.Reliability.BEST_EFFORT,
                                                 congestion_control=zenoh.CongestionControl.DROP)
        self._pub_status = s.declare_publisher(status_key(self.swarm, self.agent))
        self._pub_health = s.declare_publisher(health_key(self.swarm, self.agent))
        self._token = s.liveliness().declare_token(alive_key(self.swarm, self.agent))
        self._estimate_subs = [s.declare_subscriber(estimate_key(self.swarm, j), zenoh.handlers.RingChannel(64))
                               for j in sorted(self.listen_to)]
        self._status_sub = s.declare_subscriber(status_key(self.swarm, "*"), zenoh.handlers.RingChannel(256))
        self._alive_sub = s.liveliness().declare_subscriber(alive_key(self.swarm, "*"), zenoh.handlers.FifoChannel(1024),
                                                            history=True)
        self._subs = [*self._estimate_subs, self._status_sub, self._alive_sub]
        for j in self.listen_to:
            self.neighbours[j] = Neighbour()
        self.alive.add(self.agent)
        self.seq = 0

    def close(self) -> None:
        for sub in getattr(self, "_subs", []):
            sub.undeclare()
        if hasattr(self, "session"):
            self._token.undeclare()
            self.session.close()

    # -- the loop ----------------------------------------------------------------------------

    def drain(self) -> None:
        """Take in everything that arrived since the last call."""
        now = time.time()
        for sub in self._estimate_subs:
            newest = None
            while (sample := sub.try_recv()) is not None:
                checked = self._check(str(sample.key_expr), sample.payload.to_bytes())
                if checked is not None:
                    newest = checked
            if newest is not None:
                self._take(newest, now)
        while (sample := self._alive_sub.try_recv()) is not None:
            self._alive(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
        while (sample := self._status_sub.try_recv()) is not None:
            self._status(str(sample.key_expr), sample.payload.to_bytes())

    def _check(self, key: str, data: bytes):
        """Validate one sample's header; count and drop what is not for us or not newer."""
        try:
            status, agent, plan, seq, stamp, t_plan = decode_header(data)
        except CodecError:
            self.counters["drop_undecodable"] += 1
            return None
        nb = self.neighbours.get(agent)
        if nb is None or agent_of_key(key) != agent:
            self.counters["drop_unknown_agent"] += 1
            return None
        if plan != self.plan_id:
            self.counters["drop_other_plan"] += 1
            return None
        if seq <= nb.seq:
            self.counters["drop_old"] += 1
            return None
        return nb, data, status, seq, stamp, t_plan

    def _take(self, checked, t_rx: float) -> None:
        """Keep the newest valid sample of a neighbour (its xi checked here, once)."""
        nb, data, status, seq, stamp, t_plan = checked
        try:
            xi = decode_xi(data)
        except CodecError:
            self.counters["drop_undecodable"] += 1
            return
        nb.seq, nb.stamp_s, nb.t_plan_s, nb.status, nb.received_at = seq, stamp, t_plan, status, t_rx
        nb._payload, nb._xi = data, xi
        self.counters["estimates"] += 1

    def _status(self, key: str, data: bytes) -> None:
        try:
            msg = json.loads(data)
            agent, status = int(msg["agent"]), AgentStatus[msg["status"]]
            if agent_of_key(key) != agent or not 1 <= agent <= self.n_agents:
                raise ValueError
        except (ValueError, KeyError, TypeError):
            self.counters["drop_bad_status"] += 1
            return
        if msg.get("plan") == self.plan_id:
            self.statuses[agent] = status

    def _alive(self, key: str, present: bool) -> None:
        agent = agent_of_key(key)
        if agent is None or not 1 <= agent <= self.n_agents:
            self.counters["drop_bad_liveliness"] += 1
            return
        if present:
            self.alive.add(agent)
        elif agent != self.agent:
            self.alive.discard(agent)
            self.statuses.pop(agent, None)

    # -- outgoing ----------------------------------------------------------------------------

    def publish_estimate(self, xi, t_plan_s: float, status: AgentStatus) -> None:
        self.seq += 1
        e = Estimate(self.agent, self.plan_id, self.seq, time.time(), t_plan_s, status, xi)
        self._pub_estimate.put(encode_estimate(e))

    def publish_status(self, status: AgentStatus, reason: str = "") -> None:
        self._pub_status.put(json.dumps({"agent": self.agent, "plan": self.plan_id, "status": status.name,
                                         "reason": reason, "t": time.time()}).encode())

    def publish_health(self, health: dict) -> None:
        self._pub_health.put(json.dumps(health).encode())

    def wait_for(self, agents: list[int], t_plan_s: float, tolerance_s: float, timeout_s: float,
                 poll_s: float = 1e-4) -> None:
        """Poll (sleeping ``poll_s`` between polls, at most ``timeout_s`` in all) until every agent
        in ``agents`` has an estimate for plan time >= t_plan_s - tolerance_s. Blocks the loop for
        at most ``timeout_s``: it is the tick's own time, nothing else waits on the loop then."""
        deadline = time.monotonic() + timeout_s
        while True:
            self.drain()
            missing = [j for j in agents if (nb := self.neighbours.get(j)) is None or not nb.heard
                       or nb.t_plan_s < t_plan_s - tolerance_s]
            if not missing or time.monotonic() >= deadline:
                return
            time.sleep(poll_s)
