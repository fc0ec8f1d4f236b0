"""What a fuzzer reports: the inputs it sent by kind, how fast, the companion's own counters that
should have moved, what they should have moved by, and the problems seen (a difference, a crash, a
companion that stopped answering)."""

from __future__ import annotations

import re
from pathlib import Path
import time
from collections import Counter
from dataclasses import dataclass, field

CRASH_MARKS = ("Traceback", "Exception in callback", "exception was never retrieved", "Error in ")
"""What a companion's log holds when something raised where nothing should have (asyncio reports
an exception in a reader or a callback this way and goes on: the fuzzers treat it as a crash)."""


@dataclass
class Report:
    face: str
    inputs: int = 0
    seconds: float = 0.0
    sent: Counter = field(default_factory=Counter)
    counters: dict = field(default_factory=dict)
    """The companion's counters concerned, as it reported them."""
    expected: dict = field(default_factory=dict)
    """What those counters should be (the oracle's count); a key missing from ``counters`` is 0."""
    slack: dict = field(default_factory=dict)
    """How far below ``expected`` a counter may be: inputs sent on a link that the transport closed
    before they were confirmed delivered (the target stalled past its lease: not the parser's doing)."""
    other: dict = field(default_factory=dict)
    """Counters that moved but that the oracle does not predict exactly (shown, not judged)."""
    problems: list[str] = field(default_factory=list)

    @property
    def rate(self) -> float:
        return self.inputs / self.seconds if self.seconds > 0 else 0.0

    def compare(self) -> None:
        """A problem for every counter that is not what it should be."""
        for key, want in sorted(self.expected.items()):
            got = self.counters.get(key, 0)
            least = want - self.slack.get(key, 0)
            if not least <= got <= want:
                self.problems.append(f"counter {key}: counted {got}, expected {want}"
                                     + (f" (at least {least})" if least != want else ""))

    def text(self) -> str:
        lines = [f"{self.face}: {self.inputs} inputs in {self.seconds:.1f} s ({self.rate:,.0f} inputs/s)",
                 "  sent: " + ", ".join(f"{k} {n}" for k, n in sorted(self.sent.items())),
                 "  counters: " + ", ".join(f"{k} {self.counters.get(k, 0)} (expected {n}"
                                            + (f", at least {n - self.slack[k]})" if self.slack.get(k) else ")")
                                            for k, n in sorted(self.expected.items()))]
        if self.other:
            lines.append("  also: " + ", ".join(f"{k} {n}" for k, n in sorted(self.other.items())))
        lines += [f"  PROBLEM: {p}" for p in self.problems]
        return "\n".join(lines)


class Clock:
    """Times the fuzzing itself (not the start-up)."""

    def __enter__(self) -> "Clock":
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        self.seconds = time.perf_counter() - self.t0


def crashes(log: str) -> list[str]:
    """What raised in a companion's log (see CRASH_MARKS), once per exception and place, with how
    many times: "3 x ValueError: ... (companion/bus.py:321)"."""
    seen: Counter[str] = Counter()
    lines = log.splitlines()
    for k, line in enumerate(lines):
        if not line.startswith("Traceback"):
            continue
        where, end = "", k + 1
        while end < len(lines) and (lines[end].startswith(" ") or not lines[end].strip()):
            m = re.match(r'\s+File "([^"]+)", line (\d+)', lines[end])
            if m:
                where = f"{Path(m.group(1)).parent.name}/{Path(m.group(1)).name}:{m.group(2)}"
            end += 1
        what = lines[end] if end < len(lines) else "?"
        seen[f"{what[:200]} ({where})"] += 1
    if not seen and any(mark in log for mark in CRASH_MARKS):
        seen["an error in the log, without a traceback"] += 1
    return [f"{n} x {what}" for what, n in seen.items()]


def kernel_drops(port: int) -> int:
    """Datagrams the kernel dropped at the UDP socket bound to 127.0.0.1:``port`` (a full receive
    buffer): the counts cannot add up if it is not 0. 0 if there is no such socket."""
    try:
        text = Path("/proc/net/udp").read_text()
    except OSError:
        return 0
    want = f"0100007F:{port:04X}"
    for line in text.splitlines()[1:]:
        fields = line.split()
        if len(fields) > 12 and fields[1] == want:
            return int(fields[-1])
    return 0


def drop_keys(counters: dict) -> dict:
    """The counters of what was dropped or refused."""
    return {k: n for k, n in counters.items() if re.match(r"(drop|refused)_", k)}
