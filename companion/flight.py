"""The flight of one agent: its phase, what its reference follows, and the decisions that change
them. Nothing here runs per tick but the path check; the tick itself is ``loop.py``'s.

Phases: IDLE (no plan running), SCHEDULED (waiting for the common start time; armed shortly
before it with ``--autostart``), FLYING (the entry, the formation, or on the way back into it),
HOLDING (no path from the leader through the agents that are alive, flying and fresh: the drone
brakes to a stop and holds, pinned to its own reference, until a path returns; then it rejoins),
LANDING (asked to land: it leaves the formation, brakes and descends on its own reference, and
disarms once its flight controller says it is on the ground), LOST (the flight controller is
silent, or its clock broke: nothing is commanded until it is heard again and set up anew; then the
flight resumes as after a restart, ``Agent.take_fc_back``).

What the reference follows (``tracking``, a one-agent formation in offsets from the leader):
the entry (climb from where the drone rests, then blend into its row of the formation), the
formation itself, or a rejoin from wherever the drone was (a hold, a restart, the formation of
the plan before) that decays into the formation over ``REJOIN_S`` seconds or longer.
"""

from __future__ import annotations

import asyncio
import enum
import math
import time

import numpy as np

from triswarm.protocol import model
from triswarm.protocol.autopilots import COMPANION_MODES
from triswarm.protocol.codec import AgentStatus
from triswarm.protocol.formation import Formation, Kinematics, QuinticTransfer, RelativeTo, Rejoin, Row, Rows, rejoin_duration
from triswarm.protocol.mavlink import mavlink

from .liveliness import LOCKSTEP_GRACE_S, Liveliness

ARM_LEAD_S = 2.0
START_GRACE_S = 1.0  # after starting to fly, neighbours not yet heard from still count for the path check


class Phase(enum.Enum):
    IDLE = "idle"            # no plan running
    SCHEDULED = "scheduled"  # waiting for the common start time (armed shortly before)
    FLYING = "flying"        # in formation (or entering / rejoining it)
    HOLDING = "holding"      # no path to the leader: holding position
    LOST = "lost"            # the flight controller is lost: nothing commanded until it is back
    LANDING = "landing"      # descending on its own reference, out of the formation


PHASE_MODE = dict(zip(Phase, COMPANION_MODES))
"""The companion's HEARTBEAT custom_mode in each phase (``Phase`` is in COMPANION_MODES' order)."""
PHASE_STATUS = {Phase.IDLE: AgentStatus.IDLE, Phase.SCHEDULED: AgentStatus.IDLE, Phase.FLYING: AgentStatus.FLYING,
                Phase.HOLDING: AgentStatus.HOLDING, Phase.LOST: AgentStatus.HOLDING, Phase.LANDING: AgentStatus.HOLDING}
"""What the bus says of each phase (a lost agent publishes no estimate: its neighbours count it
absent; a landing one is out of the formation)."""
LAND_SINK_M = 0.3
"""A landing's descent aims this far below the ground it started from [m]: the touchdown is the
ground's, not the estimate's last centimetres, and the thrust falls once it is down."""
LAND_DETECT_S = 5.0
"""After the descent's end, the flight controller has this long [s, plan time] to say the vehicle
is on the ground; then a vehicle the estimate puts within LAND_FORCE_BELOW_M of the ground is
disarmed by force."""
LAND_FORCE_BELOW_M = 0.3
LAND_DISARM_RETRY_S = 1.0
"""A disarm the flight controller refused or did not answer is asked again this long after [s, plan time]."""


class Flight:
    """Agent ``agent_id``'s flight. ``fc``: its flight controller (``FlightController``); ``plans``: its
    plans (``Plans``); ``params``: the companion's parameters (``Params``); ``say(text, severity)``
    and ``log``: its voice; ``autostart``: it arms itself before the start time; ``on_phase()``: the
    phase changed (the agent publishes it); ``controller_reset(x)``: its controller row starts from
    the measured state x; ``lead_s()``: how far [s] the estimates run ahead of a sample's time;
    ``entry(plan, formation, t0_s)``: the entry the agents of the process share (``Host.entry``).
    The bus it counts its neighbours on comes with each plan opened (``opened``)."""

    def __init__(self, agent_id: int, fc, plans, params, say, log, *, autostart: bool, on_phase, controller_reset,
                 lead_s, entry) -> None:
        self.id, self.fc, self.plans, self.params, self.say, self.log = agent_id, fc, plans, params, say, log
        self.autostart = autostart
        self.on_phase, self.controller_reset, self.lead_s, self.entry = on_phase, controller_reset, lead_s, entry
        self.bus = None
        self.listen_to: frozenset[int] = frozenset()
        """The agents whose estimates this one gets."""
        self.plans_on_bus: tuple[int, ...] = ()
        """The plan ids that count on the bus (``Bus.plans_of``)."""
        self.phase = Phase.IDLE
        self.reason = ""
        self.since = fc.now_unix()
        """Why and since when [Unix s, the flight controller's clock] the phase is what it is."""
        self.flying_since = -math.inf
        self.tracking: Formation | None = None
        """What this drone's reference follows now (entry, formation, rejoin...)."""
        self.flying: Formation | None = None
        """The formation being flown (the entry first): what a rejoin goes back into."""
        self.hold: Formation | None = None
        """What a hold or a landing follows (absolute, with no leader)."""
        self.land_asked = False
        self.touchdown_s = math.inf
        """Landing: the plan time [s] the descent reaches its lowest point."""
        self.ground_z_m = 0.0
        """Where the vehicle rested before its entry (height in the local frame [m]; the swarm's
        home, if it did not start here): the ground a landing descends to."""
        self._disarm_task: asyncio.Task | None = None
        self._disarm_again_s = -math.inf
        self.silent: dict[int, float] = {}
        """Lockstep: the neighbours the watchdog counts absent, each with the instant [plan s] it had no
        estimate for; absent until one for that instant or a later one comes."""
        self._start_task: asyncio.Task | None = None
        self.liveliness = Liveliness()
        self._presence_base: tuple | None = None
        self._paths: dict[tuple, bool] = {}
        self.t_p = -math.inf  # the instant the newest tick's estimates refer to [plan s]

    @property
    def in_flight(self) -> bool:
        return self.phase in (Phase.FLYING, Phase.HOLDING, Phase.LANDING)

    def set_phase(self, phase: Phase, reason: str) -> None:
        if phase == self.phase:
            return
        now = self.fc.now_unix()
        if phase == Phase.FLYING and self.phase in (Phase.IDLE, Phase.SCHEDULED):
            self.flying_since = now
        self.phase, self.reason, self.since = phase, reason, now
        self.fc.clock.set_steady(self.in_flight)
        self.on_phase()
        if phase == Phase.HOLDING:
            self.say(f"holding, {reason}", mavlink.MAV_SEVERITY_WARNING)
        elif phase == Phase.FLYING:
            self.say("in formation")

    def mine(self, formation: Formation) -> Row:
        """This agent's row of a swarm's formation: the references it flies (entry, rejoin, hold)
        are one-agent formations."""
        return Row(formation, self.id - 1)

    def rejoin_source(self) -> Formation:
        """What a rejoin from the hold starts from: the hold, about the plan's leader."""
        return RelativeTo(self.hold, self.plans.leader)

    def opened(self, bus, listen_to: frozenset[int], plans_on_bus: tuple[int, ...]) -> None:
        """A plan was opened: this agent on ``bus`` (listening to ``listen_to``, counting the plans
        ``plans_on_bus``), with a new controller row. The old one's caches are forgotten."""
        self.bus, self.listen_to, self.plans_on_bus = bus, listen_to, plans_on_bus
        self._presence_base = None
        self._paths = {}

    # -- the start ------------------------------------------------------------------------------

    def schedule(self) -> None:
        """Fly the plan in force from its start time (after the flight controller is set up)."""
        self.cancel_start()
        self.set_phase(Phase.SCHEDULED, "")
        self._start_task = asyncio.ensure_future(self._start_when_due())

    def cancel_start(self) -> asyncio.Task | None:
        task, self._start_task = self._start_task, None
        if task is not None:
            task.cancel()
        return task

    async def _start_when_due(self) -> None:
        fc, m = self.fc, self.plans.mission
        try:
            while not (fc.clock.known and fc.ready):  # the flight controller's set-up is still running
                await asyncio.sleep(0.05)
            if self.autostart:  # (a start command has its answer already)
                self.say(f"plan {self.plans.plan.name} starts at {m.start_unix_s:.1f}")
                if fc.now_unix() > m.start_unix_s - ARM_LEAD_S:
                    self.say(f"ready {fc.now_unix() - m.start_unix_s + ARM_LEAD_S:.1f} s late for the start",
                             mavlink.MAV_SEVERITY_WARNING)
                await fc.clock.until(m.start_unix_s - ARM_LEAD_S)
                await self.arm()
            await fc.clock.until(m.start_unix_s)
            if not fc.armed:
                self.say("start time reached; waiting to be armed")
                while not fc.armed:
                    await asyncio.sleep(0.05)
            if fc.landed:  # (some flight controllers take off themselves before they hand over)
                await fc.launch(self.plans.plan.entry.climb_m, self.say)
            if not fc.in_control:  # e.g. hovering after the operator's takeoff
                await fc.take_control()
            while self.state_now() is None:  # (a position to start from)
                await asyncio.sleep(0.05)
            self.begin_entry(max(0.0, self.plans.plan_time(fc.last_sample.boot_us)))
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # the plan does not start; the companion keeps routing and reporting
            self.log.exception("plan start failed")
            self.set_phase(Phase.IDLE, "")
            self.say(f"plan not started: {exc}", mavlink.MAV_SEVERITY_ERROR)

    async def arm(self) -> None:
        result = await self.fc.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            self.say(f"the flight controller refused to arm ({result})")
            raise RuntimeError("arming refused")

    def state_now(self) -> np.ndarray | None:
        """The measured state x of (28) from the newest sample, or None before one with a position
        came (body rates that did not come count as zero)."""
        s = self.fc.last_sample
        if s is None or not all(math.isfinite(c) for c in s.position_e_m + s.velocity_e_m_s):
            return None
        eta = np.array(s.eta_rad)
        R = model.rotation_body_to_earth(eta)
        rates = np.nan_to_num(np.array(s.rate_b_rad_s))
        return np.concatenate([R.T @ np.array(s.velocity_e_m_s), rates, eta, s.position_e_m])

    def begin_entry(self, t0_s: float) -> None:
        """Take off from where the drone rests and enter the formation (the plan's entry) from plan
        time ``t0_s``."""
        x = self.state_now()
        self.controller_reset(x)
        self.ground_z_m = float(x[11])
        self.plans.set_phase("flying")
        self.flying = self.tracking = self.entry(self.plans.plan, self.plans.formation, t0_s).join(self.id - 1, x[9:12])
        self.set_phase(Phase.FLYING, "")

    async def resume(self) -> None:
        """After a restart (of the companion, or of the flight controller): join the formation again
        from wherever the vehicle is; a plan whose start is still ahead on the flight controller's
        clock is scheduled again."""
        fc, plans = self.fc, self.plans
        if plans.mission.start_unix_s > fc.now_unix():
            self.schedule()
            return
        while self.state_now() is None:
            await asyncio.sleep(0.05)
        if plans.mission.phase == "landing":  # (a landing goes on; one that is over ends)
            if not fc.armed or fc.landed:
                self.release("on the ground after the landing")
                return
            x = self.state_now()
            self.controller_reset(x)
            self.start_landing(plans.plan_time(fc.last_sample.boot_us), plans.plan.rfl.phi_r(x[None, :])[0])
            return
        if not fc.armed or fc.landed:
            if not fc.armed:
                await self.arm()
            await fc.launch(plans.plan.entry.climb_m, self.say)
            if not fc.in_control:
                await fc.take_control()
            self.begin_entry(plans.plan_time(fc.last_sample.boot_us) + 1.0)
            return
        x = self.state_now()
        self.controller_reset(x)
        t_plan = plans.plan_time(fc.last_sample.boot_us)
        self.flying = self.mine(plans.formation)
        self.hold = braking(t_plan + self.lead_s(), plans.plan.rfl.phi_r(x[None, :])[0])
        self.rejoin(t_plan, self.rejoin_source())

    def check_release(self) -> None:
        """The flight controller took the vehicle back (the operator's land or hold, a disarm):
        this flight of the plan is over. (A failsafe hold, which commands win back, is not.)"""
        fc = self.fc
        if not self.in_flight:
            return
        if not fc.armed:
            self.release("landed and disarmed" if self.phase == Phase.LANDING else "disarmed")
        elif (reason := fc.released()) is not None:
            self.release(reason)

    def release(self, reason: str) -> None:
        landed = self.phase == Phase.LANDING or self.plans.mission.phase == "landing"
        self.land_asked = False
        self.plans.set_phase("done")
        self.set_phase(Phase.IDLE, "")
        self.say(f"formation flight over: {reason}", mavlink.MAV_SEVERITY_INFO if landed else mavlink.MAV_SEVERITY_WARNING)

    # -- hold and rejoin ------------------------------------------------------------------------

    def start_hold(self, t_plan: float, xhat: np.ndarray, reason: str) -> None:
        """xhat: the estimate x_r predicted to t_plan + lead ([lambda_dot, eta_dot, eta, lambda])."""
        self.hold = braking(t_plan + self.lead_s(), xhat)
        n = self.plans.plan.n_agents
        absent = {j: self.why_absent(j) for j in range(1, n + 1) if not self.usable(j)}
        self.log.info(f"hold at t_plan {t_plan:.3f}: {reason}; absent {absent}")
        self.set_phase(Phase.HOLDING, reason)

    # -- landing ----------------------------------------------------------------------------------

    def ask_to_land(self) -> tuple[int, str]:
        """MAV_CMD_NAV_LAND to the companion: (MAV_RESULT, why refused). The next tick begins the
        landing (``start_landing``)."""
        if self.phase == Phase.LANDING or (self.land_asked and self.in_flight):
            return mavlink.MAV_RESULT_ACCEPTED, ""
        if not self.in_flight:
            return mavlink.MAV_RESULT_DENIED, ("land refused: the companion is not flying the vehicle (ask the "
                                               "flight controller to land)")
        self.land_asked = True
        return mavlink.MAV_RESULT_ACCEPTED, ""

    def start_landing(self, t_plan: float, xhat: np.ndarray) -> None:
        """Out of the formation: brake and descend to LAND_SINK_M below the ground at a mean
        LAND_SPEED, from xhat (the estimate x_r predicted to t_plan + lead)."""
        self.land_asked = False
        self.plans.set_phase("landing")
        t0 = t_plan + self.lead_s()
        self.hold, self.touchdown_s = landing(t0, xhat, self.ground_z_m - LAND_SINK_M, self.params.values["LAND_SPEED"])
        self.log.info(f"landing at t_plan {t_plan:.3f} from {xhat[11] - self.ground_z_m:.2f} m above the ground, "
                        f"down at t_plan {self.touchdown_s:.1f}")
        self.set_phase(Phase.LANDING, "asked to land")
        self.say(f"landing: down in {self.touchdown_s - t0:.0f} s")

    def landing_tick(self, t_p: float, xhat: np.ndarray) -> None:
        """Landing, at the instant t_p [plan s] the estimate xhat is of: once the descent is over and
        the flight controller says the vehicle is on the ground, disarm; if it has not said so
        LAND_DETECT_S on, disarm by force a vehicle that is within LAND_FORCE_BELOW_M of the ground."""
        if t_p < max(self.touchdown_s, self._disarm_again_s) or self._disarm_task is not None:
            return
        self._disarm_again_s = t_p + LAND_DISARM_RETRY_S
        if self.fc.landed:
            self._disarm_task = asyncio.ensure_future(self._disarm(force=False))
        elif t_p >= self.touchdown_s + LAND_DETECT_S and xhat[11] - self.ground_z_m < LAND_FORCE_BELOW_M:
            self.say(f"the flight controller has not detected the landing {LAND_DETECT_S:g} s after the descent: "
                       "disarming by force", mavlink.MAV_SEVERITY_WARNING)
            self._disarm_task = asyncio.ensure_future(self._disarm(force=True))

    async def _disarm(self, force: bool) -> None:
        try:
            result = await self.fc.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0, 21196.0 if force else 0.0)
            if result == mavlink.MAV_RESULT_ACCEPTED:
                if self.phase == Phase.LANDING:
                    self.release("landed and disarmed")
            else:
                self.say(f"the flight controller refused to disarm after the landing ({result}): asking again in "
                           f"{LAND_DISARM_RETRY_S:g} s", mavlink.MAV_SEVERITY_WARNING)
        except TimeoutError:
            self.say(f"no answer from the flight controller to the disarm after the landing: asking again in "
                       f"{LAND_DISARM_RETRY_S:g} s", mavlink.MAV_SEVERITY_WARNING)
        finally:
            self._disarm_task = None

    # -- rejoin -------------------------------------------------------------------------------------

    def rejoin(self, t_plan: float, source: Formation) -> None:
        """Into the formation from ``source`` (the braking/held trajectory, or the formation of the
        plan before): the reference starts exactly where (and as fast as) the drone is meant to be,
        and its distance to the formation decays over REJOIN_S seconds, longer if the way is long
        (peak acceleration REJOIN_ACCEL)."""
        values = self.params.values
        t0 = t_plan + self.lead_s()  # references are evaluated at the time the estimates refer to
        target = self.flying or self.mine(self.plans.formation)  # the entry, if it is not over
        rejoin = Rejoin(source, target, t0, values["REJOIN_S"])
        dp, dv = (float(np.linalg.norm(e[0])) for e in rejoin.initial_error)
        duration_s = rejoin_duration(dp, dv, values["REJOIN_ACCEL"], values["REJOIN_S"])
        if duration_s > rejoin.duration_s:
            rejoin = Rejoin(source, target, t0, duration_s)
        self.log.info(f"rejoin at t_plan {t_plan:.3f}: {dp:.2f} m and {dv:.2f} m/s away, over {rejoin.duration_s:.1f} s")
        self.tracking = rejoin
        self.set_phase(Phase.FLYING, "")

    def switched(self, t_plan: float, plans_on_bus: tuple[int, ...]) -> None:
        """A plan was put in force in flight (the plans that count on the bus now: ``plans_on_bus``):
        its formation from now, reached as a rejoin does."""
        self.plans_on_bus = plans_on_bus
        self.flying = self.mine(self.plans.formation)
        if self.phase == Phase.FLYING:
            self.rejoin(t_plan, self.tracking)

    # -- who counts -------------------------------------------------------------------------------

    def presence(self) -> tuple[bool, ...]:
        """Which agents count now (``usable``), every one. Of the agents this one does not listen
        to, only liveliness, status and the start decide: that part is kept until one changes."""
        starting = self.fc.now_unix() - self.flying_since < START_GRACE_S
        key = (self.bus.changes, starting, self._liveliness_kept())
        if self._presence_base is None or self._presence_base[0] != key:
            n = self.plans.plan.n_agents
            self._presence_base = (key, [self.usable(j) for j in range(1, n + 1)])
        present = list(self._presence_base[1])
        for j in self.listen_to:  # (their estimates' freshness changes every tick)
            present[j - 1] = self.usable(j)
        return tuple(present)

    def has_path(self, topo, present: tuple[bool, ...]) -> bool:
        """Whether this agent has a path from the leader through the present agents (cached: the
        answer only changes when an agent comes or goes)."""
        key = (topo.name, present)
        found = self._paths.get(key)
        if found is None:
            found = self._paths[key] = bool(topo.reachable_from_leader(np.array(present))[self.id - 1])
        return found

    def _liveliness_kept(self) -> frozenset[int]:
        """The agents whose liveliness token went but that still count as alive (lockstep's grace,
        ``liveliness.py``)."""
        return self.liveliness.update(self.bus.alive, self.bus.changes, self.t_p,
                                      LOCKSTEP_GRACE_S if self.fc.answers.lockstep else 0.0)

    def _alive(self, j: int) -> bool:
        """Agent j's token is there, or it went but j counts as alive for its grace (lockstep): only
        an agent this one does not listen to, whose token is all it has of it. (A neighbour's own
        estimates are its sign of life, and the lockstep wait does not wait for a neighbour whose
        token went: waiting out a dead one's grace raced the SITL's watchdog of this companion.)"""
        kept = self._liveliness_kept()  # (every time: it sees each change of the bus's set)
        return j in self.bus.alive or (j in kept and j not in self.listen_to)

    def usable(self, j: int, check_fresh: bool = True) -> bool:
        """Agent j counts: alive, flying this plan, and (for a neighbour whose estimates we get)
        with an estimate younger than NB_TIMEOUT_S. A neighbour whose fresh estimates come counts
        without its liveliness token: under loss, Zenoh has been seen to lose a token's declaration
        for a whole flight while the estimates flowed (the estimates are the better sign of life:
        they stop within NB_TIMEOUT_S when it dies)."""
        if j == self.id:
            return True
        bus = self.bus
        alive = self._alive(j)
        if not alive and (j not in self.listen_to or not check_fresh):  # (lockstep's wait: only for the living)
            return False
        starting = self.fc.now_unix() - self.flying_since < START_GRACE_S  # the swarm takes off together
        plans = self.plans_on_bus
        status = bus.status_of(j, plans)
        if status == AgentStatus.HOLDING or (status == AgentStatus.IDLE and not starting):
            return False
        if j not in self.listen_to:
            return True  # not one of ours to listen to: liveliness and status decide
        nb = bus.estimates[j]
        if j in self.silent:  # (lockstep: the watchdog's) until it has published since. (Not "an
            # estimate of now": nobody waits for a silent neighbour, so its estimate of now would have
            # to beat this tick, a race an agent on the same clock loses tick after tick.)
            if nb.t_plan_s < self.silent[j]:
                return False
            del self.silent[j]
        if not nb.heard or nb.plan_id not in plans:
            return starting and alive
        if nb.status != AgentStatus.FLYING:
            return False
        # stale in plan time (the flight controllers' clock): a pause of the whole swarm is not a loss
        return not check_fresh or self.t_p - nb.t_plan_s <= self.params.values["NB_TIMEOUT_S"]

    def why_absent(self, j: int) -> str:
        bus = self.bus
        alive = self._alive(j)
        if not alive and j not in self.listen_to:
            return "no liveliness"
        lost = "" if alive else "no liveliness, "
        status = bus.status_of(j, self.plans_on_bus)
        nb = bus.estimates.get(j)
        if nb is not None and nb.heard:
            return (f"{lost}status {status.name if status else '?'}, estimate {1e3 * (time.time() - nb.stamp_s):.0f} ms "
                    f"old, t_plan {nb.t_plan_s:.3f} (received {1e3 * (time.time() - nb.received_at):.0f} ms ago)")
        return f"{lost}status {status.name if status else '?'}, no estimate"


def braking(t: float, x: np.ndarray) -> QuinticTransfer:
    """From x_r = [lambda_dot, eta_dot, eta, lambda] at plan time t to rest at its stopping point,
    level (absolute, local frame; one agent)."""
    p0, v0, eta0, eta_dot0 = x[9:12], x[0:3], x[6:9], x[3:6]
    T = max(2.0, float(np.linalg.norm(v0)) / 2.0)
    row = lambda a: np.asarray(a, dtype=float).reshape(1, 3)  # noqa: E731
    return QuinticTransfer(row(p0), row(v0), row(p0 + v0 * T / 2.0), row(eta0), row(eta_dot0),
                           row([0.0, 0.0, eta0[2]]), t, T)


def landing(t: float, x: np.ndarray, bottom_z_m: float, speed_m_s: float) -> tuple[Formation, float]:
    """From x_r = [lambda_dot, eta_dot, eta, lambda] at plan time t: brake (as ``braking``) and
    descend to rest at height ``bottom_z_m`` [m, local frame], level, over a quintic of mean speed
    ``speed_m_s`` (its peak: 1.875 times that). Returns the reference and the plan time of the
    descent's end (absolute, local frame; one agent)."""
    stop = braking(t, x)
    T = max(stop.duration_s, (float(x[11]) - bottom_z_m) / speed_m_s)
    row = lambda a: np.asarray(a, dtype=float).reshape(1, 3)  # noqa: E731
    level = row([0.0, 0.0, x[8]])
    p_stop = stop.p1[0]
    down = QuinticTransfer(row(p_stop), row([0.0, 0.0, 0.0]), row([p_stop[0], p_stop[1], bottom_z_m]),
                           level, row([0.0, 0.0, 0.0]), level, t, T)
    return Rejoin(stop, down, t, stop.duration_s), t + T


class SharedEntry(Formation):
    """The entries of the agents of a process that begin entering one plan's formation at the same
    plan time: one entry formation (``Plan.entry_formation``) over all their rows, evaluated once
    per instant for all of them. Each agent flies its ``Row`` (``join``); an agent that joins
    later (a restart) adds a row, and the rows before keep their values to the bit (the entry is
    computed element by element)."""

    def __init__(self, plan, formation: Formation, t0_s: float) -> None:
        self.plan, self.formation, self.t0_s = plan, formation, t0_s
        self._rows: list[int] = []
        self._starts: list[np.ndarray] = []
        self._built: Formation | None = None

    @property
    def n_agents(self) -> int:
        return len(self._rows)

    def join(self, index: int, start_position_m: np.ndarray) -> Row:
        """Agent ``index`` (from 0) of the plan, resting at ``start_position_m``: its row."""
        self._rows.append(index)
        self._starts.append(np.asarray(start_position_m, dtype=float))
        self._built = None
        return Row(self, len(self._rows) - 1)

    def _entry(self) -> Formation:
        if self._built is None:
            self._built = self.plan.entry_formation(np.array(self._starts), self.t0_s,
                                                    Rows(self.formation, tuple(self._rows)))
        return self._built

    def kinematics(self, t_s: float) -> Kinematics:
        return self._entry().kinematics(t_s)

    def offsets(self, t_s: float):
        return self._entry().offsets(t_s)
