"""Pure logic of the companion: MAVLink routing rules, loop-health statistics; and whom a
ground-station link sends to, over real loopback sockets."""

import asyncio
import math
import socket
import time

import numpy as np
import pytest

from triswarm.companion.health import LoopHealth, Window
from triswarm.companion.links import MavLink, Router
from triswarm.protocol.mavlink import mavlink, new_codec


def frame(msg, sysid: int, compid: int):
    """The message as a receiver sees it (parsed from real MAVLink 2 bytes)."""
    data = msg.pack(new_codec(sysid, compid))
    parsed = new_codec(99, 99).parse_buffer(data)
    assert parsed and len(parsed) == 1
    return parsed[0]


class Link:
    def __init__(self, name):
        self.name = name

    def __repr__(self):
        return self.name


@pytest.fixture
def routed():
    """Companion of system 3 (component 191) between its flight controller and a ground station."""
    fc, gcs = Link("fc"), Link("gcs")
    r = Router(3, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
    r.learn(fc, frame(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 0, 3), 3, 1))
    r.learn(gcs, frame(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3), 255, 190))
    return r, fc, gcs


def test_broadcasts_go_everywhere_but_back(routed):
    r, fc, gcs = routed
    hb = frame(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 0, 3), 3, 1)
    assert r.destinations(fc, hb, [fc, gcs]) == [gcs]
    assert r.for_me(hb)  # a broadcast is also for this component
    req = frame(mavlink.MAVLink_param_request_list_message(0, 0), 255, 190)
    assert r.destinations(gcs, req, [fc, gcs]) == [fc] and r.for_me(req)


def test_targeted_messages_go_where_the_target_was_heard(routed):
    r, fc, gcs = routed
    to_autopilot = frame(mavlink.MAVLink_param_request_list_message(3, 1), 255, 190)
    assert r.destinations(gcs, to_autopilot, [fc, gcs]) == [fc]
    assert not r.for_me(to_autopilot)
    to_gcs = frame(mavlink.MAVLink_command_ack_message(400, 0, 0, 0, 255, 190), 3, 1)
    assert r.destinations(fc, to_gcs, [fc, gcs]) == [gcs]
    to_system = frame(mavlink.MAVLink_param_request_list_message(3, 0), 255, 190)  # every component of 3
    assert r.destinations(gcs, to_system, [fc, gcs]) == [fc] and r.for_me(to_system)


def test_messages_for_this_component_stay_here(routed):
    r, fc, gcs = routed
    mine = frame(mavlink.MAVLink_param_request_list_message(3, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER), 255, 190)
    assert r.destinations(gcs, mine, [fc, gcs]) == [] and r.for_me(mine)


def test_unknown_targets_are_not_forwarded(routed):
    r, fc, gcs = routed
    other_system = frame(mavlink.MAVLink_param_request_list_message(7, 1), 255, 190)
    assert r.destinations(gcs, other_system, [fc, gcs]) == []
    assert not r.for_me(other_system)
    unheard_component = frame(mavlink.MAVLink_param_request_list_message(3, 100), 255, 190)
    assert r.destinations(gcs, unheard_component, [fc, gcs]) == []


@pytest.mark.realtime  # (the client timeout is on the wall clock: a stall of this process ages the stations)
def test_a_ground_station_link_sends_to_every_station_heard_lately():
    """Two ground stations on one udpin port both get what the companion sends; one that falls
    silent for longer than the client timeout stops getting it, unless it is the only one; one heard
    again gets what follows, and nothing of what it missed."""
    loop = asyncio.new_event_loop()
    stations = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    link = MavLink("gcs", "udpin:127.0.0.1:0", 3, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER, client_timeout_s=0.5)
    try:
        link.open(loop, lambda *args: None)
        port = link.conn.port.getsockname()[1]
        heartbeat = mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(new_codec(255, 190))
        for s in stations:
            s.bind(("127.0.0.1", 0))
            s.settimeout(1.0)

        def speak(station) -> None:
            """A heartbeat from the station, read by the link (as the loop's reader would)."""
            before = link.counters["rx"]
            station.sendto(heartbeat, ("127.0.0.1", port))
            deadline = time.monotonic() + 2.0
            while link.counters["rx"] == before and time.monotonic() < deadline:
                link._readable()
            assert link.counters["rx"] == before + 1

        def heard(station) -> bytes | None:
            try:
                return station.recv(1024)
            except socket.timeout:
                return None

        speak(stations[0])
        speak(stations[1])
        link.write(b"to both")
        assert [heard(s) for s in stations] == [b"to both", b"to both"]
        time.sleep(0.6)  # (longer than the client timeout)
        speak(stations[1])  # station 0 has been silent for 0.6 s
        link.write(b"to the one heard")
        assert heard(stations[1]) == b"to the one heard"
        time.sleep(0.6)  # now both are silent: one is kept
        link.write(b"to the last")
        assert heard(stations[1]) == b"to the last"
        # station 0 heard again: the first datagram it gets is the next one (the two above, sent on
        # the same socket before it, would have come first); station 1, silent, is dropped now
        speak(stations[0])
        link.write(b"to the one back")
        assert heard(stations[0]) == b"to the one back"
        speak(stations[1])
        link.write(b"to both again")
        assert [heard(s) for s in stations] == [b"to both again", b"to both again"]
    finally:
        link.close()
        loop.close()
        for s in stations:
            s.close()


def test_window_percentiles_match_numpy_within_two_percent():
    rng = np.random.default_rng(7)
    w = Window(n=50)
    values = rng.lognormal(mean=math.log(1e-3), sigma=1.0, size=20000)
    for v in values:
        w.add(float(v))
    for q in (1, 50, 90, 99, 99.9):
        exact = np.percentile(values, q, method="inverted_cdf")  # the same definition: the smallest value with rank >= q %
        assert w.percentile(q, recent=False) == pytest.approx(exact, rel=0.011)  # half a bin
    assert w.percentile(50) == pytest.approx(np.percentile(values[-50:], 50))  # the recent window is exact
    assert len(w.recent) == 50 and w.count == 20000
    assert Window().percentile(99, recent=False) != Window().percentile(99, recent=False)  # nan when empty


def test_loop_health_counts_misses_not_the_flight_controllers_lag():
    h = LoopHealth(0.005)
    h.skipped(missed=20)  # while setting up, before the first command: not a miss
    assert h.deadline_misses == 0
    t = 1000.0
    for k in range(10):
        h.tick(t + 0.005 * k, t + 0.005 * k + 0.0004)
    h.tick(t + 0.05, t + 0.05 + 0.006)  # answered after more than one period: a miss
    h.skipped(missed=2, superseded=3)
    assert h.ticks == 11
    assert h.deadline_misses == 3
    assert h.skipped_samples == 5 and h.superseded_samples == 3
    s = h.summary()
    assert s["latency_p50_ms"] == pytest.approx(0.4, rel=0.02)
    assert s["jitter_p99_ms"] == pytest.approx(5.6, rel=0.02)  # commands 10.6 ms apart: 5.6 ms late


def test_mission_state_survives_a_restart_and_a_bad_file(tmp_path, paper_spec):
    from triswarm.companion.state import Mission, StateStore
    from triswarm.protocol.codec import plan_id

    store = StateStore(tmp_path / "state")
    assert store.load() is None and store.problem is None
    m = Mission(paper_spec, plan_id(paper_spec), 3, start_unix_s=1.8e9, phase="flying")
    store.save(m)
    assert StateStore(tmp_path / "state").load() == m
    assert [p.name for p in (tmp_path / "state").iterdir()] == ["mission.json"]  # no temporary left behind
    store.path.write_text('{"plan_spec": {}, "agen')  # a torn write (what the rename prevents)
    fresh = StateStore(tmp_path / "state")
    assert fresh.load() is None and "unusable saved mission" in fresh.problem
    assert StateStore(None).load() is None  # no folder: nothing kept, nothing to fail


def test_a_neighbour_counts_on_its_fresh_estimates_even_without_its_liveliness():
    """Whom an agent counts present (Flight.usable): an in-neighbour with a fresh estimate of this
    plan counts even when its liveliness token never arrived (Zenoh lost the declaration); one with
    no liveliness and a stale estimate, or no estimate, does not; an agent we do not listen to still
    needs its liveliness."""
    from types import SimpleNamespace

    from triswarm.companion.bus import Neighbour
    from triswarm.companion.flight import Flight
    from triswarm.companion.liveliness import LOCKSTEP_GRACE_S
    from triswarm.protocol.codec import AgentStatus

    plan, timeout_s = 7, 0.2
    estimates = {j: Neighbour() for j in (2, 3, 4)}
    bus = SimpleNamespace(alive={1, 4}, changes=0, estimates=estimates, status_of=lambda j, plans: None)
    fc = SimpleNamespace(now_unix=lambda: 1000.0, answers=SimpleNamespace(lockstep=False))
    flight = Flight(1, fc, None, SimpleNamespace(values={"NB_TIMEOUT_S": timeout_s}),
                    None, None, autostart=False, on_phase=None, controller_reset=None, lead_s=None, entry=None)
    flight.opened(bus, frozenset({2, 3}), (plan,))
    flight.t_p = 50.0
    for j, t_plan in ((2, 50.0 - 0.01), (3, 50.0 - 1.0)):
        nb = estimates[j]
        nb.seq, nb.t_plan_s, nb.status, nb.plan_id, nb.xi = 1, t_plan, AgentStatus.FLYING, plan, np.zeros(12)
    assert flight.usable(2)  # no liveliness, estimate 10 ms old: counts
    assert not flight.usable(2, check_fresh=False)  # but lockstep waits only for the living
    assert not flight.usable(3) and flight.why_absent(3).startswith("no liveliness, status ?, estimate")  # stale
    assert flight.usable(4)  # not listened to, alive
    bus.alive.discard(4)
    bus.changes += 1
    assert not flight.usable(4) and flight.why_absent(4) == "no liveliness"
    # in lockstep, a token gone counts only after LOCKSTEP_GRACE_S of plan time (a starved machine
    # expires Zenoh's lease on the wall clock while the flight's clock stands)
    fc.answers.lockstep = True
    bus.alive.add(4)
    bus.changes += 1
    assert flight.usable(4)
    bus.alive.discard(4)
    bus.changes += 1
    assert flight.usable(4) and flight.usable(4)
    bus.alive.add(2)  # (not a neighbour listened to: its estimates speak for it, the wait is not for it)
    bus.changes += 1
    assert flight.usable(2, check_fresh=False)
    bus.alive.discard(2)
    bus.changes += 1
    assert not flight.usable(2, check_fresh=False) and flight.usable(2) and flight.usable(4)
    flight.t_p = 50.0 + LOCKSTEP_GRACE_S
    assert not flight.usable(4) and flight.why_absent(4) == "no liveliness"
    flight.t_p = 50.0
    fc.answers.lockstep = False
    estimates[2].plan_id = plan + 1  # another plan's estimates are no sign of this plan's neighbour
    assert not flight.usable(2)


def test_only_a_new_sample_ends_a_wait_for_the_neighbours():
    """A tick waiting for its neighbours' estimates acts on what there is when its flight controller
    sends a new sample (real time: the next period has come). Any other read of that link (a
    HEARTBEAT, a state the lockstep offers again) leaves the wait as it is: acting then made two
    lockstep runs differ on a loaded machine, the wait cut short by a heartbeat in one of them."""
    import asyncio
    from collections import deque
    from types import SimpleNamespace

    from triswarm.companion.loop import ControlLoop

    loop = asyncio.new_event_loop()
    try:
        ctl = ControlLoop(loop, 1)
        finished, settled = [], []
        ctl._finish = finished.append
        fc = SimpleNamespace(backlog=deque(), settle=settled.append, take_woke=lambda: False)
        class Agent:  # (hashable, as the loop's agents are)
            clock_broke = staticmethod(lambda s: True)  # (the new sample itself is not flown here)

        agent = Agent()
        agent.fc = fc
        tick = SimpleNamespace(agent=agent, next_wall=time.monotonic() + 60.0)
        ctl.waiting[agent] = tick
        ctl._run([agent])  # a read with no new sample
        assert ctl.waiting == {agent: tick} and not finished and settled == [True]
        fc.backlog.append(SimpleNamespace())  # a new sample
        ctl._run([agent])
        assert not ctl.waiting and finished == [[tick]] and settled[-1] is False
        ctl.close()
    finally:
        loop.close()


def test_a_stall_that_began_in_a_wait_is_not_a_neighbours_silence(monkeypatch):
    """Lockstep: a tick waits for neighbour 1's estimate; the whole machine stops for 6.5 s (longer
    than NB_WATCHDOG_S); at the wake the loop's first look at who is alive must see the stall and
    count the neighbour's silence from the wake, not from its last estimate (which came before the
    stall): a neighbour whose state came during the stall is not hung. Nor is one whose link came
    back after the wake (its liveliness token came again: the stall closed the Zenoh links, and what
    it sent meanwhile was lost) until it has been silent for NB_WATCHDOG_S since. A neighbour that
    then stays silent for NB_WATCHDOG_S of looks is still counted absent."""
    import asyncio
    from types import SimpleNamespace

    from triswarm.companion import loop as loop_mod
    from triswarm.companion.loop import LOCKSTEP_RECHECK_S, NB_WATCHDOG_S, ControlLoop

    clock = {"mono": 100.0, "unix": 1.8e9}
    monkeypatch.setattr(loop_mod, "time", SimpleNamespace(monotonic=lambda: clock["mono"], time=lambda: clock["unix"]))

    def advance(s: float) -> None:
        clock["mono"] += s
        clock["unix"] += s

    warnings: list[str] = []

    class Agent:  # (hashable, as the loop's agents are)
        lockstep, nb_wait_s, dt_s = True, 0.05, 0.005
        in_neighbours = {"chain": [1]}
        topology_at = staticmethod(lambda t_p: SimpleNamespace(name="chain"))
        estimates_in = staticmethod(lambda agents, t_p: not agents)
        flight = SimpleNamespace(usable=lambda j, check_fresh=True: True, silent={})
        bus = SimpleNamespace(estimates={1: SimpleNamespace(received_at=clock["unix"] - 0.005)}, token_at={})
        fc = SimpleNamespace(settle=lambda woke: None)
        log = SimpleNamespace(warning=warnings.append)

    agent = Agent()
    loop = asyncio.new_event_loop()
    try:
        ctl = ControlLoop(loop, 1)
        ctl._finish = lambda ticks: None
        tick = SimpleNamespace(agent=agent, t_p=20.34)
        ctl._wait([tick])
        assert ctl.waiting == {agent: tick}
        advance(6.5)  # the machine stopped
        ctl._timeout()
        assert not agent.flight.silent and not warnings, warnings

        def look(for_s: float) -> None:  # regular looks, no estimate
            for _ in range(round(for_s / LOCKSTEP_RECHECK_S)):
                advance(LOCKSTEP_RECHECK_S)
                ctl._timeout()

        look(0.6 * NB_WATCHDOG_S)
        agent.bus.token_at[1] = clock["mono"]  # its link is back
        look(0.9 * NB_WATCHDOG_S)  # (past NB_WATCHDOG_S since the wake)
        assert not agent.flight.silent and not warnings, warnings
        look(0.1 * NB_WATCHDOG_S + 0.2)
        assert 1 in agent.flight.silent and len(warnings) == 1, (agent.flight.silent, warnings)
        ctl.close()
    finally:
        loop.close()


def test_one_stamp_out_of_place_is_dropped_and_a_reboot_is_still_found(monkeypatch):
    """A sample stamped far behind the flight controller's clock, or far ahead of it, is not flown;
    if the next one is on the old clock it was a stamp out of place (a hostile or corrupted
    message): dropped and counted, and the flight controller is not lost. So are samples off the
    clock that come faster than the flight controller could have rebooted (a flood between two of
    its own). A rebooted flight controller, whose samples all run on a new clock, is lost once
    CLOCK_BREAK_SAMPLES of them have come over CLOCK_BREAK_S."""
    from collections import Counter
    from types import SimpleNamespace

    from triswarm.companion import agent as agent_mod
    from triswarm.companion.agent import CLOCK_BREAK_S, CLOCK_BREAK_SAMPLES, Agent

    wall = {"s": 100.0}
    monkeypatch.setattr(agent_mod, "time", SimpleNamespace(monotonic=lambda: wall["s"]))

    def agent():
        a = SimpleNamespace(fc_lost_since=None, _last_boot=None, _off_clock=[], lost=[],
                            fc=SimpleNamespace(assembler=SimpleNamespace(counters=Counter())))
        a.fc_lost = lambda reason: (a.lost.append(reason), setattr(a, "fc_lost_since", 1.0))
        a._drop_off_clock = lambda: Agent._drop_off_clock(a)
        return a

    def broke(a, boot_s: float, after_s: float = 0.005) -> bool:
        wall["s"] += after_s
        return Agent.clock_broke(a, SimpleNamespace(boot_us=round(boot_s * 1e6)))

    for stray_s in (1.0, 0.0, 60.0):  # behind (a reboot's look, at 0 too), far ahead
        a = agent()
        assert [broke(a, t) for t in (10.000, 10.005)] == [False, False]
        assert broke(a, stray_s) is True  # (not flown)
        assert broke(a, 10.010) is False and not a.lost
        assert a.fc.assembler.counters["samples_off_the_clock"] == 1
    a = agent()  # strays that do not run on from each other are not a new clock
    assert [broke(a, t) for t in (10.000, 1.0, 5.0, 0.5)] == [False, True, True, True] and not a.lost
    a = agent()  # a flood of strays that run on, between two samples of the flight controller's own
    assert broke(a, 10.000) is False
    assert [broke(a, 1.0 + 0.001 * k, after_s=0.0005) for k in range(20)] == [True] * 20 and not a.lost
    assert broke(a, 10.010) is False and a.fc.assembler.counters["samples_off_the_clock"] == 20
    a = agent()  # a reboot: the old clock stops, the new one runs
    assert [broke(a, t) for t in (10.000, 10.005)] == [False, False]
    n = max(CLOCK_BREAK_SAMPLES, round(CLOCK_BREAK_S / 0.005) + 2)  # (over CLOCK_BREAK_S, at 200 Hz)
    new_clock = [broke(a, 0.020 + 0.005 * k) for k in range(n)]
    assert new_clock == [True] * n and len(a.lost) == 1 and "went back" in a.lost[0]
    assert broke(a, 0.020 + 0.005 * n) is False  # (lost: taken as it comes)
