"""What the fuzzers (tests/fuzz/) found, one test each, on the smallest input that showed it."""

from __future__ import annotations

import asyncio
import logging
import math
import socket
from collections import Counter
import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest

from triswarm.companion.flight_controller import FlightController
from triswarm.companion.ground_station import GroundStation
from triswarm.companion.bus import Bus, Neighbour, _Inbox, _Member, _parse_status
from triswarm.companion.links import MavLink
from triswarm.protocol.codec import AgentStatus, Estimate, agent_of_key, encode_estimate
from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink as M, new_codec
from triswarm.protocol.plan import PlanError, plan_from_dict
from triswarm.protocol.plan_transfer import PlanTransferError, field_value
from .poll import poll

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_attitude_quaternion_is_read():
    """ATTITUDE_QUATERNION carries q1..q4 (ODOMETRY an array q): reading it raised in every read.
    A yaw of 0.3 rad in NED (a quarter-angle quaternion about z down) is -0.3 rad in the paper's frame."""
    fc = FlightController(1, "udpout:127.0.0.1:9", logging.getLogger("test"), lambda: None)
    half = 0.15
    fc.take(M.MAVLink_local_position_ned_message(1000, 1.0, 2.0, -3.0, 0.0, 0.0, 0.0), 0.0)
    fc.take(M.MAVLink_attitude_quaternion_message(1000, math.cos(half), 0.0, 0.0, math.sin(half), 0.01, 0.02, 0.03,
                                                  [0.0] * 4), 0.0)
    s = fc.backlog[-1]
    assert s.eta_rad == pytest.approx((0.0, 0.0, -0.3), abs=1e-12)
    assert s.rate_b_rad_s == pytest.approx((0.01, -0.02, -0.03))
    assert s.position_e_m == pytest.approx((1.0, -2.0, 3.0))


@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan, 0.5, -1.0, float(1 << 24)])
def test_a_mission_field_that_is_not_an_integer_is_refused(value):
    """An infinite field raised OverflowError (the upload stayed open, the rest of the datagram was lost)."""
    with pytest.raises(PlanTransferError):
        field_value(value, "item 1 field 1")


@pytest.mark.parametrize("chunk", ["²", "١", "1" * 5000, "x", "-1", ""])
def test_a_key_chunk_that_is_not_a_small_ascii_number_names_no_agent(chunk):
    """"²".isdigit() and "1" * 5000 made int() raise in the Zenoh loop."""
    assert agent_of_key(f"triswarm/s/agent/{chunk}/status") is None
    assert agent_of_key("triswarm/s/agent/12/status") == 12


@pytest.mark.parametrize("payload", [b'{"agent": Infinity, "status": "IDLE"}', b'{"agent": 1e400, "status": "IDLE"}',
                                     b"[" * 50000, b'{"agent": NaN, "status": "IDLE"}'])
def test_a_status_that_does_not_parse_is_none(payload):
    """Infinity, 1e400 (OverflowError) and deep nesting (RecursionError) raised in the Zenoh loop."""
    assert _parse_status("triswarm/s/agent/2/status", payload) is None
    assert _parse_status("triswarm/s/agent/2/status", b'{"agent": 2, "status": "IDLE"}')[:2] == (2, AgentStatus.IDLE)


def test_estimates_superseded_in_one_read_are_counted():
    """Of one agent's estimates read together only the newest is used; the others were dropped
    uncounted. Now each is drop_old: taken + dropped = received."""
    bus = Bus("s", 3)
    bus._inbox = _Inbox()
    bus.members = {1: _Member(7, frozenset({2}), None, None, None, None)}
    bus.estimates = {1: Neighbour(), 2: Neighbour()}
    for seq, t in ((1, 1.0), (3, 3.0), (2, 2.0)):
        bus._inbox.put((2).to_bytes(2, "little") + encode_estimate(Estimate(2, 7, seq, 0.0, t, AgentStatus.FLYING,
                                                                              [0.0] * 12)))
    bus.take_estimates()
    assert (bus.counters["estimates"], bus.counters["drop_old"]) == (1, 2)
    assert bus.estimates[2].t_plan_s == 3.0


def test_an_inbox_counts_what_it_pushes_out():
    inbox = _Inbox(size=3)
    for k in range(5):
        inbox.put(k)
    assert list(inbox.take()) == [2, 3, 4] and inbox.dropped == 2 and not inbox


def test_a_topology_family_that_is_not_a_name_is_a_plan_error():
    """families = [[]] raised TypeError (a list is not hashable) instead of a PlanError."""
    spec = tomllib.loads((EXAMPLES / "paper-hexagon.toml").read_text())
    spec.setdefault("topology", {})["families"] = [[]]
    spec["topology"].pop("graphs", None)
    with pytest.raises(PlanError, match="unknown family"):
        plan_from_dict(spec, "p.toml")


def test_a_link_counts_empty_datagrams_and_cut_frames():
    """An empty datagram, and one that ends inside a frame, are dropped and counted (they were not)."""
    loop = asyncio.new_event_loop()
    asyncio.set_event_loop(loop)  # (MavLink.close takes the loop it was read from as the current one)
    link = MavLink("gcs", "udpin:127.0.0.1:0", 1, COMP_ONBOARD)
    got = []
    try:
        link.open(loop, lambda lk, msgs, t: got.extend(msgs))
        frame = M.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(new_codec(255, 190))
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for data in (b"", frame[:-3], frame, b""):
                s.sendto(data, link.conn.port.getsockname())
        link._readable()
    finally:
        link.close()
        asyncio.set_event_loop(None)
        loop.close()
    assert [m.get_type() for m in got] == ["HEARTBEAT"]
    assert (link.counters["drop_empty"], link.counters["drop_partial_frame"], link.counters["rx"]) == (2, 1, 1)


@pytest.mark.parametrize("half", [math.nan, math.inf, -1.0, 65536.0, 0.5])
def test_a_plan_start_whose_plan_id_is_not_two_halves_is_denied(half):
    """PLAN_START with a NaN or infinite plan-id half raised in the ground-station link's read."""
    starts, sent = [], []
    plans = SimpleNamespace(start=lambda pid, t: starts.append((pid, t)) or (M.MAV_RESULT_ACCEPTED, ""))
    gs = GroundStation(1, "udpin:127.0.0.1:0", None, fc=None, params=None, plans=plans, plan_server=None,
                       ask_to_land=None, heartbeat=None, store=None, say=lambda text, severity=None: None, log=None,
                       frames_per_s=100.0)
    link = SimpleNamespace(send=sent.append, peer=("127.0.0.1", 14550), counters=Counter())
    for p1, p2 in ((half, 0x5678), (0x1234, half), (0x1234, 0x5678)):
        gs._command(link, M.MAVLink_command_int_message(1, COMP_ONBOARD, 0, M.MAV_CMD_TRISWARM_PLAN_START, 0, 0, p1, p2,
                                                        0, 0, 1_900_000_000, 500, 0))
    assert [m.result for m in sent] == [M.MAV_RESULT_DENIED, M.MAV_RESULT_DENIED, M.MAV_RESULT_ACCEPTED]
    assert starts == [(0x12345678, 1_900_000_000.5)]


def test_a_plan_of_too_many_drones_is_a_plan_error():
    """drones = 50,000 made the parser build 50,000 x 50,000 graphs: gigabytes, then the OOM killer."""
    spec = tomllib.loads((EXAMPLES / "large-swarm.toml").read_text())
    spec["drones"] = 50_000
    with pytest.raises(PlanError, match="at most 1000"):
        plan_from_dict(spec, "p.toml")
    spec["drones"] = 1000
    assert plan_from_dict(spec, "p.toml").n_agents == 1000


def _sitl_vehicle():
    from triswarm.sitl.swarm import SitlSwarm

    sw = SitlSwarm(1)
    return sw, sw.fcs[0]


def _from_gcs(msg):
    msg.pack(new_codec(255, 190))  # (sets its source, as a parsed message has it)
    return msg


def test_a_clock_set_beyond_what_its_stamps_hold_is_refused():
    """SYSTEM_TIME with time_unix_usec = 2**64 - 1 was taken as the clock: the next SYSTEM_TIME the
    SITL packed overflowed, and the process went down with every vehicle in it."""
    sw, fc = _sitl_vehicle()
    codec = new_codec(1, 1)
    for hostile in (2**64 - 1, 2**63, 1, 10**15):  # (the last: 1970-01-12, before any GPS time)
        fc.handle(_from_gcs(M.MAVLink_system_time_message(hostile, 0)), "gcs", sw.time_s, sw.snapshot(0))
        fc.build(M.MAVLINK_MSG_ID_SYSTEM_TIME, sw.time_s + 3600.0 * 24 * 365, sw.snapshot(0)).pack(codec)
    assert fc.counters["drop_clock_implausible"] == 4 and fc.counters["clock_set"] == 0
    fc.handle(_from_gcs(M.MAVLink_system_time_message(1_800_000_000_000_000, 0)), "gcs", sw.time_s, sw.snapshot(0))
    assert fc.counters["clock_set"] == 1
    assert fc.build(M.MAVLINK_MSG_ID_SYSTEM_TIME, sw.time_s, sw.snapshot(0)).time_unix_usec // 10**6 == 1_800_000_000


def test_a_message_interval_asked_of_an_id_beyond_16_bits_is_denied():
    """MESSAGE_INTERVAL's message id is 16 bits: an answer about message 70000 could not be packed."""
    sw, fc = _sitl_vehicle()
    codec = new_codec(1, 1)
    for msg_id in (70000.0, -1.0, 65535.0):
        replies = fc.handle(_from_gcs(M.MAVLink_command_long_message(1, 1, M.MAV_CMD_GET_MESSAGE_INTERVAL, 0, msg_id,
                                                                    0, 0, 0, 0, 0, 0)), "gcs", sw.time_s, sw.snapshot(0))
        for out in replies:
            out.msg.pack(codec)
        ack = next(o.msg for o in replies if o.msg.get_type() == "COMMAND_ACK")
        assert (ack.result == M.MAV_RESULT_DENIED) == (msg_id != 65535.0), (msg_id, ack.result)


def test_an_actuator_command_answering_a_state_not_yet_sent_is_dropped():
    """A companion's time_usec says which state it answers; one from the future (2**64 - 1) would
    have answered every state to come, and a lockstep clock would no longer wait for that vehicle."""
    sw, fc = _sitl_vehicle()
    future = M.MAVLink_set_actuator_control_target_message(2**64 - 1, 0, 1, 1, [0.0] * 8)
    future.pack(new_codec(1, 191))
    fc.handle(future, "companion", sw.time_s, sw.snapshot(0))
    assert fc.counters["drop_actuator_from_the_future"] == 1 and fc.answered_us == -1


def test_the_routing_keeps_back_what_a_ground_station_may_not_send_the_flight_controller(tmp_path):
    """Through a real companion: a ground station's SYSTEM_TIME (it would set the clock plans start
    on) and setpoints are kept back and counted; a parameter read reaches the flight controller; a
    frame that claims to come from the vehicle's own system is refused before routing."""
    from .fuzz.target import CompanionUnderFuzz

    with CompanionUnderFuzz(tmp_path, 1) as cuf:
        station, fc = cuf.station, cuf.fc
        got = []
        fc.on_message = lambda m, on=fc.on_message: (got.append(m), on(m))  # (in its reader thread)
        kept = [M.MAVLink_system_time_message(2**64 - 1, 0),
                M.MAVLink_set_position_target_local_ned_message(0, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
                M.MAVLink_manual_control_message(1, 1000, 0, 0, 0, 0)]
        for msg in kept:
            station.send_msg(msg)
        spoofed = new_codec(1, 1)
        station.send(M.MAVLink_param_request_read_message(1, 1, b"SIM_LOCKSTEP", -1).pack(spoofed))
        station.send_msg(M.MAVLink_param_request_read_message(1, 1, b"MOT_MAX_RPM", -1))
        assert station.probe(1)

        def read_reached() -> bool:  # (sent last, on the same path: what was kept back would be in by then)
            return any(m.get_srcSystem() == 255 and m.get_type() == "PARAM_REQUEST_READ" for m in list(got))
        poll(read_reached, 30.0, "the parameter read reaching the flight controller")
        reached = [(m.get_srcSystem(), m.get_type()) for m in got if m.get_srcComponent() != COMP_ONBOARD]
        # (the station's heartbeats reach it too; the spoofed read does not)
        assert set(reached) <= {(255, "HEARTBEAT"), (255, "PARAM_REQUEST_READ")}, reached
        assert reached.count((255, "PARAM_REQUEST_READ")) == 1, reached
        gcs = cuf.stop()["links"]["gcs"]
    assert gcs["kept_from_fc"] == len(kept) and gcs["refused_own_system"] == 1


def test_a_heartbeat_of_an_unknown_autopilot_is_waited_past_not_raised():
    """The flight-controller fuzz sent a HEARTBEAT of autopilot 125 while the companion set its flight
    controller up (again, on a loaded machine): the set-up raised, and the traceback went to the log.
    Now the unknown autopilot is said once and the set-up waits for a HEARTBEAT it knows."""
    from triswarm.companion.autopilots.triswarm import TriswarmSitl

    fc = FlightController(1, "udpout:127.0.0.1:9", logging.getLogger("test"), lambda: None)
    said = []
    for autopilot in (125, 125):
        hb = M.MAVLink_heartbeat_message(M.MAV_TYPE_TRICOPTER, autopilot, 0, 0, 0, 3)
        hb.pack(new_codec(1, 1))
        fc.take(hb, 0.0)
        assert not fc._pick(said.append)
    assert len(said) == 1 and "autopilot 125, which the companion does not know" in said[0]
    hb = M.MAVLink_heartbeat_message(M.MAV_TYPE_TRICOPTER, M.MAV_AUTOPILOT_GENERIC, 0, 0, 0, 3)
    hb.pack(new_codec(1, 1))
    fc.take(hb, 0.0)
    assert fc._pick(said.append) and isinstance(fc.autopilot, TriswarmSitl) and len(said) == 1
