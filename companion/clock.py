"""The flight controller's clock, as its telemetry tells it, and the answers it is owed in lockstep.

A companion runs on its flight controller's clock: SYSTEM_TIME gives the offset between the
controller's boot time and Unix time, and each sample's stamp (boot time) says how far that clock
has gone. Plan time, start times, leader commands and every timeout of the protocol are read on
it, so the same code runs in real time and on a simulator's clock (lockstep), where simulated
seconds may pass faster or slower than the wall's.

In lockstep (the flight controller's SIM_LOCKSTEP parameter is 1) the simulator steps on only
when the companion has answered the newest state it was sent: with its actuator command, whose
``time_usec`` is that state's boot time, or with a command of NaNs when it commands nothing.
An answer leaves as soon as it is ready, so that the simulator takes it in while the companion is
still at work on its other agents; when the state woke a wait (a start time: an arm command to send)
it leaves at the end of the loop's turn instead, after whatever the instant woke, which then reaches
the flight controller before the answer, at the same step.
"""

from __future__ import annotations

import asyncio
import ctypes
import heapq
import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass

from .telemetry import REBOOT_JUMP_US

OFFSET_STEP_US = 500_000
"""In flight, a SYSTEM_TIME that puts the flight controller's Unix time this far [us] from the one
flown on is a step of its clock (a GPS fix, someone setting it), not drift: it is not taken."""
OFFSET_SLEW_PPM = 200
"""In flight, smaller disagreements are taken at most this fast [us per s of the boot clock]: plan
time stays continuous while it follows the drift of a crystal (tens of ppm)."""


class FcClock:
    """Kept in whole microseconds: Unix times near 1.8e9 s hold no better than a quarter of a
    microsecond in a float, so plan times computed from them would differ in their last bits from
    one run to the next (and two lockstep runs would not be the same)."""

    def __init__(self) -> None:
        self.offset_us: int | None = None
        """Unix time minus the flight controller's boot time [us] (from SYSTEM_TIME)."""
        self.boot_us: int | None = None
        """The newest sample's flight-controller time [us since its boot]."""
        self._waiters: list = []
        self._order = itertools.count()
        self.steady = False
        """In flight: SYSTEM_TIME may slew the offset, not step it (``set_offset``)."""
        self.refused_step_us: int | None = None
        """The newest step of the flight controller's Unix time not taken in flight [us]."""
        self._set_at_ms: int | None = None

    @property
    def known(self) -> bool:
        return self.offset_us is not None

    def set_offset(self, time_unix_usec: int, time_boot_ms: int) -> None:
        """SYSTEM_TIME: the flight controller's Unix time [us] at its boot time [ms]. On the ground
        it is taken as it comes; in flight (``steady``) plan time runs on the boot clock: a
        disagreement above OFFSET_STEP_US is a step and is not taken (``refused_step_us``), a
        smaller one is taken at OFFSET_SLEW_PPM at most."""
        offset, boot_ms = int(time_unix_usec) - int(time_boot_ms) * 1000, int(time_boot_ms)
        if self.offset_us is None or not self.steady:
            self.offset_us, self._set_at_ms, self.refused_step_us = offset, boot_ms, None
            return
        diff = offset - self.offset_us
        if abs(diff) > OFFSET_STEP_US:
            self.refused_step_us = diff
            return
        room = max(0, boot_ms - self._set_at_ms) * OFFSET_SLEW_PPM // 1000
        self.offset_us += max(-room, min(room, diff))
        self._set_at_ms = boot_ms

    def set_steady(self, in_flight: bool) -> None:
        """In flight plan time runs on the boot clock (``set_offset``); on the ground SYSTEM_TIME is
        taken as it comes."""
        self.steady = in_flight

    def forget(self) -> None:
        """A new flight controller (a reboot, a clock that broke): its clock is learnt again from
        its SYSTEM_TIME; until then it is not known."""
        self.offset_us = self.boot_us = self._set_at_ms = self.refused_step_us = None
        self.steady = False

    def unix(self, boot_us: int) -> float:
        """A flight-controller time as Unix time (the wall clock until SYSTEM_TIME was heard)."""
        return time.time() if self.offset_us is None else (self.offset_us + boot_us) / 1e6

    def now(self) -> float:
        """The flight controller's time now, as Unix time: that of its newest sample."""
        if self.offset_us is None or self.boot_us is None:
            return time.time()
        return (self.offset_us + self.boot_us) / 1e6

    def plan_time(self, boot_us: int, start_unix_s: float) -> float:
        """A flight-controller time as plan time: seconds since ``start_unix_s``, exactly."""
        if self.offset_us is None:
            return time.time() - start_unix_s
        return (self.offset_us + boot_us - round(start_unix_s * 1e6)) / 1e6

    def _now_us(self) -> int | None:
        return None if self.offset_us is None or self.boot_us is None else self.offset_us + self.boot_us

    def advance(self, boot_us: int) -> bool:
        """A sample of time ``boot_us`` came: wake whoever waits for that time. True if it woke any."""
        self.boot_us = boot_us
        now_us = self._now_us()
        woke = False
        while now_us is not None and self._waiters and self._waiters[0][0] <= now_us:
            fut = heapq.heappop(self._waiters)[2]
            if not fut.done():
                fut.set_result(None)
                woke = True
        return woke

    async def until(self, t_unix: float) -> None:
        """Wait until the flight controller's clock reaches ``t_unix``."""
        t_us = round(t_unix * 1e6)
        now_us = self._now_us()
        if now_us is not None and now_us >= t_us:
            return
        fut = asyncio.get_running_loop().create_future()
        heapq.heappush(self._waiters, (t_us, next(self._order), fut))
        await fut


@dataclass(frozen=True)
class KernelClock:
    """What the kernel says of the wall clock (adjtimex, kept by NTP/chrony/ntpd)."""

    synchronised: bool
    max_error_s: float


class _Timex(ctypes.Structure):  # struct timex, <sys/timex.h> (Linux)
    _fields_ = [("modes", ctypes.c_uint), ("offset", ctypes.c_long), ("freq", ctypes.c_long),
                ("maxerror", ctypes.c_long), ("esterror", ctypes.c_long), ("status", ctypes.c_int),
                ("constant", ctypes.c_long), ("precision", ctypes.c_long), ("tolerance", ctypes.c_long),
                ("tv_sec", ctypes.c_long), ("tv_usec", ctypes.c_long), ("tick", ctypes.c_long),
                ("ppsfreq", ctypes.c_long), ("jitter", ctypes.c_long), ("shift", ctypes.c_int),
                ("stabil", ctypes.c_long), ("jitcnt", ctypes.c_long), ("calcnt", ctypes.c_long),
                ("errcnt", ctypes.c_long), ("stbcnt", ctypes.c_long), ("tai", ctypes.c_int), ("_pad", ctypes.c_int * 11)]


TIME_ERROR = 5   # adjtimex's answer: the clock is not synchronised
STA_UNSYNC = 0x0040


def kernel_clock() -> KernelClock:
    """The kernel's word on the wall clock: adjtimex with no change asked (any user may), its
    ``maxerror`` [us] the bound NTP/chrony keep on its error. Not Linux: not synchronised."""
    tx = _Timex()
    try:
        state = ctypes.CDLL(None, use_errno=True).adjtimex(ctypes.byref(tx))
    except (AttributeError, OSError):
        return KernelClock(False, float("inf"))
    synced = state not in (-1, TIME_ERROR) and not tx.status & STA_UNSYNC
    return KernelClock(synced, tx.maxerror / 1e6)


class Answers:
    """Lockstep's books: the newest state the flight controller sent, and what was answered."""

    def __init__(self, write: Callable[[bytes], None]) -> None:
        self.lockstep = False
        self._write = write
        self.due_us = -1        # the newest attitude stamp received (what a tick is of) [boot us]
        self.answered_us = -1   # the newest answered
        self._last_frame: bytes | None = None
        self._repeat = False
        self.defer = False
        """The state being answered woke a wait: its answer leaves at the end of the loop's turn."""
        self.holding = True
        """No answers yet: the companion is setting up. In lockstep the simulator's clock stands until
        every companion has answered, so a set-up takes no simulated time, however long it takes."""

    def telemetry(self, t_us: int) -> None:
        """An attitude message stamped ``t_us`` (the stream the companion ticks on)."""
        if t_us < self.due_us - REBOOT_JUMP_US:  # a restarted flight controller: a new clock
            self.answered_us = -1
            self.due_us = t_us
        elif t_us > self.due_us:
            self.due_us = t_us
        if t_us <= self.answered_us:
            self._repeat = True  # sent again: the answer may have been lost

    def answer_time(self, t_us: int) -> int:
        """The stamp an answer to a sample of ``t_us`` carries: the newest telemetry it answers
        (the streams of one state may carry stamps of their own)."""
        return max(t_us, self.due_us)

    def command(self, t_us: int, frame: bytes) -> None:
        """Send an actuator command answering the telemetry up to ``t_us`` (see ``defer``)."""
        self.answered_us = t_us
        self._last_frame = frame
        if self.lockstep and self.defer:
            asyncio.get_running_loop().call_soon(self._write, frame)
        else:
            self._write(frame)

    def settle(self, busy: bool, no_command: Callable[[int], bytes]) -> None:
        """After the telemetry was taken: in lockstep, answer what is due and not answered (unless
        a tick is still ``busy`` waiting for neighbours), and answer a repeated state again."""
        repeat, self._repeat = self._repeat, False
        if not self.lockstep or busy or self.holding:
            return
        if self.due_us > self.answered_us:
            self.command(self.due_us, no_command(self.due_us))
        elif repeat and self._last_frame is not None:
            asyncio.get_running_loop().call_soon(self._write, self._last_frame)
