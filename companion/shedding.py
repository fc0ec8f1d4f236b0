"""Shedding what a ground station sends beyond what the companion handles: token buckets, one per
sender, and what is said of a flood (once when it begins, once when it ends).

A bucket holds at most ``burst`` tokens and gains ``rate_per_s`` a second; each frame taken costs
one, and a frame that finds the bucket empty is dropped and counted. The buckets run on the
companion's monotonic clock: what they protect (the loop's CPU, the flight controller's link) is
spent in wall time.
"""

from __future__ import annotations

import math
from collections import Counter, OrderedDict
from dataclasses import dataclass, field

MAX_SENDERS = 16
"""Senders with a bucket of their own; the one heard longest ago gives its bucket up to a new one."""


@dataclass
class TokenBucket:
    rate_per_s: float
    burst: float
    tokens: float = math.nan
    at_s: float = math.nan

    def take(self, now_s: float) -> bool:
        """One token at ``now_s`` [s], if there is one."""
        if math.isnan(self.at_s):
            self.tokens = self.burst
        else:
            self.tokens = min(self.burst, self.tokens + max(0.0, now_s - self.at_s) * self.rate_per_s)
        self.at_s = now_s if math.isnan(self.at_s) else max(self.at_s, now_s)
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


@dataclass
class Shedder:
    """A bucket per sender (its address), and what each sender had dropped."""

    rate_per_s: float
    burst: float
    max_senders: int = MAX_SENDERS
    buckets: OrderedDict = field(default_factory=OrderedDict)
    dropped: Counter = field(default_factory=Counter)
    """Frames dropped, by sender (of those that have a bucket)."""
    total_dropped: int = 0

    def take(self, sender, now_s: float) -> bool:
        if self.rate_per_s == math.inf:  # (no limit)
            return True
        bucket = self.buckets.pop(sender, None)
        if bucket is None:
            bucket = TokenBucket(self.rate_per_s, self.burst)
            while len(self.buckets) >= self.max_senders:
                gone, _ = self.buckets.popitem(last=False)
                self.dropped.pop(gone, None)
        self.buckets[sender] = bucket  # (the most recently heard last)
        if bucket.take(now_s):
            return True
        self.dropped[sender] += 1
        self.total_dropped += 1
        return False


QUIET_S = 2.0
"""A flood is over once nothing more was dropped for this long [s] after the first quiet look: a
sender that pauses (or a busy machine that stalls it) for a second or two is one flood, not one a
pause."""


@dataclass
class _Episode:
    count_at_start: int
    began_s: float
    quiet_since_s: float | None = None
    """The first look that saw nothing more since the last drop [s] (None while it drops)."""


@dataclass
class Episodes:
    """Floods told once each: looked at now and then (once a second), counts of drops by key say
    which keys began to drop since the last look and which stopped (nothing more since a look
    ``quiet_s`` ago, or the key is gone), with what they dropped in the episode and how long it
    lasted [s]: from the look that saw it begin to the first that saw nothing more."""

    quiet_s: float = QUIET_S
    _told: dict = field(default_factory=dict)
    _open: dict = field(default_factory=dict)
    """Keys dropping -> their ``_Episode``."""

    def look(self, counts, now_s: float) -> tuple[list[tuple[object, int]], list[tuple[object, int, float]]]:
        began, ended = [], []
        for key, n in counts.items():
            before = self._told.get(key, 0)
            self._told[key] = n
            e = self._open.get(key)
            if n != before:
                if e is None:
                    self._open[key] = _Episode(before, now_s)
                    began.append((key, n - before))
                else:
                    e.quiet_since_s = None
            elif e is not None:
                e.quiet_since_s = now_s if e.quiet_since_s is None else e.quiet_since_s
                if now_s - e.quiet_since_s >= self.quiet_s:
                    del self._open[key]
                    ended.append((key, n - e.count_at_start, e.quiet_since_s - e.began_s))
        for key in [k for k in self._open if k not in counts]:
            e = self._open.pop(key)
            quiet_since_s = now_s if e.quiet_since_s is None else e.quiet_since_s
            ended.append((key, self._told.pop(key) - e.count_at_start, quiet_since_s - e.began_s))
        for key in [k for k in self._told if k not in counts]:
            del self._told[key]
        return began, ended
