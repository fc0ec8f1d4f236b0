"""The control loop of a companion process: one tick for every telemetry sample of each of its
agents, in five steps:

    1. observe y and predict the state to t_p = t + servo delay (``FormationController``, the same
       code as the in-process simulation);
    2. publish xi_i = xhat_i - h_i(t_p) (on Zenoh, and into the process's table of estimates);
    3. wait for the in-neighbours' estimates for the same t_p (at most ``NB_WAIT_MS``; in lockstep
       until they come); the loop is free meanwhile, and an arriving estimate wakes it;
    4. check that a path from the leader remains through the agents that are alive, flying and
       fresh; if not, brake to a hold (and say so) until one returns, then rejoin;
    5. protocol (72) with the neighbours it has, RFL (49), the actuator command.

A link reader only hands its agent's samples over (``due``); the loop runs once all that was
readable has been read, over every agent whose sample came, so that the agents of a process (one on
a drone, a whole swarm in a simulation) share each step: one observer call per controller, one
evaluation of a formation per instant, one protocol and one RFL call per design. Agents whose
neighbours' estimates are not in yet wait, and finish together when they come. A bad tick costs its
agent one command, never the loop.

In lockstep there is no deadline for the neighbours: only a watchdog of NB_WATCHDOG_S of wall time
counts a live neighbour that has stopped publishing (a hung process) as absent, and says so.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import defaultdict

import numpy as np

from triswarm.protocol.agent import no_leader, pinned_input, protocol_rows
from triswarm.protocol.codec import AgentStatus
from triswarm.protocol.stall import Stalls

from .flight import Phase

LOCKSTEP_RECHECK_S = 0.1  # lockstep: while waiting for neighbours, look at who is alive this often [s, wall]
NB_WATCHDOG_S = 3.0  # lockstep: a live neighbour with no estimate for this long has hung [s, wall]
FORMATION_ERROR_EVERY = 10  # ticks between two samples of the formation error (for the 1 Hz report)


class Tick:
    """One agent's tick between its steps."""

    __slots__ = ("agent", "sample", "xhat", "t_plan", "t_p", "h", "x0", "gamma", "xi", "topo", "expected", "lockstep",
                 "since_wall", "next_wall", "nsum", "weight", "v")

    def __init__(self, agent, sample) -> None:
        self.agent, self.sample = agent, sample
        self.v = self.xi = None


class ControlLoop:
    """``agents``: how many agents the process flies.

    What a tick uses of an agent (``agent.Agent``): its flight controller (``fc``: samples, commands,
    the answers owed in lockstep), its flight (``flight``: the phase, what the reference follows, who
    counts), its controller row (``bank``, ``row``, ``design``, ``lead_s``, ``dt_s``, ``idle``), the
    plan (``plan_time``, ``topology_at``, ``plans.switch_due``, ``switch_plan``, ``plans.leader_state``),
    its neighbours (``in_neighbours``, ``in_weights``, ``bus.estimates``), its estimates on the bus
    (``publish_estimate``, ``estimates_in``, ``lockstep``, ``nb_wait_s``), and ``health``,
    ``clock_broke``, ``tick_failed``, ``log``."""

    def __init__(self, loop: asyncio.AbstractEventLoop, agents: int) -> None:
        self.loop = loop
        self._due: dict = {}          # agents with a new sample, in arrival order
        self._scheduled = False
        self.waiting: dict = {}       # agent -> its Tick waiting for neighbours' estimates
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = float("inf")
        self._buses: set = set()
        self._agents = agents
        self.stalls = Stalls(period_s=LOCKSTEP_RECHECK_S)
        """Lockstep: this process's own stalls are not counted as a neighbour's silence. Looked at
        with every batch of ticks and every look at who is alive while one waits: a gap longer than
        that (the process stopped, or idle while the flight controllers' clock stood) counts as a
        stall. (Looked at only while waiting, the first look after a stall that began in a wait
        had nothing to compare with: a neighbour whose state came in the stall counted as hung.)"""

    def watch(self, bus) -> None:
        """Estimates arriving on ``bus`` may complete waiting ticks."""
        if bus not in self._buses:
            self._buses.add(bus)
            bus.on_estimates = self._estimates_came

    def close(self) -> None:
        """The flight is over and the buses close next: nothing waits, no timer fires on them."""
        if self._timer is not None:
            self._timer.cancel()
        self._timer, self._timer_at = None, float("inf")
        self.waiting.clear()
        self._due.clear()
        self._buses.clear()

    def forget(self, agent) -> None:
        """``agent`` stops: nothing of it is due or waits any more."""
        self._due.pop(agent, None)
        self.waiting.pop(agent, None)

    def due(self, agent) -> None:
        """``agent``'s flight-controller link was read (a new sample, or a state offered again):
        run once everything readable now has been read. A sample that woke a wait (a start time)
        is acted on at once, before what it woke runs, whichever agent's link happened to be read
        first: what a tick sees at a given instant must not depend on the order of the reads (two
        lockstep runs give the same flight)."""
        if agent.fc.take_woke():
            self._due.pop(agent, None)
            self._run([agent])
            return
        self._due[agent] = None
        if not self._scheduled:
            self._scheduled = True
            self.loop.call_soon(self._run_due, True)

    def _run_due(self, once_more: bool = False) -> None:
        if once_more and len(self._due) < self._agents:
            # (one more turn of the loop first: the other agents' samples of this instant, sent
            # together, are on their way; acting on them together costs less)
            self.loop.call_soon(self._run_due)
            return
        self._scheduled = False
        agents = list(self._due)
        self._due.clear()
        self._run(agents)

    # -- the run ------------------------------------------------------------------------------------

    def _run(self, agents: list) -> None:
        # a new sample before the neighbours came: act now on what there is. (Only a new sample: a
        # read that brought none, a HEARTBEAT or a state offered again, leaves the wait as it is.)
        late = [self.waiting.pop(a) for a in agents if a in self.waiting and a.fc.backlog]
        if late:
            self._finish(late)
        for bus in self._buses:
            bus.drain()
        ticks = []
        for a in agents:
            s = self._take(a)
            if s is None or a.clock_broke(s):  # (a broken clock: the agent is lost, the sample not flown)
                continue
            if a.flight.in_flight and a.fc.ready:
                ticks.append(Tick(a, s))
            else:
                self._idle(a, s)
        if ticks:
            self._observe(ticks)
            flying = self._publish(ticks)
            earlier = list(self.waiting.values())
            self._wait(flying)
            if earlier:  # (agents of this process waiting for those that published now)
                self._check_waiting(earlier)
        for a in agents:
            a.fc.settle(a in self.waiting)
        self._arm_timer()

    def _take(self, a):
        """The newest sample of agent a; the older ones it did not act on (the loop fell behind)
        still update its estimate, as periods in which the flight controller kept the last command."""
        backlog = a.fc.backlog
        if not backlog:
            return None
        samples = list(backlog)
        backlog.clear()
        if len(samples) > 1:
            if a.flight.in_flight and a.bank is not None:
                try:
                    for old in samples[:-1]:
                        a.bank.hold_tick(np.array([old.y]), [a.row], np.array([old.rate_b_rad_s]),
                                         np.array([old.accel_b_m_s2]))
                except Exception:
                    a.tick_failed()
            half = 0.5 / a.rate_hz
            together = sum(b.t_rx - p.t_rx < half for p, b in zip(samples, samples[1:]))
            a.health.skipped(len(samples) - 1 - together, together)
        return samples[-1]

    def _idle(self, a, s) -> None:
        """No plan flying: armed on the ground in the companion's mode, the rotors idle (not the failsafe), where
        the flight controller's kind wants that."""
        fc = a.fc
        if (fc.ready and a.flight.phase in (Phase.IDLE, Phase.SCHEDULED) and fc.armed and fc.landed
                and fc.in_control and fc.autopilot.COMMANDS_WHILE_IDLE):
            fc.actuate(s, *a.idle)
            a.health.tick(s.t_rx, time.time())

    # -- 1. observe -----------------------------------------------------------------------------------

    def _observe(self, ticks: list[Tick]) -> None:
        by_bank = defaultdict(list)
        for t in ticks:
            by_bank[t.agent.bank].append(t)
        for bank, group in by_bank.items():
            try:
                xhat = bank.observe(np.array([t.sample.y for t in group]), [t.agent.row for t in group],
                                    np.array([t.sample.rate_b_rad_s for t in group]),
                                    np.array([t.sample.accel_b_m_s2 for t in group]))
            except Exception:
                for t in group:
                    t.agent.tick_failed()
                    t.xhat = None
                continue
            for k, t in enumerate(group):
                t.xhat = xhat[k]

    # -- 2. publish -----------------------------------------------------------------------------------

    def _publish(self, ticks: list[Tick]) -> list[Tick]:
        """References at t_p, xi published; holding agents get their command's input here. Returns
        the ticks of the agents flying the formation (they go on to wait for their neighbours)."""
        flying, holding = [], []
        for t in ticks:
            if t.xhat is None:
                continue
            a = t.agent
            try:
                t.t_plan = a.plan_time(t.sample.boot_us)
                t.t_p = t.t_plan + a.lead_s
                a.flight.t_p = t.t_p
                if a.plans.switch_due(t.t_plan):
                    a.switch_plan(t.t_plan)
                if a.flight.land_asked:
                    a.flight.start_landing(t.t_plan, t.xhat)
                (holding if a.flight.phase in (Phase.HOLDING, Phase.LANDING) else flying).append(t)
            except Exception:
                a.tick_failed()
        _references(flying)
        for t in flying:
            a = t.agent
            try:
                t.xi = t.xhat - t.h
                a.publish_estimate(t.xi, t.t_p, AgentStatus.FLYING)
            except Exception:
                a.tick_failed()
                t.xi = None
        for t in holding:
            try:
                self._hold_step(t)
            except Exception:
                t.agent.tick_failed()
        self._actuate([t for t in holding if t.v is not None])
        return [t for t in flying if t.xi is not None]

    def _hold_step(self, t: Tick) -> None:
        """Holding or landing: pinned to its own absolute reference (the braking or landing
        trajectory), no neighbours. A hold goes back to the formation as soon as a path from the
        leader returns; a landing ends on the ground (``Flight.landing_tick``)."""
        a = t.agent
        f = a.flight
        _references([t], tracking=f.hold, leader=no_leader)
        a.publish_estimate(t.xhat - t.h, t.t_p, AgentStatus.HOLDING)
        if f.phase == Phase.LANDING:
            f.landing_tick(t.t_p, t.xhat)
        elif f.has_path(a.topology_at(t.t_p), f.presence()):
            f.rejoin(t.t_plan, f.rejoin_source())
        t.v = pinned_input(a.design, (t.xhat - t.h)[None, :], t.x0, t.gamma[None, :])[0]

    # -- 3. wait --------------------------------------------------------------------------------------

    def _wait(self, ticks: list[Tick]) -> None:
        ready = []
        now = time.monotonic()
        self.stalls.look(now)
        for t in ticks:
            a = t.agent
            try:
                t.topo = a.topology_at(t.t_p)
                t.expected = [j for j in a.in_neighbours[t.topo.name] if a.flight.usable(j, check_fresh=False)]
            except Exception:
                a.tick_failed()
                continue
            t.since_wall = now
            t.lockstep = a.lockstep
            t.next_wall = now + (LOCKSTEP_RECHECK_S if t.lockstep else a.nb_wait_s)
            if a.estimates_in(t.expected, t.t_p):
                ready.append(t)
            else:
                self.waiting[a] = t
        if ready:
            self._finish(ready)
        self._set_waiting()
        if self.waiting:  # (looked at after ``waiting`` is set: an estimate arriving from now on rings)
            for bus in self._buses:
                bus.take_estimates()

    def _estimates_came(self) -> None:
        """New estimates from other processes: finish the ticks that have all they wait for."""
        self._check_waiting(list(self.waiting.values()))

    def _check_waiting(self, ticks: list[Tick]) -> None:
        # (only ticks still waiting: an estimate that came meanwhile may have finished some already)
        ticks = [t for t in ticks if self.waiting.get(t.agent) is t]
        ready = [t for t in ticks if t.agent.estimates_in(t.expected, t.t_p)]
        for t in ready:
            del self.waiting[t.agent]
        self._set_waiting()
        if ready:
            self._finish(ready)
            for t in ready:
                t.agent.fc.settle(False)

    def _set_waiting(self) -> None:
        for bus in self._buses:
            bus.waiting = bool(self.waiting)

    def _arm_timer(self) -> None:
        """One timer for the earliest of the waiting ticks' next moments: a deadline (real time) or
        the next look at who is alive (lockstep)."""
        if not self.waiting:
            return
        at = min(t.next_wall for t in self.waiting.values())
        if self._timer is not None:
            if at >= self._timer_at:
                return
            self._timer.cancel()
        self._timer_at = at
        self._timer = self.loop.call_at(self.loop.time() + max(0.0, at - time.monotonic()), self._timeout)

    def _timeout(self) -> None:
        self._timer, self._timer_at = None, float("inf")
        now = time.monotonic()
        self.stalls.look(now)
        for bus in self._buses:
            bus.drain()
        done = []
        for t in self.waiting.values():
            if t.next_wall > now:
                continue
            if not t.lockstep or self._lockstep_recheck(t, now):
                done.append(t)
            else:
                t.next_wall = now + LOCKSTEP_RECHECK_S
        for t in done:
            del self.waiting[t.agent]
        self._set_waiting()
        if done:
            self._finish(done)
            for t in done:
                t.agent.fc.settle(False)
        self._arm_timer()

    def _lockstep_recheck(self, t: Tick, now: float) -> bool:
        """Lockstep, still waiting: drop the neighbours that died or stopped flying (their liveliness
        and status tell), and the live ones from which no new estimate has come for NB_WATCHDOG_S of
        wall time in which this process ran (hung), saying so. The silence is a neighbour's, from its
        newest estimate on (from the wait's start for one never heard, or from its link's return),
        not each tick's: a hung neighbour costs one wait, not one per tick. True when the rest are in."""
        a = t.agent
        f = a.flight
        t.expected = [j for j in t.expected if f.usable(j, check_fresh=False) and j not in f.silent]
        late = [j for j in t.expected if not a.estimates_in([j], t.t_p)
                and self.stalls.silent_s(self._heard_at(a, j, t.since_wall, now), now) > NB_WATCHDOG_S]
        if late:
            for j in late:
                f.silent.setdefault(j, t.t_p - 0.5 * a.dt_s)  # (the instant it had no estimate for)
            a.log.warning(f"lockstep: no estimate for t_plan {t.t_p:.3f} from agent(s) {late} in "
                          f"{NB_WATCHDOG_S:g} s of wall time though alive: counted absent until they publish again")
            t.expected = [j for j in t.expected if j not in late]
        return a.estimates_in(t.expected, t.t_p)

    @staticmethod
    def _heard_at(a, j: int, since_wall: float, now: float) -> float:
        """When [s, time.monotonic] neighbour j's newest estimate came (the wait's start if never),
        or its liveliness token came again since: a link to it opened, and it may not yet have had
        the occasion to send again what was lost while there was none (a stall of either process
        past the Zenoh lease closes their links; opening them again takes Zenoh's retry period)."""
        received = a.bus.estimates[j].received_at  # [Unix s]
        heard = since_wall if not math.isfinite(received) else now - (time.time() - received)
        return max(heard, a.bus.token_at.get(j, -math.inf))

    # -- 4. path, 5. protocol and command -------------------------------------------------------------

    def _finish(self, ticks: list[Tick]) -> None:
        commanded = []
        for t in ticks:
            a = t.agent
            try:
                if not a.flight.in_flight or a.flight.phase != Phase.FLYING:
                    continue  # (the flight ended, or a hold began, while it waited)
                present = a.flight.presence()
                if not a.flight.has_path(t.topo, present):
                    a.flight.start_hold(t.t_plan, t.xhat, f"no path to the leader in {t.topo.name}")
                    self._hold_step(t)
                else:
                    self._neighbours(t, present)
                commanded.append(t)
            except Exception:
                a.tick_failed()
        self._protocol([t for t in commanded if t.v is None])
        self._actuate([t for t in commanded if t.v is not None])

    def _neighbours(self, t: Tick, present) -> None:
        """The weighted sum of the present in-neighbours' estimates and its weight."""
        a = t.agent
        table = a.bus.estimates
        nsum = np.zeros(12)
        weight = 0.0
        now = time.time()
        for j, w_ij in a.in_weights[t.topo.name]:
            nb = table[j]
            if present[j - 1] and nb.heard:
                nsum += w_ij * nb.xi
                weight += w_ij
                a.health.neighbour_age[j].add(now - nb.stamp_s)
        t.nsum, t.weight = nsum, weight

    def _protocol(self, ticks: list[Tick]) -> None:
        """(72) for each design's agents at once."""
        by_design = defaultdict(list)
        for t in ticks:
            by_design[id(t.agent.design)].append(t)  # (a design is not hashable: its arrays)
        for group in by_design.values():
            d = group[0].agent.design
            try:
                i = [t.agent.id - 1 for t in group]
                v = protocol_rows(d, np.array([t.xi for t in group]), np.array([t.nsum for t in group]),
                                   np.array([t.weight for t in group]),
                                   np.array([t.topo.pinning[k] for t, k in zip(group, i)]),
                                   np.array([t.x0 for t in group]), np.array([t.gamma for t in group]))
            except Exception:
                for t in group:
                    t.agent.tick_failed()
                continue
            for k, t in enumerate(group):
                t.v = v[k]

    def _actuate(self, ticks: list[Tick]) -> None:
        """RFL (49) for each controller's agents at once, and each agent's command."""
        by_bank = defaultdict(list)
        for t in ticks:
            by_bank[t.agent.bank].append(t)
        for bank, group in by_bank.items():
            try:
                act = bank.actuate(np.array([t.v for t in group]), [t.agent.row for t in group])
            except Exception:
                for t in group:
                    t.agent.tick_failed()
                continue
            for k, t in enumerate(group):
                a, s = t.agent, t.sample
                try:
                    a.fc.actuate(s, act.omega_rad_s[k], act.alpha_rad[k])
                    now = time.time()
                    a.health.tick(s.t_rx, now)
                    a.health.telemetry_age.add(now - a.fc.unix(s.boot_us))
                    if a.health.ticks % FORMATION_ERROR_EVERY == 0 and a.flight.phase == Phase.FLYING and t.xi is not None:
                        # (a tick of the formation, not of a hold: from its place now, its own reference)
                        err = t.xhat[9:12] - t.h[9:12] - t.x0[9:12]
                        a.health.formation_error.add(float(np.sqrt(err @ err)))
                except Exception:
                    a.tick_failed()


def _references(ticks: list[Tick], tracking=None, leader=None) -> None:
    """h at t_p, x0 at t_p and gamma (78) at the middle of the period the command is held for, for
    each tick (``reference_at`` over many agents): every agent's own reference (``tracking``,
    default its flight's), one gamma call per design."""
    by_design = defaultdict(list)
    for t in ticks:
        a = t.agent
        offsets = (tracking or a.flight.tracking).offsets
        lead = leader or a.plans.leader_state
        t_mid = t.t_p + 0.5 * a.dt_s
        h, _ = offsets(t.t_p)
        t.h = h[0]
        t.x0, _ = lead(t.t_p)
        h_mid, h_mid_dot = offsets(t_mid)
        x0_mid, x0_mid_dot = lead(t_mid)
        by_design[id(a.design)].append((t, h_mid[0] + x0_mid, h_mid_dot[0] + x0_mid_dot))
    for group in by_design.values():
        d = group[0][0].agent.design
        gamma = d.gamma(np.array([g[1] for g in group]), np.array([g[2] for g in group]))
        for k, (t, _, _) in enumerate(group):
            t.gamma = gamma[k]
