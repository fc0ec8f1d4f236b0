"""Plans and leader moves of one agent: the mission kept across restarts, the plan in force, a plan
received and waiting for its start, a plan to put in force in flight, and the operator's leader
commands.

Plans come from a file (the positional ``PLAN``) or up the ground-station link (the mission protocol,
``plan_server.py``). An uploaded plan is checked as ``triswarm plan check`` checks it (but the
flight), off the loop, and staged; MAV_CMD_TRISWARM_PLAN_START puts it in force from a start time
common to the swarm, or, in flight, switches to it at that time if it changes only the formation.
Leader commands move x0 from a plan time common to the swarm, once checked against the airframe's
limits. What is in force is saved in the state folder at every change (``state.StateStore``).

The agents of one process that fly the same plan share one ``Plan`` object (its design computed
once, its formation evaluated once per instant for all of them, and its check run once).
"""

from __future__ import annotations

import asyncio
import math
from collections import OrderedDict
from pathlib import Path

import numpy as np

from triswarm.protocol.airframe import ParameterError
from triswarm.protocol.codec import plan_id
from triswarm.protocol.formation import Formation, LeaderMove, Shifted
from triswarm.protocol.frames import flip
from triswarm.protocol.mavlink import mavlink
from triswarm.protocol.plan import Plan, PlanError, actuator_demand, in_flight_change_problem, plan_from_dict, spec_from_toml
from triswarm.protocol.plan_transfer import PlanItem, PlanTransferError, decode_plan, encode_plan

from .state import Mission, StateStore

SWITCH_MAX_JUMP = (5.0, 5.0)  # in flight, a new formation may start this far from the old one [m, m/s]
LEADER_LATE_S = 2.0  # a leader command may arrive this late for its plan time (the move starts slow)
MOVE_CHECK_STEP_S = 0.05  # a leader move is checked against the airframe's limits this often [s],
MOVE_CHECK_SAMPLES = 100  # or at this many instants over a long move
KEPT_PLANS = 8  # plans of the process kept for its agents to share


class _Shared:
    """What the agents of a process share: plans by file and by id, their checks, leaders with moves."""

    def __init__(self) -> None:
        self.plans: OrderedDict[object, Plan] = OrderedDict()
        self.checks: dict[int, asyncio.Future] = {}
        self.leaders: OrderedDict[tuple, Formation] = OrderedDict()

    def keep(self, table: OrderedDict, key, value):
        table[key] = value
        while len(table) > KEPT_PLANS:
            table.popitem(last=False)
        return value


_SHARED = _Shared()


def load_plan_file(path: Path) -> Plan:
    """The plan in a file (one ``Plan`` per file and version for the whole process)."""
    try:
        st = Path(path).stat()
        key = ("file", str(Path(path).resolve()), st.st_mtime_ns, st.st_size)
        if key in _SHARED.plans:
            return _SHARED.plans[key]
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise PlanError(f"{path}: no such plan file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise PlanError(f"{path}: cannot read the plan file ({exc.__class__.__name__})") from None
    return _SHARED.keep(_SHARED.plans, key, plan_from_dict(spec_from_toml(text, str(path)), str(path)))


def plan_of(spec: dict, source: str) -> Plan:
    """The plan of ``spec`` (one ``Plan`` per plan id for the whole process)."""
    key = ("id", plan_id(spec))
    found = _SHARED.plans.get(key)
    return found if found is not None else _SHARED.keep(_SHARED.plans, key, plan_from_dict(spec, source))


def checked(plan: Plan, loop: asyncio.AbstractEventLoop) -> asyncio.Future:
    """``plan.check()`` off the loop, once per plan for the whole process: a future of its outcome."""
    fut = _SHARED.checks.get(id(plan))
    if fut is None or fut.get_loop() is not loop:
        fut = _SHARED.checks[id(plan)] = loop.run_in_executor(None, plan.check)
    return fut


def leader_with_moves(leader: Formation, moves: list[dict]) -> Formation:
    """The plan's leader after the operator's leader commands, in order (the same object for the
    same leader and moves, process-wide: agents flying one leader evaluate it once per instant)."""
    key = (id(leader), repr(moves))
    found = _SHARED.leaders.get(key)
    if found is not None:
        return found
    out = leader
    for m in moves:
        out = LeaderMove(out, m["at_s"], m["target_m"] and tuple(m["target_m"]), m["yaw_rad"], m["speed_m_s"])
    return _SHARED.keep(_SHARED.leaders, key, out)


class Plans:
    """One agent's plans. ``clock``: the flight controller's (``clock.FcClock``), which plan time runs
    on; ``on_reopen(reopen)``: a new plan is in force (the flight opens it); ``on_schedule()``: it
    starts at ``mission.start_unix_s``; ``in_flight()``: whether the agent flies; ``clock_check()``:
    why the clock a plan starts on is not good enough for a common start, or None."""

    def __init__(self, agent: int, store: StateStore, clock, log, on_reopen, on_schedule, in_flight,
                 clock_check=lambda: None) -> None:
        self.agent = agent
        self.store = store
        self.clock = clock
        self.log = log
        self.on_reopen, self.on_schedule, self.in_flight = on_reopen, on_schedule, in_flight
        self.clock_check = clock_check
        self.mission: Mission | None = None
        self.plan: Plan | None = None
        self.leader: Formation | None = None
        """The plan's leader x0 with the operator's moves."""
        self.formation: Formation | None = None
        """The plan's formation, from its own start."""
        self.staged: tuple[Plan, int] | None = None
        """Received, valid, waiting for its start command."""
        self.switch: tuple[Plan, int, float] | None = None
        """A plan to put in force in flight, and when [Unix s]."""
        self._items: tuple = (None, [])

    @property
    def start_unix_s(self) -> float | None:
        return None if self.mission is None else self.mission.start_unix_s

    def load(self, plan_path: Path | None) -> None:
        """A saved mission (resumed after a restart) wins over a plan file with the same plan, and
        over any plan file in the middle of a flight (the plan may have changed in the air)."""
        saved = self.store.load()
        if self.store.problem:
            self.log.warning(self.store.problem)
        plan_file = load_plan_file(plan_path) if plan_path else None
        if saved is not None and saved.agent == self.agent and (plan_file is None or saved.phase in ("flying", "landing")
                                                                or plan_id(plan_file.spec) == saved.plan_id):
            self.mission = saved
            self.plan = plan_of(saved.plan_spec, f"{self.store.path}")
        elif plan_file is not None:
            self.plan = plan_file
            self.mission = Mission(plan_file.spec, plan_id(plan_file.spec), self.agent)
        if self.plan is not None and not 1 <= self.agent <= self.plan.n_agents:
            raise PlanError(f"agent {self.agent} is not in plan {self.plan.name} ({self.plan.n_agents} drones)")
        if self.plan is not None:
            self._in_force()

    def _in_force(self) -> None:
        m = self.mission
        self.leader = leader_with_moves(self.plan.leader, m.leader_moves)
        self.formation = Shifted(self.plan.formation, m.formation_shift_s) if m.formation_shift_s else self.plan.formation
        if m.next_plan is not None:
            nxt = m.next_plan
            self.switch = (plan_of(nxt["spec"], f"{self.store.path}"), nxt["plan_id"], nxt["at_unix_s"])

    def leader_state(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        h, h_dot = self.leader.offsets(t_s)
        return h[0], h_dot[0]

    def save(self) -> None:
        self.store.save(self.mission)

    def set_phase(self, phase: str) -> None:
        """The mission's phase ("scheduled", "flying", "landing", "done"), saved."""
        self.mission.phase = phase
        self.save()

    def schedule_at(self, start_unix_s: float) -> None:
        """The mission in force starts at ``start_unix_s`` [Unix s, the flight controller's clock], saved."""
        self.mission.start_unix_s = start_unix_s
        self.set_phase("scheduled")

    def plan_time(self, boot_us: int) -> float:
        """A flight-controller time [us since its boot] as plan time [s] of the mission in force."""
        return self.clock.plan_time(boot_us, self.mission.start_unix_s)

    def plan_time_now(self) -> float | None:
        """The plan time now [s] (its flight controller's newest sample), or None: no start time."""
        start = self.start_unix_s
        return None if start is None else self.clock.now() - start

    # -- the mission protocol -------------------------------------------------------------------

    def held_items(self) -> list[PlanItem]:
        """What a download gets: the plan in force, or before any, the one waiting for its start."""
        spec = self.plan.spec if self.plan is not None else self.staged[0].spec if self.staged else None
        if spec is None:
            return []
        if self._items[0] is not spec:
            self._items = (spec, encode_plan(spec))
        return self._items[1]

    def receive(self, items: list[PlanItem], loop: asyncio.AbstractEventLoop) -> tuple[int, str] | asyncio.Future:
        """A whole mission came: check it as `plan check` does (but the flight); stage it if it
        passes. The check runs off the loop (at 200 drones it takes longer than the flight
        controller's failsafe would wait for the next command): the answer is a future."""
        try:
            spec, pid = decode_plan(items)
            plan = plan_of(spec, "uploaded plan")
            if not 1 <= self.agent <= plan.n_agents:
                raise PlanError(f"uploaded plan: agent {self.agent} is not in it ({plan.n_agents} drones)")
        except PlanTransferError as exc:
            return exc.ack_code, f"plan refused: {exc}"
        except (PlanError, ParameterError, ValueError) as exc:
            return mavlink.MAV_MISSION_INVALID, f"plan refused: {exc}"
        answer = loop.create_future()

        def done(check: asyncio.Future) -> None:
            exc = check.exception()
            if isinstance(exc, (PlanError, ParameterError, ValueError)):
                answer.set_result((mavlink.MAV_MISSION_INVALID, f"plan refused: {exc}"))
            elif exc is not None:  # a bug, shown as one
                self.log.error("plan check failed", exc_info=exc)
                answer.set_result((mavlink.MAV_MISSION_ERROR, f"plan check failed: {exc.__class__.__name__}: {exc}"))
            else:
                self.staged = (plan, pid)
                answer.set_result((mavlink.MAV_MISSION_ACCEPTED, f"plan {plan.name} {pid:08x} received; waiting for its start"))

        checked(plan, loop).add_done_callback(done)
        return answer

    def clear(self) -> tuple[int, str]:
        if self.in_flight():
            return mavlink.MAV_MISSION_DENIED, "clear refused: flying; land first"
        self.staged = None
        self.plan = self.mission = self.leader = None
        self.store.clear()
        return mavlink.MAV_MISSION_ACCEPTED, "plans cleared"

    # -- starting and switching ------------------------------------------------------------------

    def start(self, pid: int, start_unix_s: float) -> tuple[int, str]:
        """MAV_CMD_TRISWARM_PLAN_START: the staged plan (or the one in force, again) from a
        common start time."""
        m = self.mission
        if m is not None and m.plan_id == pid and m.start_unix_s == start_unix_s and m.phase != "done":
            return mavlink.MAV_RESULT_ACCEPTED, ""  # a retry of the same command
        if not (math.isfinite(start_unix_s) and start_unix_s > self.clock.now() - 1.0):
            return mavlink.MAV_RESULT_DENIED, "plan start refused: the start time has passed"
        clock_problem = self.clock_check()
        if clock_problem:
            return mavlink.MAV_RESULT_DENIED, f"plan start refused: {clock_problem}"
        if self.staged is not None and self.staged[1] == pid:
            plan = self.staged[0]
        elif m is not None and m.plan_id == pid:
            plan = self.plan
        else:
            return mavlink.MAV_RESULT_DENIED, f"plan start refused: no plan {pid:08x} here; upload it first"
        if self.in_flight():
            return self._next(plan, pid, start_unix_s)
        reopen = m is None or m.plan_id != pid
        self.staged = None
        self.plan, self.mission = plan, Mission(plan.spec, pid, self.agent, start_unix_s, "scheduled")
        self.save()
        self._in_force()
        self.on_reopen(reopen)
        self.on_schedule()
        return mavlink.MAV_RESULT_ACCEPTED, f"plan {plan.name} starts at {start_unix_s:.1f}"

    def _next(self, plan: Plan, pid: int, at_unix_s: float) -> tuple[int, str]:
        """In flight: the new plan takes over at at_unix_s if it changes only the formation."""
        m = self.mission
        if m.next_plan is not None and (m.next_plan["plan_id"], m.next_plan["at_unix_s"]) == (pid, at_unix_s):
            return mavlink.MAV_RESULT_ACCEPTED, ""  # a retry
        problem = in_flight_change_problem(self.plan.spec, plan.spec) or self._switch_jump(plan, at_unix_s)
        if problem:
            return mavlink.MAV_RESULT_DENIED, f"plan start refused: {problem}"
        self.staged = None
        self.switch = (plan, pid, at_unix_s)
        m.next_plan = {"spec": plan.spec, "plan_id": pid, "at_unix_s": at_unix_s}
        self.save()
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

    def switch_due(self, t_plan: float) -> bool:
        return self.switch is not None and t_plan + self.mission.start_unix_s >= self.switch[2]

    def take_switch(self) -> tuple[Plan, int]:
        """Put the next plan in force, here in flight: its formation starts now (its t = 0), the
        swarm's plan time, graphs and leader run on."""
        plan, pid, at_unix_s = self.switch
        self.switch = None
        m = self.mission
        m.plan_spec, m.plan_id, m.next_plan = plan.spec, pid, None
        m.formation_shift_s = at_unix_s - m.start_unix_s
        self.save()
        self.plan = plan
        self._in_force()
        return plan, pid

    # -- the leader ------------------------------------------------------------------------------

    def leader_command(self, msg) -> tuple[int, str]:
        """MAV_CMD_TRISWARM_LEADER_GOTO / _HOLD: a move of x0 from a plan time common to the swarm."""
        m = self.mission
        if m is None or m.start_unix_s is None:
            return mavlink.MAV_RESULT_DENIED, "leader command refused: no plan in force"
        at_s = float(msg.param3)
        if not (math.isfinite(at_s) and at_s >= self.clock.now() - m.start_unix_s - LEADER_LATE_S):
            return mavlink.MAV_RESULT_DENIED, f"leader command refused: plan time {at_s:.2f} s has passed"
        if msg.command == mavlink.MAV_CMD_TRISWARM_LEADER_GOTO:
            if msg.get_type() == "COMMAND_INT":
                target_ned_m = [msg.x / 1000.0, msg.y / 1000.0, float(msg.z)]
            else:
                target_ned_m = [float(msg.param5), float(msg.param6), float(msg.param7)]
            if not all(math.isfinite(v) for v in target_ned_m):
                return mavlink.MAV_RESULT_DENIED, "leader command refused: the target is not a finite point"
            target = [float(v) for v in flip(target_ned_m)]  # NED on the wire, the plan's frame inside
            yaw = None if math.isnan(msg.param2) else -float(msg.param2)
            move = {"at_s": at_s, "target_m": target, "yaw_rad": yaw, "speed_m_s": float(msg.param1)}
        else:
            move = {"at_s": at_s, "target_m": None, "yaw_rad": None, "speed_m_s": 1.0}
        if move in m.leader_moves:
            return mavlink.MAV_RESULT_ACCEPTED, ""  # a retry
        if m.leader_moves and at_s < m.leader_moves[-1]["at_s"]:
            return mavlink.MAV_RESULT_DENIED, "leader command refused: older than the last one"
        try:
            leader = leader_with_moves(self.plan.leader, m.leader_moves + [move])
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
        self.save()
        what = "hold" if move["target_m"] is None else "goto " + " ".join(f"{v:.1f}" for v in move["target_m"])
        return mavlink.MAV_RESULT_ACCEPTED, f"leader {what} at t {at_s:.1f} s"
