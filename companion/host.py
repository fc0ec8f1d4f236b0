"""Several agents in one companion process: one asyncio loop and one Zenoh session.

On a drone the companion flies one agent, and that stays the default. To simulate a large swarm
on one machine, a process can fly several: each agent keeps everything of its own (a
``Companion`` each: its MAVLink links, signing key, liveliness token, state folder, counters and
mission), and only the loop and the Zenoh session are shared. Agents of one process hear each
other through the session without a network hop, and one wake-up of the loop serves every agent
whose telemetry came; per agent, that saves the context switches and the Zenoh runtime of a
process of its own, which cost more than the control itself (``make bench``).
"""

from __future__ import annotations

import asyncio
import dataclasses

from .companion import Companion, CompanionOptions, zenoh_config


class SharedZenoh:
    """The session of a process's agents, opened when the first of them needs it."""

    def __init__(self, opts: CompanionOptions, agents: frozenset[int]) -> None:
        self.opts, self.agents = opts, agents
        self._session = None

    def session(self, n_agents: int):
        if self._session is None:
            from .bus import open_session

            self._session = open_session(zenoh_config(self.opts, self.agents, n_agents))
        return self._session

    def close(self) -> None:
        if self._session is not None:
            self._session.close()
            self._session = None


def agent_options(opts: CompanionOptions, agents: list[tuple[int, str, str]]) -> list[CompanionOptions]:
    """Each agent's options: ``opts`` with its id, links, and {id} in paths replaced by its id."""
    def own(path):
        return None if path is None else type(path)(str(path).replace("{id}", str(agent)))

    out = []
    for agent, fc_url, gcs_url in agents:
        out.append(dataclasses.replace(opts, agent=agent, fc_url=fc_url, gcs_url=gcs_url,
                                       state_dir=own(opts.state_dir), stats_path=own(opts.stats_path)))
    return out


async def run_agents(options: list[CompanionOptions], stop: asyncio.Event) -> list[dict]:
    """Fly every agent until ``stop``; if one cannot start or fails, stop them all and raise its
    error. Returns each agent's stats, in order."""
    if len(options) == 1:
        return [await Companion(options[0]).run(stop)]
    shared = SharedZenoh(options[0], frozenset(o.agent for o in options))
    companions = [Companion(o, shared) for o in options]
    tasks = [asyncio.create_task(c.run(stop)) for c in companions]
    for t in tasks:
        t.add_done_callback(lambda t: t.cancelled() or t.exception() is None or stop.set())
    try:
        results = await asyncio.gather(*tasks, return_exceptions=True)
    finally:
        shared.close()
    for r in results:
        if isinstance(r, BaseException):
            raise r
    return results
