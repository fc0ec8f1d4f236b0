"""`triswarm sitl up --lockstep` over real UDP and real MAVLink framing, with the test as the
companions: the clock stands until every vehicle's companion answers, then advances one control
step per round of answers and never without them; an unanswered state is sent again; a companion
that stays silent is taken out by the wall-clock watchdog, and its vehicle's failsafe then runs on
simulated time; and, on the books alone, one that answers again is back at once."""

from __future__ import annotations

import math
import socket
import time

import pytest
from pymavlink import mavutil

from triswarm.protocol.mavlink import CustomMode
from triswarm.sitl.lockstep import Lockstep, LockstepOptions

from .poll import poll
from .sitl_helpers import command, sitl_process

M = mavutil.mavlink
NAN8 = [math.nan] * 8


class Companion:
    """A companion of the test's own on a vehicle's companion link (pymavlink, real UDP)."""

    def __init__(self, url: str, sysid: int) -> None:
        self.sysid = sysid
        self.conn = mavutil.mavlink_connection(url, source_system=sysid, source_component=191)
        # (room for every datagram while the test reads another link: a silent companion's vehicle
        # streams at the clock's pace, which with one member left is many times the wall's)
        self.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        self.last_ms = -1

    def hello(self) -> None:
        self.conn.mav.heartbeat_send(M.MAV_TYPE_ONBOARD_CONTROLLER, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def state(self, timeout_s: float = 3.0, again: bool = False) -> int | None:
        """The time [boot ms] of the next LOCAL_POSITION_NED newer than the last one (``again``: or
        the same one sent again), or None."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            m = self.conn.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=left)
            if m is not None and (m.time_boot_ms > self.last_ms or (again and m.time_boot_ms == self.last_ms)):
                self.last_ms = m.time_boot_ms
                return m.time_boot_ms
        return None

    def answer(self, boot_ms: int, controls=NAN8) -> None:
        self.conn.mav.set_actuator_control_target_send(boot_ms * 1000, 0, self.sysid, 1, controls)

    def drain(self) -> list:
        """Everything waiting (a few reads: pymavlink returns one message at a time)."""
        out = []
        for _ in range(1000):
            m = self.conn.recv_match(blocking=False)
            if m is None:
                break
            out.append(m)
        return out

    def until_answered(self) -> list:
        """Everything this link gets before the answer to a parameter read sent now. The SITL takes
        a link's datagrams in order and steps its clock in the callback that takes an answer, so any
        state it sent after the datagrams before the read (a step they caused) is in this list."""
        self.conn.mav.param_request_read_send(self.sysid, 1, b"MASS_KG", -1)
        got: list = []

        def take() -> None:
            m = self.conn.recv_match(blocking=True, timeout=0.05)
            if m is not None:
                got.append(m)

        poll(lambda: got and got[-1].get_type() == "PARAM_VALUE" and got[-1].param_id == "MASS_KG", 3.0,
             "the answer to a parameter read", every_s=0.0, step=take)
        return got[:-1]

    def close(self) -> None:
        self.conn.close()


def newer(msgs: list, than_ms: int) -> list:
    """The states among ``msgs`` newer than ``than_ms``."""
    return [m.time_boot_ms for m in msgs if m.get_type() == "LOCAL_POSITION_NED" and m.time_boot_ms > than_ms]


def test_the_clock_waits_for_every_companion_and_steps_only_on_their_answers(tmp_path):
    with sitl_process(tmp_path, 2, "--lockstep", "--rate-hz", "200") as (manifest, _):
        assert manifest["clock"]["lockstep"]
        a, b = (Companion(v["links"]["companion"]["pymavlink"], v["sysid"]) for v in manifest["vehicles"])
        try:
            a.hello()
            t0 = a.state()
            assert t0 is not None, "no state offered while the clock stands"
            a.answer(t0)  # vehicle 1 is in; vehicle 2's companion has not spoken: the clock stands
            assert newer(a.until_answered(), t0) == []
            b.hello()
            t0b = b.state()
            assert t0b == t0  # (the state it is offered is the current one: the clock stood until now)
            b.answer(t0b)  # every companion has answered: the clock runs, one control step (5 ms) at a time
            times = []
            for _ in range(20):
                ta, tb = a.state(), b.state()
                assert ta == tb is not None
                times.append(ta)
                if len(times) == 10:
                    # a pause of the companions is a pause of the clock: the next state vehicle 1's
                    # companion gets is the same one offered again, after the clock stood 0.5 s
                    assert a.state(timeout_s=3.0, again=True) == ta
                a.answer(ta)
                b.answer(tb)
            assert [t1 - t2 for t1, t2 in zip(times[1:], times)] == [5] * 19
            # one companion late: nothing moves until it answers
            ta, tb = a.state(), b.state()
            a.answer(ta)
            # its state is offered again (same instant) while the clock waits for it; and up to then
            # (the read's answer comes after anything sent before it) vehicle 1's companion got no newer one
            again = b.state(timeout_s=2.0, again=True)
            assert again == tb
            assert newer(a.until_answered(), ta) == []
            b.answer(tb)
            assert a.state() == ta + 5
        finally:
            a.close()
            b.close()
    # the answers commanded nothing (all NaN): counted as such, never as bad frames
    import json

    stats = json.loads((tmp_path / "stats.json").read_text())
    for v in stats["vehicles"]:
        assert v["counters"]["actuator_no_command"] >= 22 and v["drops"] == 0, v
    assert stats["lockstep"]["started"] and stats["lockstep"]["left"] == []


@pytest.mark.realtime  # (the watchdog is on the wall clock: a stall of this process silences vehicle 1's companion too)
def test_a_silent_companion_leaves_lockstep_and_its_failsafe_runs_on_simulated_time(tmp_path):
    with sitl_process(tmp_path, 2, "--lockstep", "--rate-hz", "200", "--lockstep-timeout-s", "1") as (manifest, _):
        a, b = (Companion(v["links"]["companion"]["pymavlink"], v["sysid"]) for v in manifest["vehicles"])
        try:
            for c in (a, b):
                c.hello()
                c.answer(c.state())
            # vehicle 2: armed (on the ground: its companion's idle command), in EXTERNAL
            assert command(b.conn, 2, M.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == M.MAV_RESULT_ACCEPTED
            idle = [0.05, 0.05, 0.05, 0.0, 0.0, 0.0, 0.0, 0.0]
            for _ in range(10):
                ta, tb = a.state(), b.state()
                a.answer(ta)
                b.answer(tb, idle)
            # vehicle 2's companion stops answering (its link stays: a hung controller): after 1 s of
            # wall time the clock runs on without it
            t_silent = tb
            t_wall = time.monotonic()
            ta = a.state()
            a.answer(ta)
            while (ta := a.state()) is not None and ta < t_silent + 2000:
                a.answer(ta)
            assert ta is not None and time.monotonic() - t_wall >= 1.0
            # and its flight controller's failsafe counted 10 s of simulated time (DISARM_PRFLT_S
            # on the ground): it disarmed, in simulated time, while vehicle 1's companion set the pace
            texts = []
            while (ta := a.state()) is not None and ta < t_silent + 12000:
                a.answer(ta)
                texts += [m.text for m in b.drain() if m.get_type() == "STATUSTEXT"]
                if ta % 1000 == 0:
                    b.hello()
            assert any("no actuator command for 10 s on ground" in t for t in texts), texts
        finally:
            a.close()
            b.close()
    import json

    stats = json.loads((tmp_path / "stats.json").read_text())
    assert stats["lockstep"]["left"][0]["sysid"] == 2  # (vehicle 1's may follow: the test stops answering at its end)
    assert not stats["vehicles"][1]["armed"] and stats["vehicles"][1]["mode"] == CustomMode.EXTERNAL.name


@pytest.mark.parametrize("args, message", [
    (["--lockstep", "--speedup", "2"], "--speedup and --lockstep exclude each other"),
    (["--lockstep", "--lockstep-timeout-s", "0"], "--lockstep-timeout-s must be positive"),
])
def test_bad_lockstep_options_are_one_sentence(tmp_path, args, message):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "triswarm.gcs.cli", "sitl", "up", "-n", "1", "--manifest",
                        str(tmp_path / "m.json"), *args], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_a_companion_that_answers_again_is_back_at_once_and_awaited_for_the_newest_state():
    """The books alone (``sitl/lockstep.py``, no I/O): a companion that left answers a state long
    gone, as a restarted one does. It is back at once, and the clock stands until it answers the
    newest state it was sent; a datagram that is not an answer (a heartbeat) does not bring it back."""
    ls = Lockstep(2, LockstepOptions(timeout_s=1.0))
    for i in (0, 1):
        ls.sent(i, 5_000, 0.0)
    assert ls.answered(0, 5_000, 0.0) is None and ls.answered(1, 5_000, 0.0) == "started" and not ls.blocked
    ls.sent(0, 10_000, 0.1)
    ls.sent(1, 10_000, 0.1)
    ls.answered(0, 10_000, 0.1)
    assert ls.blocked and ls.overdue(1.5, 0.01) == ([], [1])  # vehicle 2's companion silent: out
    assert not ls.blocked
    for k in range(2, 40):  # the clock runs on with vehicle 1's companion alone
        ls.sent(0, 5_000 * k, 2.0)
        ls.sent(1, 5_000 * k, 2.0)
        ls.answered(0, 5_000 * k, 2.0)
        assert not ls.blocked
    assert ls.answered(1, 10_000, 2.1, command=False) is None and not ls.blocked  # a heartbeat
    assert ls.answered(1, 10_000, 2.2) == "back"  # an answer, however old
    assert ls.blocked and ls.awaiting[1][0] == 5_000 * 39
    ls.answered(1, 5_000 * 39, 2.3)
    assert not ls.blocked
