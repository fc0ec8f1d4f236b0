"""A fault survived: a neighbour flies another plan. Its estimates are dropped and counted on the
bus (``drop_other_plan``: ``test_bus.py``, and in flight ``test_stack.py``, whose formation holds
with another plan's estimates on the bus); this tests what the companion says of it: once per
agent and plan, not once a second. (The agent's once-a-second telling is logic on what the bus
heard: the agent is a plain namespace here.)"""

from types import SimpleNamespace

from triswarm.companion.agent import Agent
from triswarm.protocol.codec import AgentStatus

PLAN, OTHER = 0x1234ABCD, 0x0BADF00D


def agent(statuses: dict):
    said = []
    a = SimpleNamespace(id=1, bus=SimpleNamespace(statuses=statuses), plans=SimpleNamespace(mission=SimpleNamespace(plan_id=PLAN)),
                        plans_on_bus=(PLAN,), _told_plans=set(), _told_clock_step=None,
                        fc=SimpleNamespace(clock=SimpleNamespace(refused_step_us=None)),
                        say=lambda text, severity=None: said.append(text))
    return a, said


def test_an_agent_of_another_plan_is_said_once_per_plan():
    statuses = {1: (AgentStatus.FLYING, PLAN), 2: (AgentStatus.FLYING, PLAN), 3: (AgentStatus.FLYING, OTHER)}
    a, said = agent(statuses)
    for _ in range(5):  # five seconds
        Agent.tell_others(a)
    assert said == [f"agent 3 flies another plan ({OTHER:08x}, not {PLAN:08x}): its estimates are dropped and it "
                    "counts as absent"], said
    statuses[2] = (AgentStatus.FLYING, OTHER)
    statuses[3] = (AgentStatus.FLYING, OTHER + 1)
    Agent.tell_others(a)
    Agent.tell_others(a)
    assert len(said) == 3 and "agent 2 flies another plan" in said[1] and f"({OTHER + 1:08x}," in said[2], said


def test_a_refused_clock_step_is_said_once_per_step():
    a, said = agent({})
    clock = a.fc.clock
    for step in (None, 30_000_000, 30_000_000, 30_100_000, -30_000_000, -30_000_000):
        clock.refused_step_us = step
        Agent.tell_others(a)
    assert [s.split(" in flight")[0] for s in said] == [
        "the flight controller's Unix time stepped +30.000 s", "the flight controller's Unix time stepped -30.000 s"], said
