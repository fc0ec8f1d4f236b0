"""Lockstep: the simulated clock advances only when every vehicle's companion has answered.

The SITL sends a vehicle's high-rate state (ATTITUDE, LOCAL_POSITION_NED, ...) on its companion
link; the companion answers with SET_ACTUATOR_CONTROL_TARGET whose ``time_usec`` is the
telemetry time it answers (boot time, microseconds), all controls NaN when it commands nothing.
The plant steps on only when every member has answered what it was sent, so a run is as fast as
the machine allows and behaves the same however slow or busy the machine is (PX4 and ArduPilot
SITL do the same with their simulators).

Members are the vehicles whose companions answer. The clock starts when every vehicle of the
process has answered once (it stands still until then, offering the current state again and
again, and says whom it waits for). Only a wall-clock watchdog takes a member out: a companion
silent for ``timeout_s`` has died or hung; the vehicle then flies on without it and its own
failsafe counts on simulated time. A member that answers again is back in at once, and the clock
waits for its answer to the newest state it was sent. An answer overdue by
``reoffer_s`` gets its state sent again (a datagram lost on a loaded machine costs a re-send,
not the run). This module keeps the books; ``server.py`` moves the datagrams.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from triswarm.protocol.mavlink import mavlink
from triswarm.protocol.stall import Stalls

NO_STALLS = Stalls(period_s=math.inf)
"""A watcher that never stalled: silence is wall time."""

HIGH_RATE_IDS = frozenset({mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                           mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mavlink.MAVLINK_MSG_ID_ODOMETRY,
                           mavlink.MAVLINK_MSG_ID_HIGHRES_IMU})
ATTITUDE_IDS = (mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mavlink.MAVLINK_MSG_ID_ODOMETRY)
"""A companion ticks on the first of these that its link streams (its preference: ``companion/autopilot.py``).
A datagram on a companion link with that one (with none of them streamed: any high-rate message) is a
state the companion must answer, with its stamp: streams of their own, with stamps and delays of their
own (``profiles.py``), are answered at the attitude the companion acts on."""


@dataclass(frozen=True)
class LockstepOptions:
    timeout_s: float = 10.0
    """Wall time without an answer after which a companion counts as dead and leaves lockstep [s]."""
    reoffer_s: float = 0.5
    """Wall time after which an unanswered state is sent again [s]."""
    max_rtf: float = float("inf")
    """Never faster than this many simulated seconds per wall second (1: at most real time, for a
    run watched or driven by tools on the wall clock)."""


@dataclass
class Lockstep:
    n: int
    options: LockstepOptions = field(default_factory=LockstepOptions)
    started: bool = False
    """Every vehicle has answered once: the clock runs."""
    members: set[int] = field(default_factory=set)
    awaiting: dict[int, list] = field(default_factory=dict)
    """Vehicle index -> [telemetry time it must answer (us), wall time sent, wall time last offered]."""
    last_sent_us: dict[int, int] = field(default_factory=dict)
    answered_us: dict[int, int] = field(default_factory=dict)
    """Per vehicle: the newest telemetry time answered [us]."""
    waited_wall_s: list[float] = field(default_factory=list)
    """Per vehicle: wall time from each state sent to its answer, summed (the clock stood that long
    for it, alone or with others) [s]."""
    left: list[tuple[int, float]] = field(default_factory=list)
    """(vehicle index, simulated time [s]) each time a member was taken out by the watchdog."""

    def __post_init__(self) -> None:
        self.waited_wall_s = [0.0] * self.n

    @property
    def blocked(self) -> bool:
        return not self.started or bool(self.awaiting)

    def sent(self, i: int, t_us: int, now_wall: float) -> None:
        """Vehicle i's companion was sent the state of telemetry time t_us."""
        self.last_sent_us[i] = max(t_us, self.last_sent_us.get(i, -1))
        if t_us <= self.answered_us.get(i, -1):
            return  # (already answered: a stream's message that left late)
        if i in self.members and i not in self.awaiting:
            self.awaiting[i] = [t_us, now_wall, now_wall]

    def answered(self, i: int, t_us: int, now_wall: float, command: bool = True) -> str | None:
        """Vehicle i's companion answered telemetry time t_us (at wall time ``now_wall``; ``command``:
        with an actuator command, not only a datagram of another kind). Returns what changed
        ("started", "back": vehicle i is a member again), or None."""
        said = None
        self.answered_us[i] = max(t_us, self.answered_us.get(i, -1))
        if i not in self.members and self.started and command:
            # back at its first answer, whatever state it answers: the clock then waits for its answer
            # to the newest state sent (one that answered late would otherwise fly on out of step,
            # its vehicle holding each command for as long as the companion took to catch up)
            self.members.add(i)
            said = "back"
            newest_us = self.last_sent_us.get(i, -1)
            if t_us < newest_us:
                self.awaiting[i] = [newest_us, now_wall, now_wall]
        elif i not in self.members and not self.started and t_us >= self.last_sent_us.get(i, 0):
            self.members.add(i)
            if len(self.members) == self.n:
                self.started = True
                said = "started"
        waiting = self.awaiting.get(i)
        if waiting is not None and t_us >= waiting[0]:
            del self.awaiting[i]
            self.waited_wall_s[i] += now_wall - waiting[1]
        return said

    def overdue(self, now_wall: float, sim_s: float, stalls: Stalls | None = None) -> tuple[list[int], list[int]]:
        """(vehicles whose state to send again, vehicles taken out now by the watchdog). Silence is
        counted as ``stalls`` (the SITL's own, looked at already) says: not over a stall of the SITL,
        in which nothing could be heard."""
        stalls = stalls or NO_STALLS
        offer, dropped = [], []
        for i, waiting in list(self.awaiting.items()):
            t_us, sent_wall, offered_wall = waiting
            if stalls.silent_s(sent_wall, now_wall) > self.options.timeout_s:
                del self.awaiting[i]
                self.members.discard(i)
                self.left.append((i, sim_s))
                dropped.append(i)
            elif now_wall - offered_wall > self.options.reoffer_s:
                waiting[2] = now_wall
                offer.append(i)
        return offer, dropped

    def missing(self) -> list[int]:
        """Before the clock starts: the vehicles whose companions have not answered yet."""
        return sorted(set(range(self.n)) - self.members)
