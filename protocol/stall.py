"""Wall-clock watchdogs that do not count their own process's stalls. Pure logic: every time is
passed in, in seconds of a monotonic clock.

A watchdog on the wall clock judges another process by how long it has been silent: a flight
controller not heard from for 3 s is lost, a companion that has not answered its lockstep state for
10 s has died. On a loaded machine the watching process may itself not run for seconds (and the
other side, on the same machine, often not either): that silence is the machine's, and what the
other side sent meanwhile waits unread in a socket. Counting it would call a live process dead.

``Stalls`` is looked at regularly, every ``period_s``. A look that comes more than ``slack_s`` late
means the process did not run meanwhile; the watchdogs then count silence from that look on, so a
verdict needs that much time in which the watcher ran and could have heard the other side. A real
death is still found: only later, by the length of the stall.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass
class Stalls:
    period_s: float
    """How often the process looks [s]."""
    slack_s: float = 0.5
    """A look later than ``period_s`` by more than this follows a stall [s]."""
    since_s: float = -math.inf
    """The end of the latest stall: the watchdogs count silence from here at the earliest [s]."""
    count: int = 0
    longest_s: float = 0.0
    _last_s: float | None = field(default=None, repr=False)

    def look(self, now_s: float) -> float:
        """A regular look at ``now_s``; returns ``since_s``."""
        if self._last_s is not None:
            late_s = now_s - self._last_s - self.period_s
            if late_s > self.slack_s:
                self.since_s = now_s
                self.count += 1
                self.longest_s = max(self.longest_s, late_s + self.period_s)
        self._last_s = now_s
        return self.since_s

    def silent_s(self, heard_s: float, now_s: float) -> float:
        """How long the other side has been silent, as far as this process could hear it."""
        return now_s - max(heard_s, self.since_s)
