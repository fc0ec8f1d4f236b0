"""The companion: one drone's formation controller between its flight controller and its neighbours.

One asyncio loop. Every complete telemetry sample from the flight controller (ATTITUDE and
LOCAL_POSITION_NED with the same timestamp, at ``rate_hz``) drives one tick, run in the link's
reader callback:

    1. observe y and predict the state to t_p = t + servo delay (the same FormationController
       as the in-process simulation);
    2. publish xi_i = xhat_i - h_i(t_p) on Zenoh;
    3. wait (at most ``NB_WAIT_MS``; in lockstep until they come) for the in-neighbours'
       estimates for the same t_p (the loop is free meanwhile; an arriving estimate wakes it);
    4. check that a path from the leader remains through the agents that are alive, flying and
       fresh; if not, brake to a hold (and say so) until one returns, then rejoin;
    5. protocol (72) with the neighbours it has, RFL (49), SET_ACTUATOR_CONTROL_TARGET.

Plan time is the flight controller's clock (SYSTEM_TIME) minus the swarm's common start time, and
every wait and timeout of the mission runs on that clock (``clock.py``), so the same code flies on a
simulator's clock in lockstep. There the simulator steps on when the companion has answered each
state, and the wait for neighbours has no wall-clock deadline: only a watchdog of NB_WATCHDOG_S of
wall time counts a neighbour that has stopped publishing (a dead or hung process) as absent.

With a signing key (``--signing-key``), the ground-station link signs every frame the companion
sends and checks every frame it receives (MAVLink 2 signing, ``protocol.mavlink.setup_signing``).
Of the unsigned ones only HEARTBEAT, PARAM_REQUEST_READ and PARAM_REQUEST_LIST pass: they change
nothing, and let a ground station without the key (a monitor) be heard and read parameters. Every
other unsigned frame, and every frame with a wrong signature or a replayed timestamp, is dropped
before routing (so it reaches neither this component nor the flight controller), counted in the
link's counters by reason, and reported to the ground station once a second. Frames forwarded
from the flight controller, whose link is not signed, reach the ground station as they came. With
a state folder, each ground-station stream's last timestamp is kept there (``signing.json``), so a
frame taken before a restart is still a replay after it.
"""

from __future__ import annotations

import asyncio
import enum
import gc
from collections import Counter, deque
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from triswarm.protocol import model
from triswarm.protocol.agent import Reference, no_leader, pinned_input, protocol_input, reference_at
from triswarm.protocol.codec import AgentStatus, plan_id
from triswarm.protocol.controller import FormationController
from triswarm.protocol.airframe import TABLE_1, ParameterError
from triswarm.protocol.formation import (Formation, LeaderMove, QuinticTransfer, RelativeTo, Rejoin, Row, Shifted,
                                         rejoin_duration)
from triswarm.protocol.graph import Topology
from triswarm.protocol.mavlink import (COMP_ONBOARD, CustomMode, attitude_to_paper, encode_actuators, mode_name,
                                       local_ned_to_paper, mavlink, rates_to_paper, read_signing_key, setup_signing)
from triswarm.protocol.plan import (Plan, PlanError, actuator_demand, in_flight_change_problem, plan_from_dict,
                                    spec_from_toml)
from triswarm.protocol.plan_transfer import PlanItem, PlanTransferError, decode_plan, encode_plan

from .bus import Bus, default_config, tune
from .clock import NO_COMMAND, REBOOT_JUMP_MS, Answers, FcClock
from .health import LoopHealth
from .links import MavLink, Router
from .plan_server import PlanServer
from .state import Mission, StateStore

log = logging.getLogger("triswarm.companion")


class StartupError(Exception):
    """The companion cannot start as asked (a link it cannot open, an unreadable signing key, a Zenoh
    session it cannot open): one sentence for the operator, exit status 2."""


class AgentLog(logging.LoggerAdapter):
    """The companion's log, each line naming its agent (several agents may share a process)."""

    def process(self, msg, kwargs):
        prefix = f"companion {self.extra['agent']}: "
        return (msg if str(msg).startswith(prefix) else prefix + str(msg)), kwargs

ARM_LEAD_S = 2.0
START_GRACE_S = 1.0  # after starting to fly, neighbours not yet heard from still count for the path check
IDLE_FRACTION = 0.3  # idle rotor speed on the ground, as a fraction of hover
SWITCH_MAX_JUMP = (5.0, 5.0)  # in flight, a new formation may start this far from the old one [m, m/s]
WARM_UP_PLAN = {"drones": 1, "formation": {"type": "rotating-polygon", "radius_m": 1.0, "altitude_m": 1.0, "rate_rad_s": 0.0}}
LEADER_LATE_S = 2.0  # a leader command may arrive this late for its plan time (the move starts slow)
MOVE_CHECK_STEP_S = 0.05  # a leader move is checked against the airframe's limits this often [s],
MOVE_CHECK_SAMPLES = 100  # or at this many instants over a long move
LOCKSTEP_RECHECK_S = 0.1  # lockstep: while waiting for neighbours, look at who is alive this often [s, wall]
NB_WATCHDOG_S = 3.0  # lockstep: a live neighbour with no estimate for this long has hung [s, wall]
HIGH_RATE = {mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
             mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mavlink.MAVLINK_MSG_ID_ODOMETRY,
             mavlink.MAVLINK_MSG_ID_HIGHRES_IMU}
UNSIGNED_FROM_GCS = frozenset({mavlink.MAVLINK_MSG_ID_HEARTBEAT, mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_READ,
                               mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_LIST})
"""With a signing key: what the ground-station link takes unsigned (see the module's text)."""
GCS_LINK_ID = 1  # the ground-station link's id in the signatures it sends


class Phase(enum.Enum):
    IDLE = "idle"            # no plan running
    SCHEDULED = "scheduled"  # waiting for the common start time (armed shortly before)
    FLYING = "flying"        # in formation (or entering / rejoining it)
    HOLDING = "holding"      # no path to the leader: holding position


PHASE_MODE = {Phase.IDLE: 0, Phase.SCHEDULED: 1, Phase.FLYING: 2, Phase.HOLDING: 3}
PHASE_STATUS = {Phase.IDLE: AgentStatus.IDLE, Phase.SCHEDULED: AgentStatus.IDLE, Phase.FLYING: AgentStatus.FLYING,
                Phase.HOLDING: AgentStatus.HOLDING}
"""What the bus says of each phase."""


@dataclass(frozen=True)
class CompanionOptions:
    agent: int
    fc_url: str
    gcs_url: str
    plan_path: Path | None = None
    autostart: bool = False
    start_at_unix_s: float | None = None
    zenoh_config: Path | None = None
    zenoh_listen: tuple[str, ...] = ()
    zenoh_connect: tuple[str, ...] = ()
    zenoh_mode: str = "peer"
    zenoh_base_port: int = 17447
    rate_hz: float = 200.0
    state_dir: Path | None = None
    swarm: str | None = None
    stats_path: Path | None = None
    signing_key_path: Path | None = None


@dataclass
class ParamSpec:
    default: float
    lo: float
    hi: float
    read_only: bool = False


_PLANS: dict[tuple, Plan] = {}


def load_plan_file(path: Path) -> Plan:
    """The plan in a file. The agents of one process that fly the same file share one ``Plan`` (its
    design is computed once, its formation evaluated once per instant for all of them)."""
    try:
        st = Path(path).stat()
        key = (str(Path(path).resolve()), st.st_mtime_ns, st.st_size)
        if key in _PLANS:
            return _PLANS[key]
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise PlanError(f"{path}: no such plan file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise PlanError(f"{path}: cannot read the plan file ({exc.__class__.__name__})") from None
    plan = _PLANS[key] = plan_from_dict(spec_from_toml(text, str(path)), str(path))
    return plan


def leader_with_moves(leader: Formation, moves: list[dict]) -> Formation:
    """The plan's leader after the operator's leader commands, in order."""
    for m in moves:
        leader = LeaderMove(leader, m["at_s"], m["target_m"] and tuple(m["target_m"]), m["yaw_rad"], m["speed_m_s"])
    return leader


@dataclass
class Sample:
    t_rx: float          # Unix time the datagram arrived (kernel receive time on UDP)
    boot_ms: int         # flight controller time of the sample
    eta: np.ndarray      # paper frame
    rates: np.ndarray
    position: np.ndarray
    velocity_e: np.ndarray


@dataclass
class _Waiting:
    """A tick between its two halves: waiting for the neighbours' estimates."""
    sample: Sample
    xhat: np.ndarray
    xi: np.ndarray
    ref: Reference
    topo: Topology
    expected: list[int]
    t_plan: float
    since_wall: float = 0.0


@dataclass
class FcState:
    heard: bool = False
    armed: bool = False
    mode: int = 0
    landed: bool = True
    max_rpm: float | None = None
    servo_deg: float | None = None
    att: tuple | None = None             # (boot_ms, eta, rates)
    pending: dict = field(default_factory=dict)


def zenoh_config(o: CompanionOptions, agents: frozenset[int], n_agents: int):
    """The Zenoh configuration of a process flying ``agents``: the file, the endpoints given, or
    peers on loopback (``bus.default_config``)."""
    import zenoh

    if o.zenoh_config is not None:
        try:
            return tune(zenoh.Config.from_file(str(o.zenoh_config)))
        except Exception as exc:  # zenoh raises its own error type for a bad file
            raise PlanError(f"{o.zenoh_config}: not a usable Zenoh configuration ({exc})") from None
    if o.zenoh_listen or o.zenoh_connect:
        from .bus import peer_config

        return peer_config(list(o.zenoh_listen), list(o.zenoh_connect), o.zenoh_mode)
    return default_config(agents, n_agents, o.zenoh_base_port)


class Companion:
    def __init__(self, opts: CompanionOptions, shared_zenoh=None) -> None:
        """``shared_zenoh``: the process's ``host.SharedZenoh`` when several agents share one."""
        self.opts = opts
        self.shared_zenoh = shared_zenoh
        self.agent = opts.agent
        self.log = AgentLog(log, {"agent": opts.agent})
        try:
            self.signing_key = None if opts.signing_key_path is None else read_signing_key(opts.signing_key_path)
        except ValueError as exc:  # (one sentence: the file and what is wrong with it)
            raise StartupError(str(exc)) from None
        self._refusals_told: Counter[str] = Counter()
        self._signing_kept: dict[str, int] = {}  # the signing streams as last saved
        self.store = StateStore(opts.state_dir)
        self.fc = FcState()
        self.clock = FcClock()
        self.answers = Answers(lambda frame: self.fc_link.write(frame))
        self._silent: dict[int, float] = {}
        """Lockstep: the neighbours the watchdog counts absent, each with the instant [plan s] it had no
        estimate for; absent until one for that instant or a later one comes."""
        self._presence_base: tuple | None = None
        self.health = LoopHealth(1.0 / opts.rate_hz)
        self.params = {
            "CTRL_RATE_HZ": ParamSpec(opts.rate_hz, 1.0, 2000.0, read_only=True),  # control (telemetry) rate
            "NB_TIMEOUT_S": ParamSpec(0.2, 0.01, 10.0),  # a neighbour's estimate older than this: absent [s]
            "NB_WAIT_MS": ParamSpec(1.0, 0.0, 4.0),      # longest wait for the neighbours' estimates [ms]
            "REJOIN_S": ParamSpec(1.0, 0.2, 60.0),       # shortest way back into the formation [s]
            "REJOIN_ACCEL": ParamSpec(4.0, 0.5, 20.0),   # peak acceleration on the way back [m/s^2]
            "GCS_TLM_HZ": ParamSpec(20.0, 0.0, 1000.0),  # high-rate telemetry forwarded to the GCS [Hz]
            "PLAN_T_S": ParamSpec(math.nan, -math.inf, math.inf, read_only=True),  # plan time when read [s]
        }
        self.values = {k: p.default for k, p in self.params.items()}
        self.phase = Phase.IDLE
        self._phase_reason, self._phase_since = "", time.time()  # why and since when [Unix s, the fc's clock]
        self.mission: Mission | None = None
        self.plan: Plan | None = None
        self.leader: Formation | None = None  # the plan's leader x0 with the operator's moves
        self.staged: tuple[Plan, int] | None = None  # received, valid, waiting for its start command
        self._start_task: asyncio.Task | None = None
        self._statustext_id = 0
        omega, alpha = model.hover_trim(TABLE_1)  # until a plan names the airframe
        self._idle = (omega * IDLE_FRACTION, alpha)
        self._queue: deque[Sample] = deque(maxlen=50)
        self._gcs_last: dict[int, float] = {}
        self._errors = 0
        self._flying_since = -math.inf
        self._t_p = -math.inf
        self._waiting: _Waiting | None = None
        self._flying: Formation | None = None  # the formation being flown (the entry first)
        self.formation: Formation | None = None  # the plan's formation, from its own start
        self._tracking: Formation | None = None  # what this drone's reference follows now (entry, rejoin, ...)
        self._switch: tuple[Plan, int, float] | None = None  # a plan to put in force in flight, and when
        self._deadline: asyncio.TimerHandle | None = None

    # -- plan ---------------------------------------------------------------------------------

    def load_mission(self) -> None:
        """A saved mission (resumed after a restart) wins over a plan file with the same plan, and
        over any plan file in the middle of a flight (the plan may have changed in the air)."""
        saved = self.store.load()
        if self.store.problem:
            self.log.warning(self.store.problem)
        plan_file = load_plan_file(self.opts.plan_path) if self.opts.plan_path else None
        if saved is not None and saved.agent == self.agent and (plan_file is None or saved.phase == "flying"
                                                                or plan_id(plan_file.spec) == saved.plan_id):
            self.mission = saved
            self.plan = plan_from_dict(saved.plan_spec, f"{self.store.path}")
        elif plan_file is not None:
            self.plan = plan_file
            self.mission = Mission(plan_file.spec, plan_id(plan_file.spec), self.agent)
        if self.plan is not None and not 1 <= self.agent <= self.plan.n_agents:
            raise PlanError(f"agent {self.agent} is not in plan {self.plan.name} ({self.plan.n_agents} drones)")
        if self.plan is not None:
            self._plan_in_force()

    def _plan_in_force(self) -> None:
        m = self.mission
        self.leader = leader_with_moves(self.plan.leader, m.leader_moves)
        self.formation = Shifted(self.plan.formation, m.formation_shift_s) if m.formation_shift_s else self.plan.formation
        if m.next_plan is not None:
            nxt = m.next_plan
            self._switch = (plan_from_dict(nxt["spec"], f"{self.store.path}"), nxt["plan_id"], nxt["at_unix_s"])
        self.values["COUPLING_C"] = self.plan.design.c
        self.params["COUPLING_C"] = ParamSpec(self.plan.design.c, 0.0, 1e9, read_only=True)

    def _leader_state(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        h, h_dot = self.leader.offsets(t_s)
        return h[0], h_dot[0]

    def _held_items(self) -> list[PlanItem]:
        """What a download gets: the plan in force, or before any, the one waiting for its start."""
        spec = self.plan.spec if self.plan is not None else self.staged[0].spec if self.staged else None
        if spec is None:
            return []
        if getattr(self, "_items", (None,))[0] is not spec:
            self._items = (spec, encode_plan(spec))
        return self._items[1]

    def _receive_plan(self, items: list[PlanItem]) -> tuple[int, str] | asyncio.Future:
        """A whole mission came: check it as `plan check` does (but the flight); stage it if it
        passes. The check runs off the loop (at 200 drones it takes longer than the flight
        controller's failsafe would wait for the next command): the answer is a future."""
        try:
            spec, pid = decode_plan(items)
            plan = plan_from_dict(spec, "uploaded plan")
            if not 1 <= self.agent <= plan.n_agents:
                raise PlanError(f"uploaded plan: agent {self.agent} is not in it ({plan.n_agents} drones)")
        except PlanTransferError as exc:
            return exc.ack_code, f"plan refused: {exc}"
        except (PlanError, ParameterError, ValueError) as exc:
            return mavlink.MAV_MISSION_INVALID, f"plan refused: {exc}"
        answer = self.loop.create_future()

        def checked(done: asyncio.Future) -> None:
            exc = done.exception()
            if isinstance(exc, (PlanError, ParameterError, ValueError)):
                answer.set_result((mavlink.MAV_MISSION_INVALID, f"plan refused: {exc}"))
            elif exc is not None:  # a bug, shown as one
                self.log.error("plan check failed", exc_info=exc)
                answer.set_result((mavlink.MAV_MISSION_ERROR, f"plan check failed: {exc.__class__.__name__}: {exc}"))
            else:
                self.staged = (plan, pid)
                answer.set_result((mavlink.MAV_MISSION_ACCEPTED, f"plan {plan.name} {pid:08x} received; waiting for its start"))

        self.loop.run_in_executor(None, plan.check).add_done_callback(checked)
        return answer

    def _clear_plans(self) -> tuple[int, str]:
        if self.phase in (Phase.FLYING, Phase.HOLDING):
            return mavlink.MAV_MISSION_DENIED, "clear refused: flying; land first"
        self.staged = None
        if self._start_task is not None:
            self._start_task.cancel()
        self.plan = self.mission = self.leader = None
        self.store.clear()
        self._set_phase(Phase.IDLE, "")
        return mavlink.MAV_MISSION_ACCEPTED, "plans cleared"

    def _start_plan(self, pid: int, start_unix_s: float) -> tuple[int, str]:
        """MAV_CMD_TRISWARM_PLAN_START: the staged plan (or the one in force, again) from a
        common start time."""
        m = self.mission
        if m is not None and m.plan_id == pid and m.start_unix_s == start_unix_s and m.phase != "done":
            return mavlink.MAV_RESULT_ACCEPTED, ""  # a retry of the same command
        if not (math.isfinite(start_unix_s) and start_unix_s > self.clock.now() - 1.0):
            return mavlink.MAV_RESULT_DENIED, "plan start refused: the start time has passed"
        if self.staged is not None and self.staged[1] == pid:
            plan = self.staged[0]
        elif m is not None and m.plan_id == pid:
            plan = self.plan
        else:
            return mavlink.MAV_RESULT_DENIED, f"plan start refused: no plan {pid:08x} here; upload it first"
        if self.phase in (Phase.FLYING, Phase.HOLDING):
            return self._plan_next(plan, pid, start_unix_s)
        reopen = m is None or m.plan_id != pid or not hasattr(self, "bus")
        self.staged = None
        self.plan, self.mission = plan, Mission(plan.spec, pid, self.agent, start_unix_s, "scheduled")
        self.store.save(self.mission)
        self._plan_in_force()
        if reopen:
            if hasattr(self, "bus"):
                self.bus.close()
            self._open_bus(self.loop)
        self._schedule()
        return mavlink.MAV_RESULT_ACCEPTED, f"plan {plan.name} starts at {start_unix_s:.1f}"

    def _plan_next(self, plan: Plan, pid: int, at_unix_s: float) -> tuple[int, str]:
        """In flight: the new plan takes over at at_unix_s if it changes only the formation."""
        m = self.mission
        if m.next_plan is not None and (m.next_plan["plan_id"], m.next_plan["at_unix_s"]) == (pid, at_unix_s):
            return mavlink.MAV_RESULT_ACCEPTED, ""  # a retry
        problem = in_flight_change_problem(self.plan.spec, plan.spec) or self._switch_jump(plan, at_unix_s)
        if problem:
            return mavlink.MAV_RESULT_DENIED, f"plan start refused: {problem}"
        self.staged = None
        self._switch = (plan, pid, at_unix_s)
        m.next_plan = {"spec": plan.spec, "plan_id": pid, "at_unix_s": at_unix_s}
        self.store.save(m)
        return mavlink.MAV_RESULT_ACCEPTED, f"plan {plan.name} takes over at {at_unix_s:.1f}"

    def _switch_jump(self, plan: Plan, at_unix_s: float) -> str | None:
        """Whether the new formation at its t = 0 is near the old one at that time, for every drone
        (the same answer on every companion: both are the plans', not this drone's)."""
        old, old_dot = self.formation.offsets(at_unix_s - self.mission.start_unix_s)
        new, new_dot = plan.formation.offsets(0.0)
        dp = float(np.max(np.linalg.norm(old[:, 9:12] - new[:, 9:12], axis=1)))
        dv = float(np.max(np.linalg.norm(old_dot[:, 9:12] - new_dot[:, 9:12], axis=1)))
        if dp > SWITCH_MAX_JUMP[0] or dv > SWITCH_MAX_JUMP[1]:
            return (f"at that time the new formation starts {dp:.1f} m and {dv:.1f} m/s from the old one (at most "
                    f"{SWITCH_MAX_JUMP[0]:g} m, {SWITCH_MAX_JUMP[1]:g} m/s): start it where the two meet")
        return None

    def _switch_plan(self, t_plan: float) -> None:
        """Put the next plan in force, here in flight: its formation starts now (its t = 0), the
        swarm's plan time, graphs and leader run on, and the reference leaves the old formation
        for the new one as a rejoin does (the error decays)."""
        plan, pid, at_unix_s = self._switch
        self._switch = None
        m = self.mission
        m.plan_spec, m.plan_id, m.next_plan = plan.spec, pid, None
        m.formation_shift_s = at_unix_s - m.start_unix_s
        self.store.save(m)
        self.plan = plan
        self._plan_in_force()
        self.bus.switch_plan(pid)
        self._flying = self._mine(self.formation)
        self.statustext(f"companion {self.agent}: plan {plan.name} {pid:08x} in force")
        if self.phase == Phase.FLYING:
            self._rejoin(t_plan, self._tracking)

    def _leader_command(self, msg) -> tuple[int, str]:
        """MAV_CMD_TRISWARM_LEADER_GOTO / _HOLD: a move of x0 from a plan time common to the swarm."""
        m = self.mission
        if m is None or m.start_unix_s is None:
            return mavlink.MAV_RESULT_DENIED, "leader command refused: no plan in force"
        at_s = float(msg.param3)
        if not (math.isfinite(at_s) and at_s >= self.clock.now() - m.start_unix_s - LEADER_LATE_S):
            return mavlink.MAV_RESULT_DENIED, f"leader command refused: plan time {at_s:.2f} s has passed"
        if msg.command == mavlink.MAV_CMD_TRISWARM_LEADER_GOTO:
            if msg.get_type() == "COMMAND_INT":
                target = [msg.x / 1000.0, msg.y / 1000.0, float(msg.z)]
            else:
                target = [float(msg.param5), float(msg.param6), float(msg.param7)]
            yaw = None if math.isnan(msg.param2) else float(msg.param2)
            move = {"at_s": at_s, "target_m": target, "yaw_rad": yaw, "speed_m_s": float(msg.param1)}
        else:
            move = {"at_s": at_s, "target_m": None, "yaw_rad": None, "speed_m_s": 1.0}
        if move in m.leader_moves:
            return mavlink.MAV_RESULT_ACCEPTED, ""  # a retry
        if m.leader_moves and at_s < m.leader_moves[-1]["at_s"]:
            return mavlink.MAV_RESULT_DENIED, "leader command refused: older than the last one"
        try:
            leader = leader_with_moves(self.leader, [move])
        except ParameterError as exc:
            return mavlink.MAV_RESULT_DENIED, f"leader command refused: {exc}"
        # the formation about the moving leader, through the move, against the airframe's limits
        # (at most MOVE_CHECK_SAMPLES instants: a few milliseconds of the loop, once per command)
        end_s = max(leader.end_s, at_s)
        step_s = max(MOVE_CHECK_STEP_S, (end_s - at_s) / MOVE_CHECK_SAMPLES)
        times = np.arange(at_s, end_s + step_s, step_s)
        problem = actuator_demand(self.plan.rfl, leader, self.formation, times).problem(self.plan.airframe)
        if problem is not None:
            return mavlink.MAV_RESULT_DENIED, f"leader command refused: the move cannot be flown: {problem}"
        self.leader = leader
        m.leader_moves.append(move)
        self.store.save(m)
        what = "hold" if move["target_m"] is None else "goto " + " ".join(f"{v:.1f}" for v in move["target_m"])
        return mavlink.MAV_RESULT_ACCEPTED, f"leader {what} at t {at_s:.1f} s"

    # -- run ----------------------------------------------------------------------------------

    async def run(self, stop: asyncio.Event) -> dict:
        loop = asyncio.get_running_loop()
        self.loop = loop
        self.load_mission()
        if self.plan is None:  # the kernels now, not when a plan starts (a first compile takes seconds)
            FormationController.warm_up(plan_from_dict(WARM_UP_PLAN).design, self.opts.rate_hz)
        self.fc_link = MavLink("fc", self.opts.fc_url, self.agent, COMP_ONBOARD)
        self.gcs_link = MavLink("gcs", self.opts.gcs_url, self.agent, COMP_ONBOARD)
        if self.signing_key is not None:
            setup_signing(self.gcs_link.codec, self.signing_key, GCS_LINK_ID, UNSIGNED_FROM_GCS.__contains__,
                          self.gcs_link.counters)
            self._restore_signing_streams()
        self.links = [self.fc_link, self.gcs_link]
        self.router = Router(self.agent, COMP_ONBOARD)
        self.plans = PlanServer(self._receive_plan, self._clear_plans, self._held_items, self._say)
        tasks: list[asyncio.Task] = []
        try:
            try:
                self.fc_link.open(loop, self._on_fc)
                self.gcs_link.open(loop, self._on_gcs)
            except OSError as exc:  # (MavLink.open: one sentence naming the link and its URL)
                raise StartupError(str(exc)) from None
            if self.plan is not None:
                import zenoh

                try:
                    self._open_bus(loop)
                except zenoh.ZError as exc:  # e.g. a port to listen on that is taken
                    raise StartupError(f"cannot open the Zenoh session: {exc}") from None
            self.fc_link.after_read = self._process_samples
            tasks.append(asyncio.create_task(self._every_second()))
            tasks.append(asyncio.create_task(self._poll_plans()))
            tasks.append(asyncio.create_task(self._mission_task()))
            await stop.wait()
        finally:  # stop ticking first, then the tasks, then the bus
            for link in self.links:
                link.close()
            if self._deadline is not None:
                self._deadline.cancel()
            self._waiting = None
            if self._start_task is not None:
                tasks.append(self._start_task)
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            self._keep_signing_streams()
            if hasattr(self, "bus"):
                self.bus.close()
        return self.stats()

    def _restore_signing_streams(self) -> None:
        """The ground station's signing streams as they were before a restart: a frame captured
        before it stays a replay after it (a new stream alone would take any frame up to a minute
        old, as the specification allows)."""
        saved = self.store.load_signing_streams()
        if self.store.problem:
            self.log.warning(self.store.problem)
            self.store.problem = None
        taken = self.gcs_link.codec.signing.restore(saved)
        if taken:
            self.log.info(f"signing: {taken} ground-station stream(s) taken up where they were")
        self._signing_kept = self.gcs_link.codec.signing.streams()

    def _keep_signing_streams(self) -> None:
        """Save the signing streams if they moved (once a second at most, from ``_every_second``)."""
        if self.signing_key is None:
            return
        streams = self.gcs_link.codec.signing.streams()
        if streams != self._signing_kept:
            try:
                self.store.save_signing_streams(streams)
                self._signing_kept = streams
            except OSError as exc:
                self.log.warning(f"signing streams not saved: {exc}")

    def _open_bus(self, loop) -> None:
        plan = self.plan
        i = self.agent - 1
        listen_to = frozenset(int(j) + 1 for t in plan.schedule.topologies for j in t.in_neighbours(i))
        swarm = self.opts.swarm or plan.name
        self.bus = Bus(swarm, self.agent, self.mission.plan_id, listen_to, plan.n_agents, reliable=self.answers.lockstep)
        self.bus.on_estimate = self._on_estimate
        self.bus.open(self._zenoh(plan.n_agents), loop)
        self._design = plan.design
        self._in_neighbours = {t.name: [int(j) + 1 for j in t.in_neighbours(i)] for t in plan.schedule.topologies}
        self._in_weights = {t.name: [(j, float(t.adjacency[i, j - 1])) for j in self._in_neighbours[t.name]]
                            for t in plan.schedule.topologies}
        self._paths: dict[tuple, bool] = {}
        self._presence_base = None
        self.ctrl = FormationController(self._design, 1, self.opts.rate_hz,
                                        thrust_adaptation_rate_1_s=plan.controller.thrust_adaptation_rate_1_s)
        omega, alpha = model.hover_trim(plan.airframe)
        self._idle = (omega * IDLE_FRACTION, alpha)
        FormationController.warm_up(self._design, self.opts.rate_hz)
        self.bus.publish_status(AgentStatus.IDLE)

    def _zenoh(self, n_agents: int):
        """This agent's Zenoh session (shared with the process's other agents), or its config."""
        if self.shared_zenoh is not None:
            return self.shared_zenoh.session(n_agents)
        return zenoh_config(self.opts, frozenset({self.agent}), n_agents)

    # -- the flight controller ----------------------------------------------------------------

    def _on_fc(self, link: MavLink, msgs: list, t_rx: float) -> None:
        for msg in msgs:
            self.router.learn(link, msg)
            mine = self.router.for_me(msg)
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            if src == (self.agent, mavlink.MAV_COMP_ID_AUTOPILOT1):
                self._fc_message(msg, t_rx)
            for dest in self.router.destinations(link, msg, self.links):
                if dest is self.gcs_link and not self._gcs_rate_ok(msg):
                    continue
                dest.write(msg.get_msgbuf())
            if mine and src[0] != self.agent:
                self._handle_for_me(link, msg)

    def _gcs_rate_ok(self, msg) -> bool:
        """High-rate telemetry reaches the ground station at GCS_TLM_HZ at most."""
        mid = msg.get_msgId()
        if mid not in HIGH_RATE:
            return True
        rate = self.values["GCS_TLM_HZ"]
        if rate <= 0:
            return False
        now = time.monotonic()
        if now - self._gcs_last.get(mid, -math.inf) < 1.0 / rate:
            return False
        self._gcs_last[mid] = now
        return True

    def _fc_message(self, msg, t_rx: float) -> None:
        fc = self.fc
        t = msg.get_type()
        if t == "HEARTBEAT":
            fc.heard = True
            fc.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            fc.mode = msg.custom_mode
            if self.phase in (Phase.FLYING, Phase.HOLDING):
                if not fc.armed:
                    self._release("disarmed")
                elif fc.mode != CustomMode.EXTERNAL and msg.system_status != mavlink.MAV_STATE_CRITICAL:
                    self._release(f"the flight controller is in {mode_name(fc.mode)}")
        elif msg.get_msgId() in HIGH_RATE:
            boot_ms = msg.time_boot_ms if hasattr(msg, "time_boot_ms") else msg.time_usec // 1000
            self.answers.telemetry(boot_ms)
            if t == "ATTITUDE":
                fc.att = (msg.time_boot_ms, attitude_to_paper(msg.roll, msg.pitch, msg.yaw),
                          rates_to_paper(msg.rollspeed, msg.pitchspeed, msg.yawspeed))
            elif t == "LOCAL_POSITION_NED" and fc.att is not None and fc.att[0] == msg.time_boot_ms:
                last = getattr(self, "_last_sample", None)
                if last is not None and 0 <= last.boot_ms - msg.time_boot_ms < REBOOT_JUMP_MS:
                    return  # the same state again (a lockstep simulator's re-send): one tick each
                self._sample(Sample(t_rx, msg.time_boot_ms, fc.att[1], fc.att[2],
                                    local_ned_to_paper(msg.x, msg.y, msg.z), local_ned_to_paper(msg.vx, msg.vy, msg.vz)))
        elif t == "SYSTEM_TIME":
            if msg.time_unix_usec > 0:
                self.clock.set_offset(msg.time_unix_usec, msg.time_boot_ms)
        elif t == "EXTENDED_SYS_STATE":
            fc.landed = msg.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
        elif t == "COMMAND_ACK":
            fut = fc.pending.pop(("ack", msg.command), None)
            if fut is not None and not fut.done():
                fut.set_result(msg.result)
        elif t == "PARAM_VALUE":
            fut = fc.pending.pop(("param", msg.param_id), None)
            if fut is not None and not fut.done():
                fut.set_result(msg.param_value)

    async def _fc_request(self, key, send, timeout_s: float = 0.5, tries: int = 6):
        for _ in range(tries):
            fut = self.loop.create_future()
            self.fc.pending[key] = fut
            send()
            try:
                return await asyncio.wait_for(fut, timeout_s)
            except asyncio.TimeoutError:
                continue
        raise TimeoutError(f"flight controller did not answer {key}")

    async def fc_command(self, command: int, *params: float) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        return await self._fc_request(("ack", command), lambda: self.fc_link.send(
            mavlink.MAVLink_command_long_message(self.agent, 1, command, 0, *p)))

    async def fc_param(self, name: str) -> float:
        return await self._fc_request(("param", name), lambda: self.fc_link.send(
            mavlink.MAVLink_param_request_read_message(self.agent, 1, name.encode(), -1)))

    async def setup_fc(self) -> None:
        """Wait for the flight controller, learn its actuator scaling, ask for the telemetry."""
        while not self.fc.heard:
            self.fc_link.send(self._heartbeat())
            await asyncio.sleep(0.2)
        self.fc.max_rpm = await self.fc_param("MOT_MAX_RPM")
        self.fc.servo_deg = await self.fc_param("SERVO_LIM_DEG")
        try:
            self.answers.lockstep = await self.fc_param("SIM_LOCKSTEP") == 1.0
        except TimeoutError:  # an autopilot, not triswarm's simulator
            self.answers.lockstep = False
        if self.answers.lockstep:
            self.log.info("the flight controller is a simulator in lockstep: every state is answered")
            if hasattr(self, "bus"):
                self.bus.reliable_estimates()
        interval = 1e6 / self.opts.rate_hz
        for msg_id, us in ((mavlink.MAVLINK_MSG_ID_ATTITUDE, interval), (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, interval),
                           (mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, -1), (mavlink.MAVLINK_MSG_ID_ODOMETRY, -1),
                           (mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, -1), (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, 1e6)):
            await self.fc_command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, us)
        await self.fc_command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_SYSTEM_TIME)
        while not self.clock.known:
            await asyncio.sleep(0.05)
        # Set up and about to fly: keep the start-up objects out of every later garbage collection,
        # which would otherwise stall the loop for tens of milliseconds at a time.
        gc.collect()
        gc.freeze()

    def fc_unix(self, boot_ms: int) -> float:
        """The flight controller's time of a sample, as Unix time (its SYSTEM_TIME clock)."""
        return self.clock.unix(boot_ms)

    # -- the mission --------------------------------------------------------------------------

    async def _mission_task(self) -> None:
        try:
            await self._mission()
        except Exception as exc:  # the mission stops; the companion keeps routing and reporting
            self.log.exception("mission stopped")
            self.statustext(f"companion {self.agent}: mission stopped: {exc}"[:50], mavlink.MAV_SEVERITY_ERROR)

    async def _mission(self) -> None:
        await self.setup_fc()
        m = self.mission
        if m is None:
            self.log.info(f"agent {self.agent}: no plan; waiting for one")
            return
        now = self.clock.now()
        if m.phase == "flying" and m.start_unix_s is not None and m.start_unix_s <= now:
            self.statustext(f"companion {self.agent}: resuming plan after restart")
            await self._resume()
            return
        if self.opts.autostart and m.phase != "done":
            m.start_unix_s = self.opts.start_at_unix_s or default_start_time(now)
            m.phase = "scheduled"
            self.store.save(m)
        if m.phase == "scheduled":
            self._schedule()

    def _schedule(self) -> None:
        """Fly the plan in force from its start time (after the flight controller is set up)."""
        if self._start_task is not None:
            self._start_task.cancel()
        self._set_phase(Phase.SCHEDULED, "")
        self._start_task = asyncio.ensure_future(self._start_when_due())

    async def _start_when_due(self) -> None:
        m = self.mission
        try:
            while not self.clock.known or self.fc.max_rpm is None:  # setup_fc is still running
                await asyncio.sleep(0.05)
            if self.opts.autostart:  # (a start command has its answer already)
                self.statustext(f"companion {self.agent}: plan {self.plan.name} starts at {m.start_unix_s:.1f}")
                if self.clock.now() > m.start_unix_s - ARM_LEAD_S:
                    self.statustext(f"companion {self.agent}: ready {self.clock.now() - m.start_unix_s + ARM_LEAD_S:.1f} s "
                                    f"late for the start", mavlink.MAV_SEVERITY_WARNING)
                await self.clock.until(m.start_unix_s - ARM_LEAD_S)
                await self._arm()
            await self.clock.until(m.start_unix_s)
            if not self.fc.armed:
                self.statustext(f"companion {self.agent}: start time reached; waiting to be armed")
                while not self.fc.armed:
                    await asyncio.sleep(0.05)
            if self.fc.mode != CustomMode.EXTERNAL:  # e.g. hovering after the operator's takeoff
                result = await self.fc_command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                                               CustomMode.EXTERNAL)
                if result != mavlink.MAV_RESULT_ACCEPTED:
                    raise RuntimeError(f"the flight controller refused external control ({result})")
                self.fc.mode = CustomMode.EXTERNAL
            self._begin_entry(max(0.0, self._plan_time(self._last_sample)))
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # the plan does not start; the companion keeps routing and reporting
            self.log.exception("plan start failed")
            self._set_phase(Phase.IDLE, "")
            self.statustext(f"companion {self.agent}: plan not started: {exc}", mavlink.MAV_SEVERITY_ERROR)

    def _release(self, reason: str) -> None:
        """The flight controller took the vehicle back (the operator's land or hold, a disarm):
        this flight of the plan is over."""
        self.mission.phase = "done"
        self.store.save(self.mission)
        self._set_phase(Phase.IDLE, "")
        self.statustext(f"companion {self.agent}: formation flight over: {reason}", mavlink.MAV_SEVERITY_WARNING)

    async def _arm(self) -> None:
        result = await self.fc_command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            self.statustext(f"companion {self.agent}: the flight controller refused to arm ({result})")
            raise RuntimeError("arming refused")

    def _current_state(self) -> np.ndarray | None:
        s = getattr(self, "_last_sample", None)
        if s is None:
            return None
        R = model.rotation_body_to_earth(s.eta)
        return np.concatenate([R.T @ s.velocity_e, s.rates, s.eta, s.position])

    def _begin_entry(self, t0_s: float) -> None:
        """Take off from where the drone rests and enter the formation (the plan's entry) from plan
        time ``t0_s``."""
        x = self._current_state()
        self.ctrl.reset(x[None, :])
        m = self.mission
        m.phase = "flying"
        self.store.save(m)
        self._flying = self._tracking = self.plan.entry_formation(x[None, 9:12], t0_s, self._mine(self.formation))
        self._set_phase(Phase.FLYING, "")

    async def _resume(self) -> None:
        """After a restart: join the formation again from wherever the vehicle is."""
        while self._current_state() is None:
            await asyncio.sleep(0.05)
        if not self.fc.armed or self.fc.landed:
            if not self.fc.armed:
                await self._arm()
            self._begin_entry(self._plan_time(self._last_sample) + 1.0)
            return
        x = self._current_state()
        self.ctrl.reset(x[None, :])
        t_plan = self._plan_time(self._last_sample)
        self._flying = self._mine(self.formation)
        self._hold = self._braking(t_plan + self.ctrl.lead_s, self.ctrl.rfl.phi_r(x[None, :])[0])
        self._rejoin(t_plan, RelativeTo(self._hold, self.leader))

    def _braking(self, t: float, x: np.ndarray) -> QuinticTransfer:
        """From x_r = [lambda_dot, eta_dot, eta, lambda] at plan time t to rest at its stopping
        point, level (absolute, local frame; one agent, as ``_mine``)."""
        p0, v0, eta0, eta_dot0 = x[9:12], x[0:3], x[6:9], x[3:6]
        T = max(2.0, float(np.linalg.norm(v0)) / 2.0)
        row = lambda a: np.asarray(a, dtype=float).reshape(1, 3)  # noqa: E731
        return QuinticTransfer(row(p0), row(v0), row(p0 + v0 * T / 2.0), row(eta0), row(eta_dot0),
                               row([0.0, 0.0, eta0[2]]), t, T)

    def _mine(self, formation: Formation) -> Row:
        """This agent's row of a swarm's formation: the references it flies (entry, rejoin, hold)
        are one-agent formations."""
        return Row(formation, self.agent - 1)

    def _rejoin(self, t_plan: float, source: Formation) -> None:
        """Into the formation from ``source`` (the braking/held trajectory, or the formation of the
        plan before): the reference starts exactly where (and as fast as) the drone is meant to be,
        and its distance to the formation decays over REJOIN_S seconds, longer if the way is long
        (peak acceleration REJOIN_ACCEL_M_S2)."""
        t0 = t_plan + self.ctrl.lead_s  # references are evaluated at the time the estimates refer to
        target = self._flying or self._mine(self.formation)  # the entry, if it is not over
        rejoin = Rejoin(source, target, t0, self.values["REJOIN_S"])
        dp, dv = (float(np.linalg.norm(e[0])) for e in rejoin.initial_error)
        duration_s = rejoin_duration(dp, dv, self.values["REJOIN_ACCEL"], self.values["REJOIN_S"])
        if duration_s > rejoin.duration_s:
            rejoin = Rejoin(source, target, t0, duration_s)
        self.log.info(f"rejoin at t_plan {t_plan:.3f}: {dp:.2f} m and {dv:.2f} m/s away, over {rejoin.duration_s:.1f} s")
        self._tracking = rejoin
        self._set_phase(Phase.FLYING, "")

    def _set_phase(self, phase: Phase, reason: str) -> None:
        if phase != self.phase:
            if phase == Phase.FLYING and self.phase in (Phase.IDLE, Phase.SCHEDULED):
                self._flying_since = self.clock.now()
            self.phase, self._phase_reason, self._phase_since = phase, reason, self.clock.now()
            self._publish_status()
            if phase == Phase.HOLDING:
                self.statustext(f"companion {self.agent}: holding, {reason}", mavlink.MAV_SEVERITY_WARNING)
            elif phase == Phase.FLYING:
                self.statustext(f"companion {self.agent}: in formation")

    def _publish_status(self) -> None:
        """The phase on the bus, with why and since when."""
        if hasattr(self, "bus"):
            self.bus.publish_status(PHASE_STATUS[self.phase], self._phase_reason, self._phase_since)

    def _plan_time(self, s: Sample) -> float:
        return self.clock.plan_time(s.boot_ms, self.mission.start_unix_s)

    # -- the tick -----------------------------------------------------------------------------

    def _sample(self, s: Sample) -> None:
        prev = getattr(self, "_last_sample", None)
        if prev is not None and s.t_rx - prev.t_rx > 0.05 and self.phase == Phase.FLYING:
            self.log.info(f"telemetry gap {1e3 * (s.t_rx - prev.t_rx):.0f} ms (fc time {s.boot_ms - prev.boot_ms} ms)")
        self._last_sample = s
        self.answers.defer = self.clock.advance(s.boot_ms)
        self._queue.append(s)

    def _process_samples(self) -> None:
        """After the flight-controller link has read everything waiting: act on the newest
        sample, right here in the reader (no task switch on the hot path). Samples the loop fell
        behind on still update the estimate, as periods in which the flight controller kept the
        last command (deadline misses). In lockstep, answer what was not commanded."""
        try:
            self._take_samples()
        finally:
            self.answers.settle(self._waiting is not None, self._no_command)

    def _take_samples(self) -> None:
        if not self._queue:
            return
        if self._waiting is not None:  # a new sample before the neighbours came: act now
            self._finish_tick()
        backlog = list(self._queue)
        self._queue.clear()
        try:
            if self.phase in (Phase.FLYING, Phase.HOLDING):
                for old in backlog[:-1]:
                    self.ctrl.hold_tick(np.concatenate([old.eta, old.position])[None, :])
            if len(backlog) > 1:
                half = 0.5 / self.opts.rate_hz
                together = sum(b.t_rx - a.t_rx < half for a, b in zip(backlog, backlog[1:]))
                self.health.skipped(len(backlog) - 1 - together, together)
            self._tick(backlog[-1])
        except Exception:  # a bad tick costs one command, never the loop
            self._tick_failed()

    def _tick_failed(self) -> None:
        self._waiting = None
        self._errors += 1
        if self._errors <= 3:
            self.log.exception("tick failed")

    def _tick(self, s: Sample) -> None:
        """First half of a tick: estimate, publish, and wait for the neighbours' estimates of the
        same instant (at most NB_WAIT_MS from now; see ``_finish_tick``)."""
        if self.fc.max_rpm is None:
            return
        if self.phase in (Phase.IDLE, Phase.SCHEDULED):
            if self.fc.armed and self.fc.landed and self.fc.mode == CustomMode.EXTERNAL:
                self._send_actuators(*self._idle, s)  # armed on the ground: idle, not the failsafe
            return
        self.bus.drain()
        y = np.concatenate([s.eta, s.position])[None, :]
        xhat = self.ctrl.observe(y)
        t_plan = self._plan_time(s)
        lead, dt = self.ctrl.lead_s, self.ctrl.dt_s
        self._t_p = t_plan + lead
        if self._switch is not None and t_plan + self.mission.start_unix_s >= self._switch[2]:
            self._switch_plan(t_plan)
        if self.phase == Phase.HOLDING:
            self._hold_step(s, xhat, t_plan)
            return
        ref = reference_at(self._design, self._tracking.offsets, self._leader_state, t_plan, lead, dt)
        xi = xhat - ref.h
        self.bus.publish_estimate(xi[0], ref.t_p, AgentStatus.FLYING)
        topo = self.plan.schedule.at(ref.t_p)
        expected = [j for j in self._in_neighbours[topo.name] if self._usable(j, check_fresh=False)]
        self._waiting = _Waiting(s, xhat, xi, ref, topo, expected, t_plan, time.monotonic())
        self.bus.waiting = True  # before looking: an estimate arriving from now on rings
        self.bus.take_estimates()  # (may complete the tick through _on_estimate)
        if self._waiting is not None:
            if self.bus.ready(expected, ref.t_p, 0.5 * dt):
                self._finish_tick()
            elif self.answers.lockstep:  # no deadline: they come, or the watchdog says who died
                self._deadline = self.loop.call_later(LOCKSTEP_RECHECK_S, self._lockstep_recheck)
            else:
                # the wait counts from now, not from the datagram's arrival: a late wake-up
                # must not also cost the neighbours' estimates
                self._deadline = self.loop.call_later(self.values["NB_WAIT_MS"] / 1000.0, self._finish_tick)

    def _on_estimate(self) -> None:
        w = self._waiting
        if w is not None and self.bus.ready(w.expected, w.ref.t_p, 0.5 * self.ctrl.dt_s):
            self._finish_tick()

    def _lockstep_recheck(self) -> None:
        """Lockstep, still waiting for neighbours: drop the ones that died or stopped flying (their
        liveliness and status tell), and after NB_WATCHDOG_S of wall time the live ones that never
        published (hung), saying so; finish the tick when the rest are in."""
        self._deadline = None
        w = self._waiting
        if w is None:
            return
        self.bus.drain()
        w.expected = [j for j in w.expected if self._usable(j, check_fresh=False) and j not in self._silent]
        tolerance = 0.5 * self.ctrl.dt_s
        if time.monotonic() - w.since_wall > NB_WATCHDOG_S:
            late = [j for j in w.expected if not self.bus.ready([j], w.ref.t_p, tolerance)]
            if late:
                for j in late:
                    self._silent.setdefault(j, w.ref.t_p - tolerance)
                self.log.warning(f"lockstep: no estimate for t_plan {w.ref.t_p:.3f} from agent(s) {late} in "
                            f"{NB_WATCHDOG_S:g} s of wall time though alive: counted absent until they publish again")
            w.expected = [j for j in w.expected if j not in late]
        if self.bus.ready(w.expected, w.ref.t_p, tolerance):
            self._finish_tick()
        else:
            self._deadline = self.loop.call_later(LOCKSTEP_RECHECK_S, self._lockstep_recheck)

    def _finish_tick(self) -> None:
        """Second half: the neighbours' estimates are in (or the wait is over): check the path
        from the leader, then protocol (72), RFL (49) and the command."""
        w, self._waiting = self._waiting, None
        self.bus.waiting = False
        if w is None:
            return
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None
        try:
            self._protocol_step(w)
        except Exception:
            self._tick_failed()
        finally:
            self.answers.settle(False, self._no_command)

    def _protocol_step(self, w: "_Waiting") -> None:
        i, topo, bus = self.agent - 1, w.topo, self.bus
        present = self._presence()
        if not self._has_path(topo, present):
            self._start_hold(w.t_plan, w.xhat[0], f"no path to the leader in {topo.name}")
            self._hold_step(w.sample, w.xhat, w.t_plan)
            return
        nsum = np.zeros(12)
        weight = 0.0
        now = time.time()
        for j, w_ij in self._in_weights[topo.name]:
            nb = bus.neighbours[j]
            if present[j - 1] and nb.heard:
                nsum += w_ij * nb.xi
                weight += w_ij
                self.health.neighbour_age[j].add(now - nb.stamp_s)
        v = protocol_input(self._design, w.xi, nsum[None, :], np.array([weight]),
                           topo.pinning[i:i + 1], w.ref.x0, w.ref.gamma)
        self._actuate(v, w.sample)
        if self.health.ticks % 10 == 0:  # 20 Hz is plenty for a 1 Hz report
            h, _ = self.formation.offsets(w.ref.t_p)
            x0, _ = self._leader_state(w.ref.t_p)
            self.health.formation_error.add(float(np.linalg.norm(w.xhat[0, 9:12] - h[i, 9:12] - x0[9:12])))

    def _hold_step(self, s: Sample, xhat: np.ndarray, t_plan: float) -> None:
        """Holding: pinned to its own absolute reference (the braking trajectory), no neighbours;
        back to the formation as soon as a path from the leader returns."""
        ref = reference_at(self._design, self._hold.offsets, no_leader, t_plan, self.ctrl.lead_s, self.ctrl.dt_s)
        self.bus.publish_estimate(xhat[0] - ref.h[0], ref.t_p, AgentStatus.HOLDING)
        if self._has_path(self.plan.schedule.at(ref.t_p), self._presence()):
            self._rejoin(t_plan, RelativeTo(self._hold, self.leader))
        v = pinned_input(self._design, xhat - ref.h, ref.x0, ref.gamma)
        self._actuate(v, s)

    def _presence(self) -> tuple[bool, ...]:
        """Which agents count now (``_usable``), every one. Of the agents this one does not listen
        to, only liveliness, status and the start decide: that part is kept until one changes."""
        starting = self.clock.now() - self._flying_since < START_GRACE_S
        key = (self.bus.changes, starting)
        if self._presence_base is None or self._presence_base[0] != key:
            self._presence_base = (key, [self._usable(j) for j in range(1, self.plan.n_agents + 1)])
        present = list(self._presence_base[1])
        for j in self.bus.neighbours:  # (their estimates' freshness changes every tick)
            present[j - 1] = self._usable(j)
        return tuple(present)

    def _has_path(self, topo, present: tuple[bool, ...]) -> bool:
        """Whether this agent has a path from the leader through the present agents (cached: the
        answer only changes when an agent comes or goes)."""
        key = (topo.name, present)
        found = self._paths.get(key)
        if found is None:
            found = bool(topo.reachable_from_leader(np.array(present))[self.agent - 1])
            self._paths[key] = found
        return found

    def _usable(self, j: int, check_fresh: bool = True) -> bool:
        """Agent j counts: alive, flying this plan, and (for a neighbour whose estimates we get)
        with an estimate younger than NB_TIMEOUT_S."""
        if j == self.agent:
            return True
        bus = self.bus
        if j not in bus.alive:
            return False
        starting = self.clock.now() - self._flying_since < START_GRACE_S  # the swarm takes off together
        status = bus.statuses.get(j, AgentStatus.FLYING)
        if status == AgentStatus.HOLDING or (status == AgentStatus.IDLE and not starting):
            return False
        nb = bus.neighbours.get(j)
        if nb is None:
            return True  # not one of ours to listen to: liveliness and status decide
        if j in self._silent:  # (lockstep: the watchdog's) until it has published since. (Not "an
            # estimate of now": nobody waits for a silent neighbour, so its estimate of now would have
            # to beat this tick, a race an agent on the same clock loses tick after tick.)
            if nb.t_plan_s < self._silent[j]:
                return False
            del self._silent[j]
        if not nb.heard:
            return starting
        if nb.status != AgentStatus.FLYING:
            return False
        # stale in plan time (the flight controllers' clock): a pause of the whole swarm is not a loss
        return not check_fresh or self._t_p - nb.t_plan_s <= self.values["NB_TIMEOUT_S"]

    def _start_hold(self, t_plan: float, xhat: np.ndarray, reason: str) -> None:
        """xhat: the estimate x_r predicted to t_plan + lead ([lambda_dot, eta_dot, eta, lambda])."""
        self._hold = self._braking(t_plan + self.ctrl.lead_s, xhat)
        absent = {j: self._why_absent(j) for j in range(1, self.plan.n_agents + 1) if not self._usable(j)}
        self.log.info(f"hold at t_plan {t_plan:.3f}: {reason}; absent {absent}")
        self._set_phase(Phase.HOLDING, reason)

    def _why_absent(self, j: int) -> str:
        bus = self.bus
        if j not in bus.alive:
            return "no liveliness"
        status = bus.statuses.get(j)
        nb = bus.neighbours.get(j)
        if nb is not None and nb.heard:
            return (f"status {status.name if status else '?'}, estimate {1e3 * (time.time() - nb.stamp_s):.0f} ms old, "
                    f"t_plan {nb.t_plan_s:.3f} (received {1e3 * (time.time() - nb.received_at):.0f} ms ago)")
        return f"status {status.name if status else '?'}, no estimate"

    def _actuate(self, v: np.ndarray, s: Sample) -> None:
        act = self.ctrl.actuate(v)
        self._send_actuators(act.omega_rad_s[0], act.alpha_rad[0], s)
        self.health.telemetry_age.add(time.time() - self.fc_unix(s.boot_ms))

    def _send_actuators(self, omega, alpha, s: Sample) -> None:
        """The command answering sample s (its time_usec is the sample's time, boot us)."""
        controls = encode_actuators(omega, alpha, self.fc.max_rpm * math.pi / 30.0, math.radians(self.fc.servo_deg))
        self.health.tick(s.t_rx, time.time())  # the command leaves now (loopback may preempt us in the call)
        self.answers.command(s.boot_ms, self._actuator_frame(s.boot_ms, controls))

    def _no_command(self, boot_ms: int) -> bytes:
        """Lockstep's answer to a state it commands nothing for (NaN controls)."""
        return self._actuator_frame(boot_ms, NO_COMMAND)

    def _actuator_frame(self, boot_ms: int, controls: list[float]) -> bytes:
        return mavlink.MAVLink_set_actuator_control_target_message(
            (boot_ms & 0xFFFFFFFF) * 1000, 0, self.agent, 1, controls).pack(self.fc_link.codec)

    # -- the ground station and component 191 -------------------------------------------------

    def _on_gcs(self, link: MavLink, msgs: list, t_rx: float) -> None:
        for msg in msgs:
            self.router.learn(link, msg)
            for dest in self.router.destinations(link, msg, self.links):
                dest.write(msg.get_msgbuf())
            if self.router.for_me(msg):
                self._handle_for_me(link, msg)

    def _handle_for_me(self, link: MavLink, msg) -> None:
        if self.plans.handle(link, msg, time.monotonic()):
            return
        t = msg.get_type()
        if t == "PARAM_REQUEST_LIST":
            for k in range(len(self.values)):
                link.send(self._param_value(k))
        elif t == "PARAM_REQUEST_READ":
            names = list(self.values)
            name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="replace")
            k = msg.param_index if msg.param_index >= 0 else (names.index(name) if name in names else -1)
            if 0 <= k < len(names):
                link.send(self._param_value(k))
        elif t == "PARAM_SET":
            self._param_set(link, msg)
        elif t in ("COMMAND_LONG", "COMMAND_INT"):
            self._command(link, msg)

    def _param_value(self, k: int):
        name = list(self.values)[k]
        if name == "PLAN_T_S":  # the plan time now, for commands timed in it (NaN: no plan in force)
            m = self.mission
            self.values[name] = math.nan if m is None or m.start_unix_s is None else self.clock.now() - m.start_unix_s
        return mavlink.MAVLink_param_value_message(name.encode(), float(self.values[name]), mavlink.MAV_PARAM_TYPE_REAL32,
                                                   len(self.values), k)

    def _param_set(self, link: MavLink, msg) -> None:
        name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="replace")
        spec = self.params.get(name)
        if spec is None:
            self.statustext(f"companion {self.agent}: unknown parameter {name}")
            return
        value = float(msg.param_value)
        if spec.read_only:
            self.statustext(f"companion {self.agent}: {name} is read-only")
        elif not (math.isfinite(value) and spec.lo <= value <= spec.hi):
            self.statustext(f"companion {self.agent}: {name} must be within [{spec.lo:g}, {spec.hi:g}]")
        else:
            self.values[name] = value
        link.send(self._param_value(list(self.values).index(name)))

    def _command(self, link: MavLink, msg) -> None:
        reason = ""
        if msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE and msg.param1 == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            result = mavlink.MAV_RESULT_ACCEPTED
            link.send(self._heartbeat())
        elif msg.command == mavlink.MAV_CMD_TRISWARM_PLAN_START:
            if msg.get_type() != "COMMAND_INT":
                result, reason = mavlink.MAV_RESULT_DENIED, "plan start needs COMMAND_INT (its time is in x and y)"
            else:
                result, reason = self._start_plan(int(msg.param1) << 16 | int(msg.param2), msg.x + msg.y / 1000.0)
        elif msg.command in (mavlink.MAV_CMD_TRISWARM_LEADER_GOTO, mavlink.MAV_CMD_TRISWARM_LEADER_HOLD):
            result, reason = self._leader_command(msg)
        else:
            result = mavlink.MAV_RESULT_UNSUPPORTED
        if reason:
            self._say(reason, mavlink.MAV_SEVERITY_INFO if result == mavlink.MAV_RESULT_ACCEPTED else mavlink.MAV_SEVERITY_WARNING)
        link.send(mavlink.MAVLink_command_ack_message(msg.command, result, 0, 0, msg.get_srcSystem(),
                                                      msg.get_srcComponent()))

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        """To the ground station; a text longer than 50 bytes goes in chunks (MAVLink 2 id, chunk_seq)."""
        self.log.info(text)
        data = text.encode()
        if len(data) <= 50:
            self.gcs_link.send(mavlink.MAVLink_statustext_message(severity, data))
            return
        self._statustext_id = self._statustext_id % 0xFFFF + 1
        for k in range(0, len(data) + 1, 50):  # (a text of a multiple of 50 ends with an empty chunk)
            self.gcs_link.send(mavlink.MAVLink_statustext_message(severity, data[k:k + 50], self._statustext_id, k // 50))

    def _say(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        self.statustext(f"companion {self.agent}: {text}", severity)

    async def _poll_plans(self) -> None:
        while True:
            self.plans.poll(time.monotonic())
            await asyncio.sleep(0.1)

    def _heartbeat(self):
        status = {Phase.HOLDING: mavlink.MAV_STATE_CRITICAL, Phase.FLYING: mavlink.MAV_STATE_ACTIVE}.get(
            self.phase, mavlink.MAV_STATE_STANDBY)
        return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                                                 mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PHASE_MODE[self.phase], status, 3)

    async def _every_second(self) -> None:
        while True:
            hb = self._heartbeat()
            for link in self.links:
                link.send(hb)
            self._tell_refusals()
            self._keep_signing_streams()
            if hasattr(self, "bus"):
                report = self.health_report()
                self.bus.publish_health(report)
                self._publish_status()  # (whole again each second: a put may be lost on the way)
                boot_ms = int(time.monotonic() * 1000) & 0xFFFFFFFF
                for name, key in (("LOOP_HZ", "loop_rate_hz"), ("JIT_P99MS", "jitter_p99_ms"), ("LAT_P99MS", "latency_p99_ms"),
                                  ("MISSES", "deadline_misses"), ("TLM_AGEMS", "telemetry_age_ms"),
                                  ("FORM_ERRM", "formation_error_m")):
                    value = report.get(key)
                    if value is not None:
                        self.gcs_link.send(mavlink.MAVLink_named_value_float_message(boot_ms, name.encode(), float(value)))
                for j, age in report["neighbour_age_ms"].items():
                    if age is not None:
                        self.gcs_link.send(mavlink.MAVLink_named_value_float_message(boot_ms, f"NB{j}_AGEMS".encode(), age))
            await asyncio.sleep(1.0)

    def _tell_refusals(self) -> None:
        """The frames from the ground station refused since the last time, by reason (a ground
        station without the key, or with another, learns why it gets no answer)."""
        refused = Counter({k: n for k, n in self.gcs_link.counters.items() if k.startswith("refused_")})
        new = refused - self._refusals_told
        if new:
            self._refusals_told = refused
            counts = ", ".join(f"{n} {k.removeprefix('refused_').replace('_', ' ')}" for k, n in sorted(new.items()))
            self._say(f"refused frames from the ground station: {counts}", mavlink.MAV_SEVERITY_WARNING)

    def health_report(self) -> dict:
        now = time.time()
        ages = {j: (now - nb.stamp_s if nb.heard else math.inf) for j, nb in self.bus.neighbours.items()}
        report = self.health.report(ages)
        report.update(agent=self.agent, phase=self.phase.value, alive=sorted(self.bus.alive),
                      counters=self.bus.counts(), t=now)
        return report

    def stats(self) -> dict:
        out = {"agent": self.agent, "phase": self.phase.value, "loop": self.health.summary(),
               "tick_errors": self._errors,
               "links": {lk.name: dict(lk.counters) for lk in self.links}}
        if hasattr(self, "bus"):
            out["zenoh"] = self.bus.counts()
        return out


def default_start_time(now: float) -> float:
    """Companions started together agree without talking: the next multiple of 10 s at least 5 s ahead."""
    return math.ceil((now + 5.0) / 10.0) * 10.0


def write_stats(path: Path, stats: dict) -> None:
    from .state import write_json_atomically

    write_json_atomically(path, json.loads(json.dumps(stats, default=float)))
