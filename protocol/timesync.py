"""The offset and drift of a remote clock (a flight controller's boot clock) against the local one,
from MAVLink TIMESYNC exchanges (https://mavlink.io/en/services/timesync.html). Pure math: every
time is passed in, in integer nanoseconds.

One exchange: the local clock reads ``sent_ns`` when the request leaves, the remote stamps its
answer ``remote_ns`` at some instant between, and the local clock reads ``received_ns`` when the
answer arrives. Whatever the delays on the way out and back, the remote's stamp belongs to a local
instant within [sent, received]: taking the midpoint errs by at most half the round trip.

The model is a straight line, remote = local + offset + drift (local - ref), fitted over the last
``window`` exchanges by least squares weighted by 1/(half round trip)^2 (an exchange that took long
says little). Exchanges whose round trip exceeds ``max_rtt_ns`` are refused outright (PX4 keeps
those under 10 ms). An exchange whose residual exceeds what its own round trip allows (half of it,
plus three robust standard deviations of all residuals) is an outlier (a stale or mis-stamped
answer): it is left out and the line fitted again.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

MAX_RTT_NS = 10_000_000
"""Exchanges with a longer round trip are refused [ns] (PX4's own limit)."""
STAMP_FLOOR_NS = 20_000
"""Added to every half round trip before weighting: stamps are no finer than this [ns]."""
MIN_EXCHANGES = 8
"""A fit needs this many exchanges."""


@dataclass(frozen=True)
class Exchange:
    sent_ns: int
    """Local clock when the request left [ns]."""
    received_ns: int
    """Local clock when the answer arrived [ns]."""
    remote_ns: int
    """The remote's stamp in the answer [ns]."""

    @property
    def rtt_ns(self) -> int:
        return self.received_ns - self.sent_ns


@dataclass(frozen=True)
class ClockFit:
    """remote = local + offset_ns + drift_ppm 1e-6 (local - ref_local_ns)."""

    ref_local_ns: int
    """The local time the offset refers to: the newest exchange's midpoint [ns]."""
    offset_ns: float
    """Remote minus local at ``ref_local_ns`` [ns]."""
    drift_ppm: float
    """How much faster the remote clock runs than the local one [parts per million]."""
    used: int
    """Exchanges in the fit."""
    outliers: int
    """Exchanges of the window left out as outliers."""
    rtt_min_ns: int
    residual_rms_ns: float
    span_ns: int
    """Local time from the oldest to the newest exchange used [ns]."""

    def remote_at(self, local_ns: int) -> float:
        """The remote clock at local time ``local_ns`` [ns]."""
        return local_ns + self.offset_ns + self.drift_ppm * 1e-6 * (local_ns - self.ref_local_ns)

    def local_at(self, remote_ns: int) -> float:
        """The local time at which the remote clock read ``remote_ns`` [ns]."""
        rate = 1.0 + self.drift_ppm * 1e-6
        ref_remote = self.ref_local_ns + self.offset_ns
        return self.ref_local_ns + (remote_ns - ref_remote) / rate


class TimesyncFilter:
    """The last ``window`` accepted exchanges and the line through them."""

    def __init__(self, window: int = 128, max_rtt_ns: int = MAX_RTT_NS) -> None:
        if window < MIN_EXCHANGES:
            raise ValueError(f"window must be at least {MIN_EXCHANGES}, got {window}")
        self.max_rtt_ns = max_rtt_ns
        self.exchanges: deque[Exchange] = deque(maxlen=window)
        self.refused = 0
        """Exchanges refused for their round trip (negative or above ``max_rtt_ns``)."""

    def add(self, ex: Exchange) -> bool:
        """Take an exchange; False if refused for its round trip."""
        if not 0 <= ex.rtt_ns <= self.max_rtt_ns:
            self.refused += 1
            return False
        self.exchanges.append(ex)
        return True

    def reset(self) -> None:
        """Forget every exchange (the remote rebooted: a new clock)."""
        self.exchanges.clear()

    def fit(self) -> ClockFit | None:
        """The line through the window's exchanges, or None with fewer than MIN_EXCHANGES."""
        return fit_exchanges(list(self.exchanges))


def fit_exchanges(exchanges: list[Exchange], rounds: int = 3) -> ClockFit | None:
    """Weighted least squares with outliers left out (see the module's text)."""
    if len(exchanges) < MIN_EXCHANGES:
        return None
    sent = np.array([e.sent_ns for e in exchanges], dtype=np.int64)
    received = np.array([e.received_ns for e in exchanges], dtype=np.int64)
    remote = np.array([e.remote_ns for e in exchanges], dtype=np.int64)
    mid2 = sent + received  # twice the midpoint, exactly
    ref2 = int(mid2[-1])
    x = (mid2 - ref2).astype(np.float64) / 2.0                 # local time from the reference [ns]
    y_int = 2 * remote - mid2                                   # twice (remote - midpoint)
    y0 = int(y_int[-1])
    y = (y_int - y0).astype(np.float64) / 2.0                   # remote - local, less y0/2 [ns]
    half_rtt = (received - sent).astype(np.float64) / 2.0
    w = 1.0 / (half_rtt + STAMP_FLOOR_NS) ** 2
    keep = np.ones(len(exchanges), dtype=bool)
    a = b = 0.0
    for _ in range(rounds):
        if keep.sum() < MIN_EXCHANGES:
            return None
        a, b = _weighted_line(x[keep], y[keep], w[keep])
        r = y - (a + b * x)
        sigma = 1.4826 * float(np.median(np.abs(r[keep])))
        new_keep = np.abs(r) <= half_rtt + STAMP_FLOOR_NS + 3.0 * sigma
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    if keep.sum() < MIN_EXCHANGES:
        return None
    r = (y - (a + b * x))[keep]
    xs = x[keep]
    return ClockFit(ref_local_ns=ref2 // 2, offset_ns=a + y0 / 2.0,
                    drift_ppm=b * 1e6, used=int(keep.sum()), outliers=int((~keep).sum()),
                    rtt_min_ns=int((received - sent)[keep].min()), residual_rms_ns=float(np.sqrt(np.mean(r * r))),
                    span_ns=int(xs.max() - xs.min()))


def _weighted_line(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """(a, b) minimising sum w (y - a - b x)^2."""
    sw = w.sum()
    xm = float((w * x).sum() / sw)
    ym = float((w * y).sum() / sw)
    dx = x - xm
    sxx = float((w * dx * dx).sum())
    b = float((w * dx * (y - ym)).sum()) / sxx if sxx > 0 else 0.0
    return ym - b * xm, b


START_CLOCK_MAX_ERROR_S = 0.005
"""The largest error of the clock a plan starts on [s]. A plan's places move with plan time, so two
drones whose clocks differ by d fly references v d apart: the case study's places move at 10 m/s
(10 m from the centre at 1 rad/s), and two clocks each within 5 ms of UTC are within 10 ms of each
other, 0.1 m at that speed, the paper's whole bound on the formation error."""


def start_clock_problem(synchronised: bool, max_error_s: float, fc_minus_companion_s: float | None,
                        bound_s: float = START_CLOCK_MAX_ERROR_S) -> str | None:
    """Why a plan must not start on this clock, or None. The plan runs on the flight controller's
    Unix time (its SYSTEM_TIME); its error is that clock's distance from the companion's
    (``fc_minus_companion_s``, through TIMESYNC; None: not known yet) plus the companion's own
    error bound (the kernel's ``max_error_s``, kept by NTP/chrony; ``synchronised`` False: none)."""
    if not synchronised:
        return "the companion's clock is not synchronised (no NTP/chrony lock): the swarm has no common start time"
    if fc_minus_companion_s is None:
        return "no TIMESYNC with the flight controller yet: its clock's error is unknown"
    error_s = abs(fc_minus_companion_s) + max_error_s
    if not error_s <= bound_s:
        return (f"the start clock may be {error_s * 1e3:.1f} ms off (flight controller {fc_minus_companion_s * 1e3:+.1f} ms "
                f"from the companion, whose error is up to {max_error_s * 1e3:.1f} ms), over {bound_s * 1e3:g} ms")
    return None
