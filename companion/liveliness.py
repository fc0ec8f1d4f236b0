"""Who is alive, on the clock the flight runs on.

Zenoh's liveliness is on the wall clock: a token goes when its session's lease (a second) expires.
On a real vehicle that is what a lost neighbour looks like, and it is taken as it comes. In lockstep
the flight runs on the simulators' clock, and a machine that starves a process for a second expires
its lease while, on that clock, nothing has happened: the clock stands until the starved process
answers. So in lockstep a token that went counts as gone only once ``grace_s`` of plan time has run
since this agent saw it go; an agent back within that time was never absent. The flight applies it
to the agents it does not listen to, whose token is all it has of them (``Flight._alive``): a
neighbour's own estimates are its sign of life.
"""

from __future__ import annotations

LOCKSTEP_GRACE_S = 1.0
"""In lockstep, plan time [s] a neighbour whose liveliness token went still counts as alive."""


class Liveliness:
    """The agents that count as alive: those whose token is there, and those in their grace."""

    def __init__(self) -> None:
        self.kept: frozenset[int] = frozenset()
        """Agents whose token went less than the grace ago [plan s]: still alive for the flight."""
        self._ever: set[int] = set()
        self._gone_at: dict[int, float] = {}
        self._changes = -1
        self._asked: tuple[float, float] | None = None

    def update(self, alive: set[int], changes: int, t_plan_s: float, grace_s: float) -> frozenset[int]:
        """Take the bus's ``alive`` set (``changes``: its count of changes, so that an unchanged set
        costs nothing) at plan time ``t_plan_s``; ``grace_s`` 0 takes the tokens as they are.
        Returns ``kept``."""
        if changes != self._changes:
            self._changes = changes
            for j in self._ever - alive:
                self._gone_at.setdefault(j, t_plan_s)
            for j in alive:
                self._gone_at.pop(j, None)
            self._ever |= alive
        elif (t_plan_s, grace_s) == self._asked:
            return self.kept  # (asked again within one tick: nothing can have changed)
        self._asked = (t_plan_s, grace_s)
        if not self._gone_at or grace_s <= 0.0:
            self.kept = frozenset()
        else:
            self.kept = frozenset(j for j, at in self._gone_at.items() if t_plan_s - at < grace_s)
        return self.kept
