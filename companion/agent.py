"""One agent of a companion process: one drone's formation controller between its flight controller
and its neighbours, made of rooms that each have one job:

- ``flight_controller.FlightController``: the flight controller (link, state, clock, telemetry,
  commands), with its ``Autopilot`` (``autopilots/``: what differs between kinds of flight controller);
- ``ground_station.GroundStation``: the ground station (link, routing, parameters, commands);
- ``plan_server.PlanServer``: plans up and down the ground-station link (the mission protocol);
- ``plans.Plans``: the plan in force, the one staged, leader moves, kept across restarts;
- ``flight.Flight``: the phase, the entry, hold and rejoin, who counts;
- ``health.LoopHealth``: loop timing and the formation error, reported once a second;

while the process (``host.Host``) gives every agent its share of the Zenoh bus, a row of the
controller of its plan's design, and the control loop (``loop.ControlLoop``) that ticks it.

The agent builds each room from the rooms and callbacks it uses, passed to its constructor; no room
is handed the agent, and a room changes another only through that room's methods.

Plan time is the flight controller's clock (SYSTEM_TIME) minus the swarm's common start time, and
every wait and timeout of the mission runs on that clock (``clock.py``), so the same code flies on a
simulator's clock in lockstep.

A dead flight controller's clock stops with it, so a lost flight controller is told on the wall
clock: nothing heard from it for FC_SILENT_S (``watch_fc``, once a second). A clock that broke (its
boot time back by REBOOT_JUMP_US or more: a reboot; or ahead of the wall clock by CLOCK_JUMP_US) is
told once CLOCK_BREAK_SAMPLES samples in a row show it over CLOCK_BREAK_S (``clock_broke``; those
samples are not flown, and fewer are dropped as stale or future stamps, counted). Either way the agent
is LOST: it commands nothing and says so; once the flight controller is heard again it is set up as
a new one (its parameters, streams and clock) and the flight resumes as after a restart
(``take_fc_back``).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time

import numpy as np

from triswarm.protocol import model
from triswarm.protocol.airframe import TABLE_1
from triswarm.protocol.mavlink import mavlink
from triswarm.protocol.stall import Stalls

from triswarm.protocol.timesync import start_clock_problem

from .autopilots.base import AutopilotError
from .flight_controller import FlightController
from .clock import OFFSET_STEP_US, kernel_clock
from .errors import CompanionError
from .flight import PHASE_MODE, PHASE_STATUS, Flight, Phase
from .ground_station import GroundStation, Params
from .health import LoopHealth
from .options import CompanionOptions, home_of
from .plan_server import PlanServer
from .plans import Plans
from .state import StateStore, read_signing_key
from .telemetry import REBOOT_JUMP_US

log = logging.getLogger("triswarm.companion")

IDLE_FRACTION = 0.3  # idle rotor speed on the ground, as a fraction of hover
FC_SILENT_S = 3.0
"""Nothing from the flight controller for this long [s, wall clock]: it is lost. (It sends a heartbeat
a second at least; a simulator in lockstep too while its clock stands.)"""
REPUBLISH_AFTER_S = 1.0
"""In lockstep, an estimate not followed by another for this long (the clock stands) is sent again
(``Bus.republish``)."""
CLOCK_JUMP_US = REBOOT_JUMP_US
"""A sample whose boot time ran this much further [us] than the wall clock since the one before:
the flight controller's clock jumped."""
CLOCK_BREAK_SAMPLES = 3
CLOCK_BREAK_S = 0.1
"""A broken clock is believed once CLOCK_BREAK_SAMPLES samples in a row show it, running on from
each other, over CLOCK_BREAK_S [s, wall] at least (a rebooted flight controller's stream does);
samples that show it and are followed by one on the old clock were stamps out of place (a hostile
message, a frame corrupted past its checksum: a flood of them still leaves the flight controller's
own telemetry between them) and are dropped, counted as ``samples_off_the_clock``. One message must
not take the vehicle's control down."""


class StartupError(CompanionError):
    """The companion cannot start as asked (a link it cannot open, an unreadable signing key, a Zenoh
    session it cannot open): one sentence for the operator, exit status 2."""


class AgentLog(logging.LoggerAdapter):
    """The companion's log, each line naming its agent (several agents may share a process)."""

    def process(self, msg, kwargs):
        prefix = f"companion {self.extra['agent']}: "
        return (msg if str(msg).startswith(prefix) else prefix + str(msg)), kwargs


class Agent:
    """``host``: the process (its bus, controllers and loop); ``row``: this agent's row in them."""

    def __init__(self, opts: CompanionOptions, host, row: int) -> None:
        self.opts, self.host, self.row = opts, host, row
        self.id = opts.id
        self.log = AgentLog(log, {"agent": opts.id})
        try:
            key = None if opts.signing_key is None else read_signing_key(opts.signing_key)
        except ValueError as exc:  # (one sentence: the file and what is wrong with it)
            raise StartupError(str(exc)) from None
        self.store = StateStore(opts.state_dir, self.warn)
        self.rate_hz = opts.rate_hz
        """The control rate [Hz]: the rate asked for, or the one the attitude comes at."""
        self.params = Params(opts.rate_hz)
        self.health = LoopHealth(1.0 / opts.rate_hz)
        self.fc = FlightController(self.id, opts.fc, self.log, lambda: self.flight.check_release(), opts.fc_profile,
                                   home_of(opts), after_read=lambda: host.loop_ctl.due(self), on_link_event=self.warn)
        self.kernel_clock = kernel_clock
        """The kernel's word on the wall clock (a test puts its own)."""
        self.plans = Plans(self.id, self.store, self.fc.clock, self.log, self._reopen, self._schedule,
                           lambda: self.flight.in_flight, clock_check=self.start_clock_problem)
        self.plan_server = PlanServer(lambda items: self.plans.receive(items, self.loop), self._clear_plans,
                                      self.plans.held_items, self.say)
        self.flight = Flight(self.id, self.fc, self.plans, self.params, self.say, self.log, autostart=opts.autostart,
                             on_phase=self.publish_status, controller_reset=self.controller_reset,
                             lead_s=lambda: self.lead_s, entry=host.entry)
        self.gcs = GroundStation(self.id, opts.gcs, key, fc=self.fc, params=self.params, plans=self.plans,
                                 plan_server=self.plan_server, ask_to_land=self.flight.ask_to_land,
                                 heartbeat=self.heartbeat, store=self.store, say=self.say, log=self.log,
                                 frames_per_s=opts.gcs_frames_per_s, on_link_event=self.warn)
        omega, alpha = model.hover_trim(TABLE_1)  # until a plan names the airframe
        self.idle = (omega * IDLE_FRACTION, alpha)
        self.bus = None
        self.bank = None
        """The controller of this agent's design (a row each for the process's agents), once a plan is open."""
        self._asking: asyncio.Future | None = None
        self.design = None
        self.listen_to: frozenset[int] = frozenset()
        self.in_neighbours: dict[str, list[int]] = {}
        self.in_weights: dict[str, list[tuple[int, float]]] = {}
        self.plans_on_bus: tuple[int, ...] = ()
        self.errors = 0
        self.fc_lost_since: float | None = None
        """Since when the flight controller is lost [s, time.monotonic] (None: it is not)."""
        self._fc_back: asyncio.Task | None = None
        self.stalls = Stalls(period_s=1.0)
        """This process's own stalls, seen by the once-a-second work: not counted as the flight
        controller's silence."""
        self._last_boot: tuple[int, float] | None = None  # (boot us, monotonic s) of the newest sample on the clock
        self._off_clock: list[tuple[int, float]] = []  # the samples since, in a row, that show it broken
        self._told_plans: set[tuple[int, object]] = set()
        self._told_clock_step: int | None = None

    # -- what the rooms share ---------------------------------------------------------------------

    @property
    def lead_s(self) -> float:
        return self.bank.lead_s

    @property
    def dt_s(self) -> float:
        return self.bank.dt_s

    def plan_time(self, boot_us: int) -> float:
        return self.plans.plan_time(boot_us)

    @property
    def lockstep(self) -> bool:
        """Its flight controller is a simulator in lockstep (every state it sends is answered)."""
        return self.fc.answers.lockstep

    @property
    def nb_wait_s(self) -> float:
        """The longest wait for the neighbours' estimates [s, wall] (``NB_WAIT_MS``; not in lockstep)."""
        return self.params.values["NB_WAIT_MS"] / 1000.0

    def topology_at(self, t_plan: float):
        """The graph of the plan in force at plan time ``t_plan`` [s]."""
        return self.plans.plan.schedule.at(t_plan)

    def publish_estimate(self, xi: np.ndarray, t_p: float, status) -> None:
        """This agent's xi for plan time ``t_p`` [s] on the bus, with its status."""
        self.bus.publish_estimate(self.id, xi, t_p, status)

    def estimates_in(self, agents: list[int], t_p: float) -> bool:
        """Whether the estimates of ``agents`` for plan time ``t_p`` [s] (within half a period) are in."""
        return self.bus.ready(agents, t_p, 0.5 * self.dt_s, self.plans_on_bus)

    def controller_reset(self, x: np.ndarray) -> None:
        self.bank.reset(x[None, :], rows=np.array([self.row]))

    def say(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        """To the log and the ground station, as this companion."""
        text = f"companion {self.id}: {text}"
        self.log.info(text)
        self.gcs.statustext(text, severity)

    def warn(self, text: str) -> None:
        """``say`` as a warning (a state file that cannot be written, a serial port that failed and is back)."""
        self.say(text, mavlink.MAV_SEVERITY_WARNING)

    def tick_failed(self) -> None:
        """A tick that raised: it costs one command, never the loop."""
        self.errors += 1
        if self.errors <= 3:
            self.log.exception("tick failed")

    def heartbeat(self):
        status = {Phase.HOLDING: mavlink.MAV_STATE_CRITICAL, Phase.LOST: mavlink.MAV_STATE_CRITICAL,
                  Phase.FLYING: mavlink.MAV_STATE_ACTIVE}.get(
            self.flight.phase, mavlink.MAV_STATE_STANDBY)
        return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                                                 mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PHASE_MODE[self.flight.phase],
                                                 status, 3)

    def publish_status(self) -> None:
        """The phase on the bus, with why and since when."""
        if self.bus is not None:
            f = self.flight
            self.bus.publish_status(self.id, PHASE_STATUS[f.phase], f.reason, f.since)

    # -- a plan in force ------------------------------------------------------------------------

    def open_plan(self) -> None:
        """Fly the plan in force: this agent on its swarm's bus, its neighbours, its controller row."""
        plan, i = self.plans.plan, self.id - 1
        topologies = plan.schedule.topologies
        self.listen_to = frozenset(int(j) + 1 for t in topologies for j in t.in_neighbours(i))
        self.in_neighbours = {t.name: [int(j) + 1 for j in t.in_neighbours(i)] for t in topologies}
        self.in_weights = {t.name: [(j, float(t.adjacency[i, j - 1])) for j in self.in_neighbours[t.name]]
                           for t in topologies}
        if self.bus is not None:
            self.bus.leave(self.id)
        self.bus = self.host.bus(self.opts.swarm or plan.name, plan.n_agents)
        self.bus.join(self.id, self.plans.mission.plan_id, self.listen_to)
        if self.lockstep:
            self.bus.reliable_estimates()
        self.plans_on_bus = self.bus.plans_of(self.id)
        self.design = plan.design
        self.bank = self.host.controller(plan, self.rate_hz)
        self.params.declare("COUPLING_C", plan.design.c)
        omega, alpha = model.hover_trim(plan.airframe)
        self.idle = (omega * IDLE_FRACTION, alpha)
        self.flight.opened(self.bus, self.listen_to, self.plans_on_bus)
        self.publish_status()
        if self.fc.ready:  # (a plan after the set-up: else the set-up asks)
            self._asking = asyncio.ensure_future(self._ask_accelerometer())  # (kept: a task only weakly held is lost)

    def set_rate(self, rate_hz: float) -> None:
        """Control at ``rate_hz`` (the rate the attitude comes at), before any flight."""
        self.rate_hz = rate_hz
        self.params.values["CTRL_RATE_HZ"] = rate_hz
        self.health.period_s = 1.0 / rate_hz
        if self.bank is not None:
            plan = self.plans.plan
            self.bank = self.host.controller(plan, rate_hz)

    def _reopen(self, reopen: bool) -> None:
        if reopen or self.bus is None:
            self.open_plan()

    def _schedule(self) -> None:
        self.flight.schedule()

    def switch_plan(self, t_plan: float) -> None:
        """The plan to put in force in flight is due now."""
        plan, pid = self.plans.take_switch()
        self.bus.switch_plan(self.id, pid)
        self.plans_on_bus = self.bus.plans_of(self.id)
        self.params.declare("COUPLING_C", plan.design.c)
        self.say(f"plan {plan.name} {pid:08x} in force")
        self.flight.switched(t_plan, self.plans_on_bus)

    def _clear_plans(self) -> tuple[int, str]:
        code, reason = self.plans.clear()
        if code == mavlink.MAV_MISSION_ACCEPTED:
            self.flight.cancel_start()
            self.flight.set_phase(Phase.IDLE, "")
        return code, reason

    # -- run --------------------------------------------------------------------------------------

    async def run(self, stop: asyncio.Event) -> dict:
        self.loop = asyncio.get_running_loop()
        self.plans.load(self.opts.plan)
        self.gcs.restore_signing_streams()
        self.store.write_in_background(self._warn_from_thread)  # (a disk's wait must not stall the loop)
        tasks: list[asyncio.Task] = []
        try:
            try:
                self.fc.link.open(self.loop, lambda link, msgs, t_rx: self.gcs.from_fc(msgs, t_rx))
                self.gcs.link.open(self.loop, self.gcs.from_gcs)
            except OSError as exc:  # (MavLink.open: one sentence naming the link and its URL)
                raise StartupError(str(exc)) from None
            if self.plans.plan is not None:
                import zenoh

                try:
                    self.open_plan()
                except zenoh.ZError as exc:  # e.g. a port to listen on that is taken
                    raise StartupError(f"cannot open the Zenoh session: {exc}") from None
            tasks.append(asyncio.create_task(self._every_second()))
            tasks.append(asyncio.create_task(self._poll_plans()))
            tasks.append(asyncio.create_task(self._mission_task()))
            tasks.append(asyncio.create_task(self.fc.keep_time()))
            await stop.wait()
        finally:  # stop ticking first, then the tasks, then the bus
            for link in (self.fc.link, self.gcs.link):
                link.close()
            self.host.loop_ctl.forget(self)
            start = self.flight.cancel_start()
            if start is not None:
                tasks.append(start)
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            self.gcs.keep_signing_streams()
            if not await asyncio.to_thread(self.store.close):
                self.log.warning("the state folder did not take the newest state within 5 s of the stop")
            if self.bus is not None and self.bus.is_open:
                self.bus.leave(self.id)
        return self.stats()

    def _warn_from_thread(self, text: str) -> None:
        """``warn`` from another thread (the state's writer): on the loop, while it runs."""
        try:
            self.loop.call_soon_threadsafe(self.warn, text)
        except RuntimeError:  # (the loop is closed: the log keeps it)
            self.log.warning(text)

    async def _mission_task(self) -> None:
        try:
            await self._mission()
        except Exception as exc:  # the mission stops; the companion keeps routing and reporting
            if isinstance(exc, AutopilotError):  # (the flight controller cannot be flown as it is: said)
                self.log.warning(f"mission stopped: {exc}")
            else:
                self.log.exception("mission stopped")
            self.say(f"mission stopped: {exc}", mavlink.MAV_SEVERITY_ERROR)

    async def _setup_fc(self) -> None:
        """Set the flight controller up (``Autopilot.setup``) and run at the rate it sends at."""
        af = self.plans.plan.airframe if self.plans.plan is not None else TABLE_1
        rate_hz = await self.fc.setup(self.rate_hz, self.heartbeat,
                                             (af.max_rotor_speed_rad_s * 30.0 / math.pi, math.degrees(af.servo_limit_rad)),
                                             self.say)
        if rate_hz != self.rate_hz:
            self.set_rate(rate_hz)
        if self.bus is not None and self.lockstep:
            self.bus.reliable_estimates()
        await self._ask_accelerometer()

    async def _ask_accelerometer(self) -> None:
        """The flight controller's accelerometer stream, once set up, if the plan in force takes it
        (``Plan.controller_accelerometer``); a plan that does not costs its line nothing."""
        plan = self.plans.plan
        if plan is None or not self.fc.ready or not plan.controller_accelerometer(plan.wind):
            return
        try:
            await self.fc.ask_accelerometer(self.rate_hz)
        except TimeoutError:
            self.warn("the flight controller did not answer the request for its accelerometer: the observer "
                      "runs on what comes")

    async def _mission(self) -> None:
        await self._setup_fc()
        m = self.plans.mission
        if m is None:
            self.log.info(f"agent {self.id}: no plan; waiting for one")
            return
        now = self.fc.now_unix()
        if m.phase in ("flying", "landing") and m.start_unix_s is not None and m.start_unix_s <= now:
            self.say("resuming plan after restart")
            await self.flight.resume()
            return
        if self.opts.autostart and m.phase != "done":
            problem = self.start_clock_problem()
            if problem:
                self.say(f"plan start refused: {problem}", mavlink.MAV_SEVERITY_ERROR)
                return
            self.plans.schedule_at(self.opts.start_at or default_start_time(now))
        if m.phase == "scheduled":
            self.flight.schedule()

    async def _poll_plans(self) -> None:
        while True:
            self.plan_server.poll(time.monotonic())
            await asyncio.sleep(0.1)

    async def _every_second(self) -> None:
        while True:
            self.watch_fc()
            self.tell_others()
            if self.bus is not None and self.lockstep and self.id in self.bus.members:
                self.bus.republish(self.id, REPUBLISH_AFTER_S)
            hb = self.heartbeat()
            for link in (self.fc.link, self.gcs.link):
                link.send(hb)
            self.gcs.tell_refusals()
            self.gcs.tell_floods()
            self.gcs.keep_signing_streams()
            if self.bus is not None:
                report = self.health_report()
                self.bus.publish_health(self.id, report)
                self.publish_status()  # (whole again each second: a put may be lost on the way)
                self.gcs.health_values(report)
            await asyncio.sleep(1.0)

    def start_clock_problem(self) -> str | None:
        """Why a plan must not start on the flight controller's clock now, or None (its SYSTEM_TIME
        against the companion's clock through TIMESYNC, and the companion's clock's error). Not
        checked with triswarm's simulator, whose clock is its host's, shared with the companions."""
        ap = self.fc
        if ap.simulator:
            return None
        boot = ap.timesync.fc_boot_unix_s()
        fc_minus = None if boot is None or not ap.clock.known else ap.clock.offset_us / 1e6 - boot
        k = self.kernel_clock()
        return start_clock_problem(k.synchronised, k.max_error_s, fc_minus)

    def health_report(self) -> dict:
        now = time.time()
        table = self.bus.estimates
        ages = {j: (now - table[j].stamp_s if table[j].heard else math.inf) for j in sorted(self.listen_to)}
        report = self.health.report(ages)
        heard = self.fc.heard_s
        silent = None if heard is None else round(time.monotonic() - heard, 3)
        report.update(agent=self.id, phase=self.flight.phase.value, alive=sorted(self.bus.alive),
                      counters=self.bus.counts(), links=self.link_counters(), t=now,
                      fc_lost=self.fc_lost_since is not None, fc_silent_s=silent,
                      loop_turns=getattr(self.host.loop, "turns", None),  # (the process's: ``host.CountingLoop``)
                      stalls={"count": self.stalls.count, "longest_s": round(self.stalls.longest_s, 2)},
                      state_write_failures=self.store.failed_writes, gcs_shed=self.gcs.shed_counts(),
                      **self.fc.timesync.report())
        return report

    # -- faults -------------------------------------------------------------------------------------

    def watch_fc(self) -> None:
        """Once a second: a flight controller set up and silent for FC_SILENT_S (while this process
        ran: ``Stalls``) is lost; a lost one heard again is taken back."""
        fc, heard = self.fc, self.fc.heard_s
        now = time.monotonic()
        self.stalls.look(now)
        if heard is None:
            return
        if self.fc_lost_since is None:
            silent = self.stalls.silent_s(heard, now)
            if fc.ready and silent > FC_SILENT_S:
                self.fc_lost(f"nothing heard from it for {silent:.1f} s")
        elif heard > self.fc_lost_since and self._fc_back is None:
            self._fc_back = asyncio.ensure_future(self.take_fc_back())

    def clock_broke(self, s) -> bool:
        """Whether sample ``s`` is not to be flown because it shows the flight controller's clock
        broken: its boot time REBOOT_JUMP_US or more behind the newest (a reboot), or ahead of the
        wall clock's time since by more than CLOCK_JUMP_US. Once CLOCK_BREAK_SAMPLES in a row show
        it over CLOCK_BREAK_S, running on from each other, the agent is lost; a sample on the old
        clock before that drops them as stamps out of place."""
        now = time.monotonic()
        if self.fc_lost_since is not None:
            self._last_boot, self._off_clock = (s.boot_us, now), []
            return False
        reason = None if self._last_boot is None else _clock_break(self._last_boot, s.boot_us, now)
        if reason is None:
            self._last_boot = (s.boot_us, now)
            self._drop_off_clock()
            return False
        if self._off_clock and _clock_break(self._off_clock[-1], s.boot_us, now) is not None:
            self._drop_off_clock()  # (they do not run on to this one: not one new clock)
        self._off_clock.append((s.boot_us, now))
        if len(self._off_clock) >= CLOCK_BREAK_SAMPLES and now - self._off_clock[0][1] >= CLOCK_BREAK_S:
            self._last_boot, self._off_clock = (s.boot_us, now), []
            self.fc_lost(reason)
        return True

    def _drop_off_clock(self) -> None:
        if self._off_clock:
            self.fc.assembler.counters["samples_off_the_clock"] += len(self._off_clock)
            self._off_clock = []

    def fc_lost(self, reason: str) -> None:
        """Command nothing (its own failsafe flies the vehicle) until the flight controller is back."""
        self.fc_lost_since = time.monotonic()
        self.flight.cancel_start()
        text = f"flight controller lost: {reason}"
        self.flight.set_phase(Phase.LOST, text)
        self.say(f"{text}; commanding nothing until it is back", mavlink.MAV_SEVERITY_CRITICAL)

    async def take_fc_back(self) -> None:
        """The flight controller is heard again: it may be another one (a reboot, a simulator
        started again), so it is set up anew (parameters, streams, clock), then the mission
        resumes as after a restart of the companion."""
        fc = self.fc
        try:
            self.say("flight controller heard again: setting it up anew")
            fc.forget()
            self._last_boot, self._off_clock = None, []
            await self._setup_fc()
            self.fc_lost_since = None
            m = self.plans.mission
            if m is not None and m.phase == "flying" and m.start_unix_s is not None:
                self.say("flight controller back: resuming the plan as after a restart")
                self.flight.set_phase(Phase.IDLE, "")
                await self.flight.resume()
            elif m is not None and m.phase == "scheduled":
                self.say("flight controller back: the plan is scheduled again")
                self.flight.schedule()
            else:
                self.say("flight controller back")
                self.flight.set_phase(Phase.IDLE, "")
        except Exception as exc:  # (e.g. it did not answer its set-up): lost again; tried again when heard
            if isinstance(exc, AutopilotError):  # (it cannot be flown as it is: said, no traceback)
                self.log.warning(f"taking the flight controller back failed: {exc}")
            else:
                self.log.exception("taking the flight controller back failed")
            self.fc_lost_since = time.monotonic()
            self.flight.set_phase(Phase.LOST, f"flight controller lost: {exc}")
            self.say(f"flight controller not taken back: {exc}", mavlink.MAV_SEVERITY_ERROR)
        finally:
            self._fc_back = None

    def tell_others(self) -> None:
        """Once a second: say (once each) which agents fly another plan (their estimates are dropped
        and they count as absent), and a step of the flight controller's clock not taken in flight."""
        if self.bus is not None and self.plans.mission is not None:
            for j, (_, plan) in sorted(self.bus.statuses.items()):
                if j != self.id and plan not in self.plans_on_bus and (j, plan) not in self._told_plans:
                    self._told_plans.add((j, plan))
                    other = f"{plan:08x}" if isinstance(plan, int) else repr(plan)
                    self.say(f"agent {j} flies another plan ({other}, not {self.plans.mission.plan_id:08x}): its "
                             f"estimates are dropped and it counts as absent", mavlink.MAV_SEVERITY_WARNING)
        step, told = self.fc.clock.refused_step_us, self._told_clock_step
        if step is not None and (told is None or abs(step - told) > OFFSET_STEP_US):
            self._told_clock_step = step
            self.say(f"the flight controller's Unix time stepped {step / 1e6:+.3f} s in flight: not taken, plan time "
                     f"runs on its boot clock", mavlink.MAV_SEVERITY_WARNING)

    def link_counters(self) -> dict:
        """Each MAVLink link's counters (what it took, dropped and refused, by reason)."""
        return {lk.name: dict(lk.counters) for lk in (self.fc.link, self.gcs.link)}

    def stats(self) -> dict:
        out = {"agent": self.id, "phase": self.flight.phase.value, "loop": self.health.summary(),
               "tick_errors": self.errors, "state_write_failures": self.store.failed_writes,
               "links": self.link_counters(), "fc_clock": self.fc.timesync.report(),
               "missions": dict(self.plan_server.counters), "telemetry": dict(self.fc.assembler.counters)}
        if self.bus is not None:
            out["zenoh"] = self.bus.counts()
        return out


def default_start_time(now: float) -> float:
    """Companions started together agree without talking: the next multiple of 10 s at least 5 s ahead."""
    return math.ceil((now + 5.0) / 10.0) * 10.0


def _clock_break(last: tuple[int, float], boot_us: int, now_s: float) -> str | None:
    """Why a sample stamped ``boot_us`` at ``now_s`` [s, monotonic] breaks the clock of the one
    ``last`` (boot us, monotonic s), or None: back REBOOT_JUMP_US or more (a reboot), or ahead of
    the wall clock's time since by more than CLOCK_JUMP_US."""
    back_us = last[0] - boot_us
    ahead_us = boot_us - last[0] - 1e6 * (now_s - last[1])
    if back_us >= REBOOT_JUMP_US:
        return f"its clock went back {back_us / 1e6:.3f} s (it rebooted)"
    if ahead_us > CLOCK_JUMP_US:
        return f"its clock jumped {ahead_us / 1e6:.3f} s ahead of the wall clock"
    return None
