"""Loop health of a companion: rates, jitter, latency, deadline misses, ages, formation error."""

from __future__ import annotations

import math
import time
from collections import defaultdict, deque

import numpy as np


class Window:
    """The last ``n`` samples of a quantity, plus every sample for whole-run percentiles."""

    def __init__(self, n: int = 400, keep_all: bool = True) -> None:
        self.recent: deque[float] = deque(maxlen=n)
        self.all: list[float] | None = [] if keep_all else None

    def add(self, value: float) -> None:
        self.recent.append(value)
        if self.all is not None:
            self.all.append(value)

    def percentile(self, q: float, recent: bool = True) -> float:
        data = self.recent if recent else (self.all or [])
        return float(np.percentile(np.fromiter(data, float), q)) if len(data) else math.nan


class LoopHealth:
    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.ticks = 0
        self.deadline_misses = 0
        self.skipped_samples = 0
        self.interval = Window()          # between consecutive telemetry samples the loop handled [s]
        self.latency = Window()           # telemetry datagram received -> command written [s]
        self.telemetry_age = Window()     # command written - telemetry sample time (FC clock) [s]
        self.neighbour_age: dict[int, Window] = defaultdict(Window)  # use time - publish time [s]
        self.formation_error = Window(n=200, keep_all=False)
        self._last_rx: float | None = None
        self._rate_count = 0
        self._rate_t0 = time.monotonic()
        self.loop_rate_hz = math.nan
        self._cpu0: float | None = None  # from the first tick: start-up imports are not the loop
        self._wall0 = 0.0

    def tick(self, t_rx: float, t_sent: float) -> None:
        """One control step: telemetry received at t_rx, command written at t_sent (monotonic)."""
        if self._cpu0 is None:
            self._cpu0, self._wall0 = time.process_time(), time.monotonic()
        self.ticks += 1
        self._rate_count += 1
        if self._last_rx is not None:
            self.interval.add(t_rx - self._last_rx)
        self._last_rx = t_rx
        self.latency.add(t_sent - t_rx)
        if t_sent - t_rx > self.period_s:
            self.deadline_misses += 1

    def skipped(self, n: int = 1) -> None:
        """Samples that arrived while the loop was still busy and were never acted on."""
        self.skipped_samples += n
        self.deadline_misses += n

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
        jitter = [abs(x - self.period_s) for x in self.interval.recent]
        return {
            "loop_rate_hz": round(self.loop_rate_hz, 2),
            "jitter_p99_ms": round(1e3 * float(np.percentile(jitter, 99)), 3) if jitter else None,
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
        jitter = [abs(x - self.period_s) for x in (self.interval.all or [])]
        ages = [a for w in self.neighbour_age.values() for a in (w.all or [])]
        return {
            "ticks": self.ticks,
            "deadline_misses": self.deadline_misses,
            "skipped_samples": self.skipped_samples,
            "jitter_p99_ms": 1e3 * float(np.percentile(jitter, 99)) if jitter else None,
            "latency_p50_ms": _ms(self.latency.percentile(50, recent=False)),
            "latency_p99_ms": _ms(self.latency.percentile(99, recent=False)),
            "neighbour_age_p50_ms": 1e3 * float(np.percentile(ages, 50)) if ages else None,
            "neighbour_age_p99_ms": 1e3 * float(np.percentile(ages, 99)) if ages else None,
            "cpu_fraction": self.cpu_fraction(),
        }


def _ms(x: float) -> float | None:
    return None if not math.isfinite(x) else round(1e3 * x, 3)


def _round(x: float) -> float | None:
    return None if not math.isfinite(x) else round(x, 4)
