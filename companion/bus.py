"""The Zenoh side of a companion process: its agents' estimates out, their neighbours' in,
liveliness and status.

One ``Bus`` per process and swarm, on one Zenoh session, whatever the number of agents the process
flies (one on a drone). Each agent ``join``s it with its plan and the agents it listens to; the bus
declares the agent's keys (estimate, status, health, liveliness token) and subscribes to the
estimates of the agents it listens to that fly in other processes. The newest estimate of every
agent (``estimates``) is one table for the whole process: an agent of this process writes its own
there when it publishes, so its neighbours in the process read it with no network hop and no
decoding; estimates from other processes come through Zenoh, are validated, and land in the same
table. Each agent reads only its in-neighbours' entries, and only those of the plans it flies.

Transport: the estimates are published best effort (express, dropped under congestion): a lost
estimate is replaced by the next one a period later, and nothing waits for a retransmission.
Declarations, liveliness, status and health are reliable. Three link layouts serve
(``zenoh_session.copies_backup``):

- one TCP link to each peer (``zenoh_session.default_config``: peers on one machine): everything on it, no copies.
- a TCP and a UDP link to each peer (``transport/unicast/max_links`` 2; good networks, the client
  configuration): the estimates ride UDP, the rest TCP. Every ``COPY_EVERY``-th estimate also goes
  reliably, on TCP: a UDP path that dies while TCP lives (on a lossy network, Zenoh's UDP listener
  can stop taking a peer's datagrams for good, all its peers' at once) then costs a neighbour's
  estimates their latency, not the neighbour. The copies that arrive after the best-effort original
  are dropped as old (``drop_old``).
- one reliable UDP link to each peer (``udp/...?rel=1;mixed_rel=1``, QUIC: lossy networks,
  ``deploy/zenoh/companion-peer.json5``): the rest on its streams, the estimates as its datagrams,
  and no copies, which would share the link's congestion window with the estimates they back up.

In lockstep (``reliable_estimates``) every estimate is awaited, so they are published reliably and
no copy is sent.

Zenoh callbacks only hand samples to the loop: an estimate subscriber's callback runs on the Zenoh
thread, tags the payload with the agent whose key it came on and puts it in an inbox (the newest
256 kept, the older ones dropped and counted); while the loop waits for estimates it also rings a
doorbell (a local datagram socket pair the asyncio loop watches), so an awaited estimate wakes the
loop the moment it arrives and the others cost no wake-up at all. Decoding, validation and counting
happen in the loop. Statuses change rarely: an inbox of their own that the loop drains at every
tick; liveliness: a channel drained likewise.

What the bus drops, it counts (``counts``), by reason: ``drop_undecodable``, ``drop_unknown_agent``,
``drop_other_plan``, ``drop_old`` (estimates), ``drop_bad_status``, ``drop_bad_liveliness``, and
``drop_inbox_full`` / ``drop_status_inbox_full`` (more came between two reads than an inbox keeps);
``estimates`` and ``statuses`` count what it took.
"""

from __future__ import annotations

import asyncio
import functools
import json
import math
import socket
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from triswarm.protocol.codec import (AgentStatus, CodecError, Estimate, agent_of_key, alive_key, decode_header,
                                     decode_xi, encode_estimate, estimate_key, health_key, status_key)

from .zenoh_session import close_session, open_session

COPY_EVERY = 2  # every how many best-effort estimates (UDP) one also goes reliably (TCP)
STATUS_ALIVE_S = 3.0
"""An agent whose liveliness token never came is alive while its statuses (one a second at least)
come: until this long [s, wall] after the newest."""
INBOX_SIZE = 256  # estimates (or statuses) handed over and not yet read (the newest kept)
class Neighbour:
    """The newest valid estimate of one agent (of this process or another)."""

    __slots__ = ("seq", "stamp_s", "t_plan_s", "status", "plan_id", "received_at", "xi")

    def __init__(self) -> None:
        self.seq = -1
        self.stamp_s = -math.inf      # when it was published (the sender's wall clock) [s]
        self.t_plan_s = -math.inf     # the plan time it refers to [s]
        self.status = AgentStatus.IDLE
        self.plan_id = -1
        self.received_at = -math.inf  # when this process took it in [s]
        self.xi = None                # (12,) x_r order

    @property
    def heard(self) -> bool:
        return self.xi is not None


class _Inbox:
    """Samples handed from Zenoh's thread to the loop: the newest ``size`` kept; ``dropped`` counts
    the older ones pushed out."""

    def __init__(self, size: int = INBOX_SIZE) -> None:
        self.size = size
        self.items: deque = deque()
        self.dropped = 0
        self._lock = threading.Lock()

    def put(self, item) -> None:
        with self._lock:
            if len(self.items) >= self.size:
                self.items.popleft()
                self.dropped += 1
            self.items.append(item)

    def take(self) -> deque:
        """Everything waiting, oldest first."""
        with self._lock:
            items, self.items = self.items, deque()
        return items

    def __bool__(self) -> bool:
        return bool(self.items)


@functools.lru_cache(maxsize=1024)
def _parse_status(key: str, data: bytes) -> tuple[int, AgentStatus, object] | None:
    """(agent, status, plan) of a status sample, None if it is not a valid one for its key."""
    try:
        msg = json.loads(data)
        agent, status = int(msg["agent"]), AgentStatus[msg["status"]]
    except (ValueError, KeyError, TypeError, OverflowError, RecursionError):  # (Infinity; nesting too deep)
        return None
    if agent_of_key(key) != agent:
        return None
    return agent, status, msg.get("plan")


@dataclass
class _Member:
    """An agent of this process on the bus: its plans and its keys."""
    plan_id: int
    listen_to: frozenset[int]
    publisher: object
    status_publisher: object
    health_publisher: object
    token: object
    copy_publisher: object = None
    """The reliable copies' publisher (None in lockstep, where every estimate is reliable, and on a
    reliable UDP link)."""
    seq: int = 0
    last: bytes | None = None
    """The newest estimate published, as sent."""
    last_at: float = 0.0
    """When it was published [s, monotonic]."""
    previous_plan_id: int | None = None
    """After a plan change in flight, the plan before it: its estimates still count (neighbours
    switch within a tick of each other, and their estimates stay continuous through it)."""

    @property
    def plans(self) -> tuple[int, ...]:
        return (self.plan_id,) if self.previous_plan_id is None else (self.plan_id, self.previous_plan_id)


class Bus:
    """The process's agents on one swarm's key space (``open``, then ``join`` each agent)."""

    def __init__(self, swarm: str, n_agents: int, reliable: bool = False, copies: bool = True) -> None:
        self.swarm = swarm
        self.n_agents = n_agents
        """Agent numbers above this are not of the swarm (the largest plan of the process's agents)."""
        self.reliable = reliable
        """Publish estimates reliably (lockstep: a lost one would stall the swarm's clock)."""
        self.copies = copies
        """Back the best-effort estimates up with reliable copies (``copies_backup``)."""
        self.counters: Counter[str] = Counter()
        self.estimates: dict[int, Neighbour] = {}
        """The newest valid estimate of every agent of this process and of every agent one of them
        listens to."""
        self.alive: set[int] = set()
        """The agents whose liveliness token is there, and those whose token never came but whose
        statuses do (``STATUS_ALIVE_S``): Zenoh has been seen to lose a token's declaration for a
        whole flight while the agent flew and said so."""
        self._tokens: set[int] = set()
        self.token_at: dict[int, float] = {}
        """When [s, monotonic] each agent's liveliness token last came: a link to it was (re)opened,
        and what it sent while there was none is lost."""
        self._said_at: dict[int, float] = {}  # agents alive by their statuses: the newest's [s, monotonic]
        self._said_checked = 0.0
        self.statuses: dict[int, tuple[AgentStatus, object]] = {}
        """The newest status of each agent and the plan it said it flies."""
        self.changes = 0
        """Counts the changes of ``alive`` and ``statuses`` (a reader caches what it derives from them)."""
        self.members: dict[int, _Member] = {}
        self.on_estimates: Callable[[], None] | None = None
        """Called (in the loop) after estimates from other processes were taken in."""
        self.waiting = False
        """Set by the loop while an agent waits for estimates: the callbacks then ring the doorbell."""
        self._subscribed: dict[int, object] = {}
        self.session: zenoh.Session | None = None
        """Its session, from ``open`` until ``close``."""

    # -- session ------------------------------------------------------------------------------

    def open(self, config: zenoh.Config | zenoh.Session, loop: asyncio.AbstractEventLoop) -> None:
        """Open a session with ``config``, or use a session of the process (its owner closes it)."""
        self.loop = loop
        self._inbox = _Inbox()
        self._status_inbox = _Inbox()
        self._doorbell, self._bell = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        for sock in (self._doorbell, self._bell):
            sock.setblocking(False)
        self._own_session = not isinstance(config, zenoh.Session)
        self.session = open_session(config) if self._own_session else config
        s = self.session
        put_status = self._status_inbox.put
        self._status_sub = s.declare_subscriber(
            status_key(self.swarm, "*"),
            zenoh.handlers.Callback(lambda sample: put_status((str(sample.key_expr), sample.payload.to_bytes())),
                                    indirect=False))
        self._alive_sub = s.liveliness().declare_subscriber(alive_key(self.swarm, "*"), zenoh.handlers.FifoChannel(1024),
                                                            history=True)
        loop.add_reader(self._doorbell.fileno(), self._answer_door)

    def close(self) -> None:
        """Undeclare everything and close the session (again: nothing)."""
        session, self.session = self.session, None
        if session is None:
            return
        for agent in list(self.members):
            self.leave(agent)
        self._status_sub.undeclare()
        self._alive_sub.undeclare()
        if self._own_session:
            close_session(session)
        try:
            self.loop.remove_reader(self._doorbell.fileno())
        except (RuntimeError, ValueError):
            pass
        self._doorbell.close()
        self._bell.close()

    @property
    def is_open(self) -> bool:
        return self.session is not None

    # -- members ------------------------------------------------------------------------------

    def join(self, agent: int, plan_id: int, listen_to: frozenset[int]) -> None:
        """Declare agent ``agent`` of this process (its keys and liveliness), flying plan ``plan_id``
        and listening to the estimates of ``listen_to``."""
        if agent in self.members:
            self.leave(agent)
        s = self.session
        self.members[agent] = _Member(plan_id, frozenset(listen_to), self._estimate_publisher(agent),
                                      s.declare_publisher(status_key(self.swarm, agent)),
                                      s.declare_publisher(health_key(self.swarm, agent)),
                                      s.liveliness().declare_token(alive_key(self.swarm, agent)),
                                      None if self.reliable or not self.copies else self._estimate_publisher(agent, copies=True))
        self.estimates.setdefault(agent, Neighbour())
        for j in listen_to:
            self.estimates.setdefault(j, Neighbour())
        self.alive.add(agent)
        self._resubscribe()

    def leave(self, agent: int) -> None:
        member = self.members.pop(agent, None)
        if member is None:
            return
        for declared in (member.publisher, member.status_publisher, member.health_publisher, member.token,
                         member.copy_publisher):
            if declared is not None:
                declared.undeclare()
        self._resubscribe()

    def switch_plan(self, agent: int, plan_id: int) -> None:
        """Agent ``agent`` flies ``plan_id`` from now on; the plan before still counts."""
        m = self.members[agent]
        m.previous_plan_id, m.plan_id = m.plan_id, plan_id

    def plans_of(self, agent: int) -> tuple[int, ...]:
        return self.members[agent].plans

    def reliable_estimates(self) -> None:
        """From now on publish estimates reliably."""
        if self.reliable:
            return
        self.reliable = True
        for agent, m in self.members.items():
            m.publisher.undeclare()
            m.publisher = self._estimate_publisher(agent)
            if m.copy_publisher is not None:
                m.copy_publisher.undeclare()
                m.copy_publisher = None

    def _estimate_publisher(self, agent: int, copies: bool = False):
        """Agent ``agent``'s estimates: reliable in lockstep, else best effort; ``copies``: the
        reliable copies beside the best-effort ones, dropped rather than waited for when TCP's queue
        is full."""
        reliable, block = self.reliable or copies, self.reliable and not copies
        return self.session.declare_publisher(
            estimate_key(self.swarm, agent), express=True,
            reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT,
            congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP)

    def _resubscribe(self) -> None:
        """Subscribe to exactly the estimates of the agents some member listens to and that fly
        in other processes (a member's own key is never heard from outside: an impostor's estimates
        for it go nowhere)."""
        wanted = set().union(*(m.listen_to for m in self.members.values())) - set(self.members)
        for j in set(self._subscribed) - wanted:
            self._subscribed.pop(j).undeclare()
        for j in sorted(wanted - set(self._subscribed)):
            self._subscribed[j] = self.session.declare_subscriber(
                estimate_key(self.swarm, j), zenoh.handlers.Callback(self._handover(j), indirect=False))

    def _handover(self, agent: int) -> Callable:
        """The subscriber callback for agent j's key (runs on a Zenoh thread): tag, hand over,
        and ring if the loop is waiting. (Appending before looking at ``waiting``, while the loop
        sets ``waiting`` before it looks at the inbox, loses no wake-up.)"""
        tag, append, ring = agent.to_bytes(2, "little"), self._inbox.put, self._bell.send

        def handover(sample) -> None:
            append(tag + sample.payload.to_bytes())
            if self.waiting:
                try:
                    ring(b"!")
                except OSError:  # the doorbell's buffer is full: the loop is awake anyway
                    pass

        return handover

    def _answer_door(self) -> None:
        try:
            while self._doorbell.recv(16):
                pass
        except BlockingIOError:
            pass
        self.take_estimates()

    def counts(self) -> dict[str, int]:
        """What the bus took in and what it dropped, by reason."""
        out = dict(self.counters)
        for name, inbox in (("drop_inbox_full", self.__dict__.get("_inbox")),
                            ("drop_status_inbox_full", self.__dict__.get("_status_inbox"))):
            if inbox is not None and inbox.dropped:
                out[name] = inbox.dropped
        return out

    # -- the loop ----------------------------------------------------------------------------

    def take_estimates(self) -> None:
        """Everything the Zenoh callbacks handed over: keep each agent's newest valid estimate."""
        if not self._inbox:
            return
        newest: dict[int, tuple] = {}
        for data in self._inbox.take():
            checked = self._check(int.from_bytes(data[0:2], "little"), data[2:])
            if checked is None:
                continue
            earlier = newest.get(checked[0])
            if earlier is None or _newer(checked[6], checked[4], earlier[6], earlier[4]):
                newest[checked[0]] = checked
                if earlier is not None:  # (older than one read with it: never used)
                    self.counters["drop_old"] += 1
            else:
                self.counters["drop_old"] += 1
        if newest:
            now = time.time()
            for checked in newest.values():
                self._take(checked, now)
            if self.on_estimates is not None:
                self.on_estimates()

    def drain(self) -> None:
        """Take in liveliness and status changes (and any estimate not yet read)."""
        self.take_estimates()
        now = time.monotonic()
        while (sample := self._alive_sub.try_recv()) is not None:
            self._alive(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT, now)
        if self._status_inbox:
            for key, data in self._status_inbox.take():
                self._status(key, data, now)
        if self._said_at and now - self._said_checked >= 0.5:
            self._said_checked = now
            self._forget_silent(now)

    def ready(self, agents: list[int], t_plan_s: float, tolerance_s: float, plans: tuple[int, ...]) -> bool:
        """Whether every agent in ``agents`` has an estimate of one of ``plans`` for plan time
        >= t_plan_s - tolerance_s."""
        table = self.estimates
        at = t_plan_s - tolerance_s
        for j in agents:
            nb = table[j]
            if nb.t_plan_s < at or nb.plan_id not in plans:
                return False
        return True

    def status_of(self, agent: int, plans: tuple[int, ...]) -> AgentStatus | None:
        """What ``agent`` last said it does, if it said so for one of ``plans``."""
        said = self.statuses.get(agent)
        return None if said is None or said[1] not in plans else said[0]

    def _check(self, key_agent: int, data: bytes):
        """Validate one estimate's header; count and drop what is not for us or not newer."""
        try:
            status, agent, plan, seq, stamp, t_plan = decode_header(data)
        except CodecError:
            self.counters["drop_undecodable"] += 1
            return None
        nb = self.estimates.get(agent)
        if nb is None or key_agent != agent or agent in self.members:
            self.counters["drop_unknown_agent"] += 1
            return None
        if not any(plan in m.plans for m in self.members.values()):
            self.counters["drop_other_plan"] += 1
            return None
        if not _newer(t_plan, seq, nb.t_plan_s, nb.seq):
            self.counters["drop_old"] += 1
            return None
        return agent, nb, data, status, seq, stamp, t_plan, plan

    def _take(self, checked, t_rx: float) -> None:
        """Keep the newest valid sample of a neighbour (its xi checked here, once)."""
        _, nb, data, status, seq, stamp, t_plan, plan = checked
        try:
            xi = decode_xi(data)
        except CodecError:
            self.counters["drop_undecodable"] += 1
            return
        nb.seq, nb.stamp_s, nb.t_plan_s, nb.status, nb.plan_id, nb.received_at, nb.xi = \
            seq, stamp, t_plan, status, plan, t_rx, xi
        self.counters["estimates"] += 1

    def _status(self, key: str, data: bytes, t_rx_s: float) -> None:
        """A status, taken at ``t_rx_s`` [s, monotonic]."""
        parsed = _parse_status(key, data)
        if parsed is None or not 1 <= parsed[0] <= self.n_agents:
            self.counters["drop_bad_status"] += 1
            return
        agent, status, plan = parsed
        self.counters["statuses"] += 1
        if self.statuses.get(agent) != (status, plan):
            self.statuses[agent] = (status, plan)
            self.changes += 1
        if agent not in self._tokens and agent not in self.members:  # (its token never came: alive while it speaks)
            if agent not in self.alive:
                self.alive.add(agent)
                self.changes += 1
            self._said_at[agent] = t_rx_s

    def _forget_silent(self, now_s: float) -> None:
        """The agents alive by their statuses alone that have said nothing for STATUS_ALIVE_S."""
        for agent in [a for a, at in self._said_at.items() if now_s - at > STATUS_ALIVE_S]:
            del self._said_at[agent]
            self.alive.discard(agent)
            self.statuses.pop(agent, None)
            self.changes += 1

    def _alive(self, key: str, present: bool, t_rx_s: float) -> None:
        """A liveliness token came (``present``) or went, taken at ``t_rx_s`` [s, monotonic]."""
        agent = agent_of_key(key)
        if agent is None or not 1 <= agent <= self.n_agents:
            self.counters["drop_bad_liveliness"] += 1
            return
        if present:
            self.alive.add(agent)
            self._tokens.add(agent)
            self.token_at[agent] = t_rx_s
            self._said_at.pop(agent, None)
        elif agent not in self.members:
            self.alive.discard(agent)
            self.statuses.pop(agent, None)
        self.changes += 1

    # -- outgoing ----------------------------------------------------------------------------

    def publish_estimate(self, agent: int, xi, t_plan_s: float, status: AgentStatus) -> None:
        """Agent ``agent``'s estimate: into the process's table at once, and out on Zenoh."""
        m = self.members[agent]
        m.seq += 1
        now = time.time()
        nb = self.estimates[agent]
        nb.seq, nb.stamp_s, nb.t_plan_s, nb.status, nb.plan_id, nb.received_at, nb.xi = \
            m.seq, now, t_plan_s, status, m.plan_id, now, xi
        data = encode_estimate(Estimate(agent, m.plan_id, m.seq, now, t_plan_s, status, xi))
        m.publisher.put(data)
        m.last, m.last_at = data, time.monotonic()
        if m.copy_publisher is not None and m.seq % COPY_EVERY == 0:
            m.copy_publisher.put(data)

    def republish(self, agent: int, after_s: float) -> bool:
        """Agent ``agent``'s newest estimate again if it is ``after_s`` old (wall) or more: in
        lockstep, where the clock stands until every awaited estimate is in, one lost with a Zenoh
        session that a stall of the machine ended comes again (the others drop it as old)."""
        m = self.members[agent]
        if m.last is None or time.monotonic() - m.last_at < after_s:
            return False
        m.publisher.put(m.last)
        m.last_at = time.monotonic()
        self.counters["republished"] += 1
        return True

    def publish_status(self, agent: int, status: AgentStatus, reason: str = "", since_s: float | None = None) -> None:
        """The status, why, and since when (Unix time [s]). Sent at every change and once a second,
        whole each time: a put lost on the way costs a second, not the reason or the time."""
        m = self.members[agent]
        now = time.time()
        m.status_publisher.put(json.dumps({"agent": agent, "plan": m.plan_id, "status": status.name, "reason": reason,
                                           "since": now if since_s is None else since_s, "t": now}).encode())

    def publish_health(self, agent: int, health: dict) -> None:
        self.members[agent].health_publisher.put(json.dumps(health).encode())


def _newer(t_plan_s: float, seq: int, than_t_plan_s: float, than_seq: int) -> bool:
    """Order of one agent's estimates: by the instant they refer to, then by sequence number. (A
    restarted companion counts its sequence from 1 again; its plan time goes on.)"""
    return t_plan_s > than_t_plan_s or (t_plan_s == than_t_plan_s and seq > than_seq)
