"""The Zenoh side of a companion: its estimate out, its neighbours' in, liveliness and status.

Transport: every session has a TCP and a UDP link to each peer (``transport/unicast/max_links`` 2).
Estimates are published best effort (express, dropped under congestion) and so ride UDP: a lost
estimate is replaced by the next one 5 ms later, and nothing waits for a retransmission. In
lockstep (``reliable_estimates``) every estimate is awaited, so they are published reliably (TCP).
Declarations, liveliness, status and health are reliable and ride TCP.

Zenoh callbacks only hand samples to the loop: an estimate subscriber's callback runs on the Zenoh
thread, tags the payload with the agent whose key it came on and appends it to an inbox (a deque,
the newest 256 kept); while the loop waits for its neighbours it also rings a doorbell (a local
datagram socket pair the asyncio loop watches), so an awaited estimate wakes the loop the moment
it arrives and the others cost no wake-up at all. An estimate of an agent of the same process is
delivered in the publisher's call, on the loop's own thread: that one is taken at the loop's next
turn, with no doorbell. Decoding, validation and counting all happen in
the loop. Liveliness and status change rarely: ring channels the loop drains at every tick.
"""

from __future__ import annotations

import asyncio
import functools
import json
import math
import os
import socket
import threading
import time
from collections.abc import Callable
from collections import Counter, deque
from dataclasses import dataclass, field

import zenoh

from triswarm.protocol.codec import (AgentStatus, CodecError, Estimate, agent_of_key, alive_key, decode_header,
                                     decode_xi, encode_estimate, estimate_key, health_key, status_key)

DEFAULT_ZENOH_BASE_PORT = 17447
INBOX_SIZE = 256  # estimates handed over and not yet read (the newest kept)
ONE_WORKER_RUNTIME = ("(app: (worker_threads: 1), acc: (handover: app), tx: (handover: app), rx: (handover: app), "
                      "net: (handover: app))")
"""One Zenoh worker thread for everything (accept, rx, tx, network): at a few hundred samples per
second, a multi-threaded runtime only spends the CPU on waking its own threads."""


def open_session(config: zenoh.Config) -> zenoh.Session:
    """A Zenoh session of the companion's. Zenoh reads ZENOH_RUNTIME when a process opens its first
    session: unless the deployment set its own, the companion's is ``ONE_WORKER_RUNTIME``."""
    os.environ.setdefault("ZENOH_RUNTIME", ONE_WORKER_RUNTIME)
    return zenoh.open(config)


def default_config(agents: int | frozenset[int], n_agents: int, base_port: int = DEFAULT_ZENOH_BASE_PORT,
                   host: str = "127.0.0.1") -> zenoh.Config:
    """Peers on one machine, no router, no multicast: agent i listens on TCP and UDP port
    base + i and connects to every other agent's. A process of several agents listens on each of
    theirs and connects to the others'."""
    mine = frozenset({agents}) if isinstance(agents, int) else agents
    listen = [f"{proto}/{host}:{base_port + i}" for i in sorted(mine) for proto in ("tcp", "udp")]
    connect = [f"{proto}/{host}:{base_port + j}" for j in range(1, n_agents + 1) if j not in mine
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
    """The newest valid estimate from one agent."""

    __slots__ = ("seq", "stamp_s", "t_plan_s", "status", "received_at", "xi")

    def __init__(self) -> None:
        self.seq = -1
        self.stamp_s = -math.inf      # when it was published (the sender's wall clock) [s]
        self.t_plan_s = -math.inf     # the plan time it refers to [s]
        self.status = AgentStatus.IDLE
        self.received_at = -math.inf  # when this agent took it in [s]
        self.xi = None                # (12,) x_r order

    @property
    def heard(self) -> bool:
        return self.xi is not None


@functools.lru_cache(maxsize=1024)
def _parse_status(key: str, data: bytes) -> tuple[int, AgentStatus, object] | None:
    """(agent, status, plan) of a status sample, None if it is not a valid one for its key. Kept
    for the recent samples: every agent of a process hears every status, and parses it once."""
    try:
        msg = json.loads(data)
        agent, status = int(msg["agent"]), AgentStatus[msg["status"]]
    except (ValueError, KeyError, TypeError):
        return None
    if agent_of_key(key) != agent:
        return None
    return agent, status, msg.get("plan")


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
    on_estimate: Callable[[], None] | None = None
    """Called (in the loop) after new neighbour estimates were taken in."""
    changes: int = 0
    """Counts the changes of ``alive`` and ``statuses`` (a reader caches what it derives from them)."""
    reliable: bool = False
    """Publish estimates reliably (lockstep: a lost one would stall the swarm's clock)."""
    previous_plan_id: int | None = None
    """After a plan change in flight, the plan before it: its estimates still count (neighbours
    switch within a tick of each other, and their estimates stay continuous through it)."""

    def switch_plan(self, plan_id: int) -> None:
        self.previous_plan_id, self.plan_id = self.plan_id, plan_id

    def open(self, config: zenoh.Config | zenoh.Session, loop: asyncio.AbstractEventLoop) -> None:
        """Open a session with ``config``, or declare this agent's keys on a session of the process
        (several agents in one process share it; its owner closes it)."""
        self.loop = loop
        self._inbox: deque[bytes] = deque(maxlen=INBOX_SIZE)
        self._doorbell, self._bell = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        for sock in (self._doorbell, self._bell):
            sock.setblocking(False)
        self.waiting = False
        """Set by the loop while it waits for estimates: the callbacks then ring the doorbell."""
        self._loop_thread = threading.get_ident()
        self._called = False
        self._own_session = not isinstance(config, zenoh.Session)
        self.session = open_session(config) if self._own_session else config
        s = self.session
        self._declare_estimate_publisher()
        self._pub_status = s.declare_publisher(status_key(self.swarm, self.agent))
        self._pub_health = s.declare_publisher(health_key(self.swarm, self.agent))
        self._token = s.liveliness().declare_token(alive_key(self.swarm, self.agent))
        for j in self.listen_to:
            self.neighbours[j] = Neighbour()
        self._estimate_subs = [s.declare_subscriber(estimate_key(self.swarm, j),
                                                    zenoh.handlers.Callback(self._handover(j), indirect=False))
                               for j in sorted(self.listen_to)]
        self._status_sub = s.declare_subscriber(status_key(self.swarm, "*"), zenoh.handlers.RingChannel(256))
        self._alive_sub = s.liveliness().declare_subscriber(alive_key(self.swarm, "*"), zenoh.handlers.FifoChannel(1024),
                                                            history=True)
        self._subs = [*self._estimate_subs, self._status_sub, self._alive_sub]
        self.alive.add(self.agent)
        self.seq = 0
        loop.add_reader(self._doorbell.fileno(), self._answer_door)

    def _declare_estimate_publisher(self) -> None:
        reliable = self.reliable
        self._pub_estimate = self.session.declare_publisher(
            estimate_key(self.swarm, self.agent), express=True,
            reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT,
            congestion_control=zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP)

    def reliable_estimates(self) -> None:
        """From now on publish estimates reliably."""
        if self.reliable:
            return
        self.reliable = True
        if "session" in self.__dict__:
            self._pub_estimate.undeclare()
            self._declare_estimate_publisher()

    def _handover(self, agent: int) -> Callable:
        """The subscriber callback for agent j's key (runs on a Zenoh thread): tag, hand over,
        and ring if the loop is waiting. (Appending before looking at ``waiting``, while the loop
        sets ``waiting`` before it looks at the inbox, loses no wake-up.)"""
        tag, append, ring = bytes([agent]), self._inbox.append, self._bell.send

        def handover(sample) -> None:
            append(tag + sample.payload.to_bytes())
            if self.waiting:
                if threading.get_ident() == self._loop_thread:  # (an agent of this process published)
                    if not self._called:
                        self._called = True
                        self.loop.call_soon(self._take_now)
                    return
                try:
                    ring(b"!")
                except OSError:  # the doorbell's buffer is full: the loop is awake anyway
                    pass

        return handover

    def _take_now(self) -> None:
        self._called = False
        self.take_estimates()

    def _answer_door(self) -> None:
        try:
            while self._doorbell.recv(16):
                pass
        except BlockingIOError:
            pass
        self.take_estimates()

    def close(self) -> None:
        """Undeclare everything and close the session (again: nothing)."""
        session = self.__dict__.pop("session", None)
        if session is None:
            return
        for sub in self._subs:
            sub.undeclare()
        self._token.undeclare()
        for pub in (self._pub_estimate, self._pub_status, self._pub_health):
            pub.undeclare()
        if self._own_session:
            session.close()
        try:
            self.loop.remove_reader(self._doorbell.fileno())
        except (RuntimeError, ValueError):
            pass
        self._doorbell.close()
        self._bell.close()

    def counts(self) -> dict[str, int]:
        """What the bus took in and what it dropped, by reason."""
        return dict(self.counters)

    # -- the loop ----------------------------------------------------------------------------

    def take_estimates(self) -> None:
        """Everything the Zenoh callbacks handed over: keep each agent's newest valid estimate."""
        if not self._inbox:
            return
        newest: dict[int, tuple] = {}
        pop = self._inbox.popleft
        while self._inbox:
            data = pop()
            checked = self._check(data[0], data[1:])
            if checked is None:
                continue
            earlier = newest.get(checked[0])
            if earlier is None or _newer(checked[6], checked[4], earlier[6], earlier[4]):
                newest[checked[0]] = checked
            else:
                self.counters["drop_old"] += 1
        if newest:
            now = time.time()
            for checked in newest.values():
                self._take(checked, now)
            if self.on_estimate is not None:
                self.on_estimate()

    def drain(self) -> None:
        """Take in liveliness and status changes (and any estimate not yet read)."""
        self.take_estimates()
        while (sample := self._alive_sub.try_recv()) is not None:
            self._alive(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
        while (sample := self._status_sub.try_recv()) is not None:
            self._status(str(sample.key_expr), sample.payload.to_bytes())

    def ready(self, agents: list[int], t_plan_s: float, tolerance_s: float) -> bool:
        """Whether every agent in ``agents`` has an estimate for plan time >= t_plan_s - tolerance_s."""
        nbs = self.neighbours
        return all(nbs[j].t_plan_s >= t_plan_s - tolerance_s for j in agents)

    def _check(self, key_agent: int, data: bytes):
        """Validate one estimate's header; count and drop what is not for us or not newer."""
        try:
            status, agent, plan, seq, stamp, t_plan = decode_header(data)
        except CodecError:
            self.counters["drop_undecodable"] += 1
            return None
        nb = self.neighbours.get(agent)
        if nb is None or key_agent != agent:
            self.counters["drop_unknown_agent"] += 1
            return None
        if plan != self.plan_id and plan != self.previous_plan_id:
            self.counters["drop_other_plan"] += 1
            return None
        if not _newer(t_plan, seq, nb.t_plan_s, nb.seq):
            self.counters["drop_old"] += 1
            return None
        return agent, nb, data, status, seq, stamp, t_plan

    def _take(self, checked, t_rx: float) -> None:
        """Keep the newest valid sample of a neighbour (its xi checked here, once)."""
        _, nb, data, status, seq, stamp, t_plan = checked
        try:
            xi = decode_xi(data)
        except CodecError:
            self.counters["drop_undecodable"] += 1
            return
        nb.seq, nb.stamp_s, nb.t_plan_s, nb.status, nb.received_at, nb.xi = seq, stamp, t_plan, status, t_rx, xi
        self.counters["estimates"] += 1

    def _status(self, key: str, data: bytes) -> None:
        parsed = _parse_status(key, data)
        if parsed is None or not 1 <= parsed[0] <= self.n_agents:
            self.counters["drop_bad_status"] += 1
            return
        agent, status, plan = parsed
        if plan in (self.plan_id, self.previous_plan_id) and self.statuses.get(agent) != status:
            self.statuses[agent] = status
            self.changes += 1

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
        self.changes += 1

    # -- outgoing ----------------------------------------------------------------------------

    def publish_estimate(self, xi, t_plan_s: float, status: AgentStatus) -> None:
        self.seq += 1
        e = Estimate(self.agent, self.plan_id, self.seq, time.time(), t_plan_s, status, xi)
        self._pub_estimate.put(encode_estimate(e))

    def publish_status(self, status: AgentStatus, reason: str = "", since_s: float | None = None) -> None:
        """The status, why, and since when (Unix time [s]). Sent at every change and once a second,
        whole each time: a put lost on the way costs a second, not the reason or the time."""
        now = time.time()
        self._pub_status.put(json.dumps({"agent": self.agent, "plan": self.plan_id, "status": status.name,
                                         "reason": reason, "since": now if since_s is None else since_s,
                                         "t": now}).encode())

    def publish_health(self, health: dict) -> None:
        self._pub_health.put(json.dumps(health).encode())


def _newer(t_plan_s: float, seq: int, than_t_plan_s: float, than_seq: int) -> bool:
    """Order of one agent's estimates: by the instant they refer to, then by sequence number. (A
    restarted companion counts its sequence from 1 again; its plan time goes on.)"""
    return t_plan_s > than_t_plan_s or (t_plan_s == than_t_plan_s and seq > than_seq)
