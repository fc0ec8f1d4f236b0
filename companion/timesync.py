"""TIMESYNC with the flight controller: requests on the companion's clock, answers into the filter
(``protocol.timesync``), and what it makes of the flight controller's clock.

The companion's clock is CLOCK_MONOTONIC (``time.monotonic_ns``): it never steps, and NTP/chrony
slew its rate as they slew the wall clock's, so a drift against it is a drift against the
disciplined clock. The offset is also given as the flight controller's boot time in Unix time
(through the wall clock now), which SYSTEM_TIME's own claim can be held against.

A request carries ``ts1`` = the companion's clock [ns] and targets the flight controller
(component 1); an answer is one with ``tc1`` set whose ``ts1`` is a request of ours still
outstanding (PX4 answers targeted; ArduPilot with both targets 0, which is taken too). An answer
far off the line (a rebooted flight controller) starts the fit again.
"""

from __future__ import annotations

import time
from collections import Counter, OrderedDict
from collections.abc import Callable

from triswarm.protocol.mavlink import mavlink
from triswarm.protocol.timesync import ClockFit, Exchange, TimesyncFilter

from .telemetry import REBOOT_JUMP_US

EVERY_S = 0.2
"""A request this often [s, wall] (PX4 sends its own at 10 Hz)."""
OUTSTANDING = 64
"""Requests remembered for their answer."""
REBOOT_JUMP_NS = REBOOT_JUMP_US * 1000
"""An answer this far off the fitted line: the flight controller's clock started again [ns] (the
telemetry's rule)."""


class TimeSync:
    """TIMESYNC of the companion of system ``sysid`` with its flight controller."""

    def __init__(self, send: Callable[[object], None], sysid: int, window: int = 128,
                 clock_ns: Callable[[], int] = time.monotonic_ns,
                 unix_minus_clock_ns: Callable[[], int] = lambda: time.time_ns() - time.monotonic_ns()) -> None:
        self._send = send
        self.sysid = sysid
        self.clock_ns = clock_ns
        self.unix_minus_clock_ns = unix_minus_clock_ns
        self.filter = TimesyncFilter(window)
        self.fit: ClockFit | None = None
        self.counters: Counter[str] = Counter()
        self._outstanding: OrderedDict[int, None] = OrderedDict()

    def request(self) -> None:
        t = self.clock_ns()
        self._outstanding[t] = None
        while len(self._outstanding) > OUTSTANDING:
            self._outstanding.popitem(last=False)
        msg = mavlink.MAVLink_timesync_message(0, t)
        if "target_system" in msg.get_fieldnames():  # (common.xml's later extension fields)
            msg.target_system, msg.target_component = self.sysid, mavlink.MAV_COMP_ID_AUTOPILOT1
        self._send(msg)
        self.counters["requests"] += 1

    def take(self, msg) -> None:
        """A TIMESYNC from the flight controller."""
        received = self.clock_ns()
        if msg.tc1 == 0:
            self.counters["requests_heard"] += 1  # (the flight controller's own; it needs no answer)
            return
        if getattr(msg, "target_system", 0) not in (0, self.sysid) or msg.ts1 not in self._outstanding:
            self.counters["answers_not_ours"] += 1
            return
        del self._outstanding[msg.ts1]
        ex = Exchange(int(msg.ts1), received, int(msg.tc1))
        if self.fit is not None and abs(self.fit.remote_at((ex.sent_ns + ex.received_ns) // 2) - ex.remote_ns) > REBOOT_JUMP_NS:
            self.filter.reset()
            self.counters["restarts"] += 1
        if self.filter.add(ex):
            self.counters["answers"] += 1
            self.fit = self.filter.fit()
        else:
            self.counters["answers_slow"] += 1

    def fc_boot_unix_s(self) -> float | None:
        """Unix time of the flight controller's boot, as the fit and the wall clock say."""
        if self.fit is None:
            return None
        return (self.fit.local_at(0) + self.unix_minus_clock_ns()) / 1e9

    def report(self) -> dict:
        """For the health report and the stats (None where there is no fit yet)."""
        f = self.fit
        return {
            "fc_clock_drift_ppm": None if f is None else round(f.drift_ppm, 2),
            "fc_clock_offset_ns": None if f is None else round(f.offset_ns),
            "fc_clock_ref_ns": None if f is None else f.ref_local_ns,
            "fc_boot_unix_s": self.fc_boot_unix_s(),
            "fc_clock_rtt_min_us": None if f is None else round(f.rtt_min_ns / 1e3, 1),
            "fc_clock_residual_us": None if f is None else round(f.residual_rms_ns / 1e3, 1),
            "fc_clock_span_s": None if f is None else round(f.span_ns / 1e9, 1),
            "fc_clock_exchanges": 0 if f is None else f.used,
            "fc_clock_outliers": 0 if f is None else f.outliers,
            "timesync": dict(self.counters, refused_rtt=self.filter.refused),
        }
