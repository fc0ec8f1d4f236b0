"""A companion process: one asyncio loop, one Zenoh session, one control loop, and the agents it flies.

On a drone the companion flies one agent, and that stays the default. To simulate a large swarm on
one machine, a process can fly several (repeat ``--id``, ``--fc`` and ``--gcs``): each agent keeps
everything of its own (its MAVLink links, signing key, liveliness token, state folder, counters
and mission), while the process shares what costs the same for one agent or a hundred: the loop
and its wake-ups, the Zenoh session, the table of the agents' newest estimates (an agent's
neighbours in the same process read its estimate with no network hop), one controller per design
with a row for each agent that flies it, and the control loop, which ticks every agent whose
sample came in one pass (``loop.py``).
"""

from __future__ import annotations

import asyncio
import dataclasses
import selectors

from triswarm.protocol.controller import FormationController
from triswarm.protocol.plan import PlanError, plan_from_dict

from .agent import Agent
from .options import CompanionOptions
from .bus import Bus
from .zenoh_session import close_session, copies_backup, default_config, open_session, peer_config, tune
from .flight import SharedEntry
from .loop import ControlLoop

WARM_UP_PLAN = {"drones": 1, "formation": {"type": "rotating-polygon", "radius_m": 1.0, "altitude_m": 1.0, "rate_rad_s": 0.0}}


def zenoh_config(o: CompanionOptions, agents: frozenset[int], n_agents: int):
    """The Zenoh configuration of a process flying ``agents``: the file, the endpoints given, or
    peers on loopback (``zenoh_session.default_config``)."""
    import zenoh

    if o.zenoh_config is not None:
        try:
            return tune(zenoh.Config.from_file(str(o.zenoh_config)))
        except Exception as exc:  # zenoh raises its own error type for a bad file
            raise PlanError(f"{o.zenoh_config}: not a usable Zenoh configuration ({exc})") from None
    if o.zenoh_listen or o.zenoh_connect:
        return peer_config(list(o.zenoh_listen), list(o.zenoh_connect), o.zenoh_mode)
    return default_config(agents, n_agents, o.zenoh_base_port)


def agent_options(opts: CompanionOptions, agents: list[tuple[int, str, str]]) -> list[CompanionOptions]:
    """Each agent's options: ``opts`` with its id, links, and {id} in paths replaced by its id."""
    def own(path, agent):
        return None if path is None else type(path)(str(path).replace("{id}", str(agent)))

    return [dataclasses.replace(opts, id=agent, fc=fc_url, gcs=gcs_url, state_dir=own(opts.state_dir, agent),
                                stats=own(opts.stats, agent)) for agent, fc_url, gcs_url in agents]


class _CountingSelector(selectors.DefaultSelector):
    """The loop's selector: one ``select`` a turn of the loop, counted."""

    def __init__(self) -> None:
        super().__init__()
        self.turns = 0

    def select(self, timeout=None):
        self.turns += 1
        return super().select(timeout)


class CountingLoop(asyncio.SelectorEventLoop):
    """The companion's event loop, counting its turns (``turns``): a companion that spins (a wait
    that does not wait) shows as many turns, on any machine; an idle one as few."""

    def __init__(self) -> None:
        self._counting = _CountingSelector()
        super().__init__(self._counting)

    @property
    def turns(self) -> int:
        return self._counting.turns


class Host:
    def __init__(self, options: list[CompanionOptions]) -> None:
        self.options = options
        self._session = None
        self._copies = True
        self._buses: dict[str, Bus] = {}
        self._controllers: dict[tuple, tuple] = {}
        self._entries: dict[tuple, tuple] = {}

    def bus(self, swarm: str, n_agents: int) -> Bus:
        """The process's bus for ``swarm`` (opened on the process's session the first time)."""
        bus = self._buses.get(swarm)
        if bus is None:
            if self._session is None:
                agents = frozenset(o.id for o in self.options)
                config = zenoh_config(self.options[0], agents, n_agents)
                self._copies = copies_backup(config)
                self._session = open_session(config)
            bus = self._buses[swarm] = Bus(swarm, n_agents, copies=self._copies)
            bus.open(self._session, self.loop)
            self.loop_ctl.watch(bus)
        bus.n_agents = max(bus.n_agents, n_agents)
        return bus

    def controller(self, plan, rate_hz: float) -> FormationController:
        """The controller of ``plan`` (``FormationController.for_plan``, in the air the plan says it
        is flown in): one row per agent of the process (an agent's row is its place in the
        process's list)."""
        key = (id(plan.design), rate_hz, plan.controller.thrust_adaptation_rate_1_s,
               plan.controller_air_density_kg_m3(plan.wind))
        found = self._controllers.get(key)
        if found is None:
            ctrl = FormationController.for_plan(plan, len(self.options), rate_hz, plan.wind)
            found = self._controllers[key] = (plan.design, ctrl)  # (the design kept: its id stays its own)
        return found[1]

    def entry(self, plan, formation, t0_s: float) -> SharedEntry:
        """The entry of ``plan``'s ``formation`` from plan time ``t0_s`` that the agents of this
        process beginning it then share."""
        key = (id(plan), id(formation), t0_s)
        found = self._entries.get(key)
        if found is None:
            if len(self._entries) > 8:
                self._entries.clear()
            found = self._entries[key] = (plan, formation, SharedEntry(plan, formation, t0_s))
        return found[2]

    async def run(self, stop: asyncio.Event) -> list[dict]:
        """Fly every agent until ``stop``; if one cannot start or fails, stop them all and raise its
        error. Returns each agent's stats, in order."""
        self.loop = asyncio.get_running_loop()
        self.loop_ctl = ControlLoop(self.loop, len(self.options))
        agents = [Agent(o, self, row) for row, o in enumerate(self.options)]
        # the kernels now, not when a plan starts (a first compile takes seconds)
        FormationController.warm_up(plan_from_dict(WARM_UP_PLAN).design, self.options[0].rate_hz)
        tasks = [asyncio.create_task(a.run(stop)) for a in agents]
        for t in tasks:
            t.add_done_callback(lambda t: t.cancelled() or t.exception() is None or stop.set())
        try:
            results = await asyncio.gather(*tasks, return_exceptions=True)
        finally:
            self.loop_ctl.close()
            for bus in self._buses.values():
                bus.close()
            if self._session is not None:
                close_session(self._session)
        for r in results:
            if isinstance(r, BaseException):
                raise r
        return results


async def run_agents(options: list[CompanionOptions], stop: asyncio.Event) -> list[dict]:
    return await Host(options).run(stop)
