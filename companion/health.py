"""Loop health of a companion: rates, jitter, latency, deadline misses, ages, formation error."""

from __future__ import annotations

import math
import time
from collections import Counter, defaultdict, deque

import numpy as np


BIN_BATCH = 256  # samples binned together


class Window:
    """The last ``n`` samples of a quantity (for the 1 Hz report), and a log histogram of every
    sample (for whole-run percentiles, 2 % resolution, constant memory however long the flight)."""

    RATIO = 1.02
    FLOOR = 1e-7  # values at or below it share the first bin

    def __init__(self, n: int = 400, keep_all: bool = True) -> None:
        self.recent: deque[float] = deque(maxlen=n)
        self.bins: Counter[int] | None = Counter() if keep_all else None
        self._unbinned: list[float] = []  # added since the last binning (binned in bulk: a tick is hot)
        self.count = 0

    def add(self, value: float) -> None:
        self.recent.append(value)
        if self.bins is not None:
            self.count += 1
            self._unbinned.append(value)
            if len(self._unbinned) >= BIN_BATCH:
                self._bin_pending()

    def _bin_pending(self) -> None:
        if not self._unbinned:
            return
        values = np.asarray(self._unbinned, dtype=float)
        self._unbinned.clear()
        above = values > self.FLOOR
        k = np.zeros(values.size, dtype=np.int64)
        k[above] = 1 + (np.log(values[above] / self.FLOOR) / math.log(self.RATIO)).astype(np.int64)
        self.bins.update(dict(zip(*(a.tolist() for a in np.unique(k, return_counts=True)))))

    def merge(self, other: "Window") -> None:
        """Take in every sample of ``other`` (whole-run percentiles of several windows)."""
        other._bin_pending()
        self.bins.update(other.bins)
        self.count += other.count

    def percentile(self, q: float, recent: bool = True) -> float:
        """The q-th percentile of the recent samples, or of all of them (to within 2 %)."""
        if recent or self.bins is None:
            return float(np.percentile(np.fromiter(self.recent, float), q)) if self.recent else math.nan
        self._bin_pending()
        if not self.count:
            return math.nan
        rank = q / 100.0 * self.count
        seen = 0
        for k in sorted(self.bins):
            seen += self.bins[k]
            if seen >= rank:
                return self.FLOOR * self.RATIO ** (k - 0.5) if k else self.FLOOR
        return math.nan


class LoopHealth:
    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.ticks = 0
        self.deadline_misses = 0
        self.skipped_samples = 0
        self.superseded_samples = 0
        self.jitter = Window()            # |interval between consecutive commands - period| [s]
        self.latency = Window()           # telemetry datagram received -> command written [s]
        self.telemetry_age = Window()     # command written - telemetry sample time (FC clock) [s]
        self.neighbour_age: dict[int, Window] = defaultdict(Window)  # use time - publish time [s]
        self.formation_error = Window(n=200, keep_all=False)
        self._last_sent: float | None = None
        self._rate_count = 0
        self._rate_t0 = time.monotonic()
        self.loop_rate_hz = math.nan
        self._cpu0: float | None = None  # from the first tick: start-up imports are not the loop
        self._wall0 = 0.0

    def tick(self, t_rx: float, t_sent: float) -> None:
        """One control step: telemetry received at t_rx, command written at t_sent (Unix time [s])."""
        if self._cpu0 is None:
            self._cpu0, self._wall0 = time.process_time(), time.monotonic()
        self.ticks += 1
        self._rate_count += 1
        if self._last_sent is not None:
            self.jitter.add(abs(t_sent - self._last_sent - self.period_s))
        self._last_sent = t_sent
        self.latency.add(t_sent - t_rx)
        if t_sent - t_rx > self.period_s:
            self.deadline_misses += 1

    def skipped(self, missed: int, superseded: int = 0) -> None:
        """Samples never acted on: ``missed`` arrived while the loop was late (deadline misses);
        ``superseded`` were followed within half a period by the next one (the flight controller
        sent them late, together: its lag, not the loop's, so not a deadline miss). Before the first
        command (setting up) nothing counts."""
        if not self.ticks:
            return  # the loop has not started: nothing was due
        self.skipped_samples += missed + superseded
        self.superseded_samples += superseded
        self.deadline_misses += missed

    def cpu_fraction(self) -> float:
        """Share of one core this process used since its first tick."""
        if self._cpu0 is None:
            return 0.0
        return (time.process_time() - self._cpu0) / max(time.monotonic() - self._wall0, 1e-9)

    def report(self, neighbours_now: dict[int, float]) -> dict:
        """The 1 Hz health record (milliseconds where it says _ms)."""
        now = time.monotonic()
        if now - self._rate_t0 > 0:
            self.loop_rate_hz = self._rate_count / (now - self._rate_t0)
        self._rate_count, self._rate_t0 = 0, now
        return {
            "loop_rate_hz": round(self.loop_rate_hz, 2),
            "jitter_p99_ms": _ms(self.jitter.percentile(99)),
            "latency_p50_ms": _ms(self.latency.percentile(50)),
            "latency_p99_ms": _ms(self.latency.percentile(99)),
            "deadline_misses": self.deadline_misses,
            "ticks": self.ticks,
            "telemetry_age_ms": _ms(self.telemetry_age.percentile(50)),
            "neighbour_age_ms": {str(j): (None if not math.isfinite(a) else round(1e3 * a, 2))
                                 for j, a in sorted(neighbours_now.items())},
            "formation_error_m": _round(self.formation_error.percentile(100)),
            "cpu_fraction": round(self.cpu_fraction(), 4),
        }

    def summary(self) -> dict:
        """Whole-run numbers (for benchmarks)."""
        ages = Window(n=1)
        for w in self.neighbour_age.values():
            ages.merge(w)
        return {
            "ticks": self.ticks,
            "deadline_misses": self.deadline_misses,
            "skipped_samples": self.skipped_samples,
            "superseded_samples": self.superseded_samples,
            "jitter_p99_ms": _ms(self.jitter.percentile(99, recent=False)),
            "latency_p50_ms": _ms(self.latency.percentile(50, recent=False)),
            "latency_p99_ms": _ms(self.latency.percentile(99, recent=False)),
            "neighbour_age_p50_ms": _ms(ages.percentile(50, recent=False)),
            "neighbour_age_p99_ms": _ms(ages.percentile(99, recent=False)),
            "cpu_fraction": self.cpu_fraction(),
        }


def _ms(x: float) -> float | None:
    return None if not math.isfinite(x) else round(1e3 * x, 3)


def _round(x: float) -> float | None:
    return None if not math.isfinite(x) else round(x, 4)
