"""A plan as mission items and back (pure), the dialect's numbers, and the leader's moves."""

from __future__ import annotations

import copy
import struct

import numpy as np
import pytest

from triswarm.protocol.formation import ConstantFormation, LeaderMove, QuinticTransfer
from triswarm.protocol.mavlink import mavlink, new_codec
from triswarm.protocol.plan_transfer import (BYTES_PER_ITEM, CMD_PLAN_DATA, CMD_PLAN_HEADER, MISSION_INVALID,
                                             MISSION_UNSUPPORTED, PlanItem, PlanTransferError, decode_plan,
                                             encode_plan, field_value)


def test_dialect_numbers_are_the_codec_numbers():
    assert mavlink.MAV_CMD_TRISWARM_PLAN_HEADER == CMD_PLAN_HEADER
    assert mavlink.MAV_CMD_TRISWARM_PLAN_DATA == CMD_PLAN_DATA
    assert mavlink.MAV_MISSION_INVALID == MISSION_INVALID and mavlink.MAV_MISSION_UNSUPPORTED == MISSION_UNSUPPORTED
    # messages are common.xml's, byte for byte: no message of our own (the pinned common.xml's are
    # ours, tests/test_dialect.py), and every one the installed pymavlink knows has the same CRC extra
    import xml.etree.ElementTree as ET
    from pathlib import Path

    from pymavlink.dialects.v20 import common

    dialect = Path(__file__).resolve().parents[1] / "protocol" / "dialect"
    assert ET.parse(dialect / "triswarm.xml").getroot().find("messages") is None
    pinned = {int(m.get("id")) for name in ("common.xml", "standard.xml", "minimal.xml")
              for m in ET.parse(dialect / name).getroot().iter("message")}
    assert set(mavlink.mavlink_map) == pinned
    shared = mavlink.mavlink_map.keys() & common.mavlink_map.keys()
    assert len(shared) > 200
    assert {k: common.mavlink_map[k].crc_extra for k in shared} == {k: mavlink.mavlink_map[k].crc_extra for k in shared}


def test_round_trip_through_float32_and_real_frames(paper_spec):
    items = encode_plan(paper_spec)
    assert items[0].command == CMD_PLAN_HEADER and all(i.command == CMD_PLAN_DATA for i in items[1:])
    sender, receiver = new_codec(255, 190), new_codec(1, 191)
    back = []
    for seq, item in enumerate(items):
        p = item.fields
        # as MISSION_ITEM: every field a float32 (the lossy path of older clients)
        as_floats = struct.unpack("<7f", struct.pack("<7f", *map(float, p)))
        assert tuple(field_value(v, "f") for v in as_floats) == p
        frame = mavlink.MAVLink_mission_item_int_message(1, 191, seq, mavlink.MAV_FRAME_MISSION, item.command, 0, 0,
                                                         *map(float, p[:4]), p[4], p[5], float(p[6]), 0).pack(sender)
        (msg,) = receiver.parse_buffer(frame)
        back.append(PlanItem(msg.command, tuple(field_value(v, "f") for v in
                                                (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z))))
    spec, pid = decode_plan(back)
    assert spec == paper_spec
    header = items[0].fields
    assert header[0] == 1 and header[2] == 6 and (header[4] << 16 | header[5]) == pid
    assert header[1] <= (len(items) - 1) * BYTES_PER_ITEM < header[1] + BYTES_PER_ITEM


@pytest.mark.parametrize("mutate, code, words", [
    (lambda it: it[1:], MISSION_UNSUPPORTED, "not a triswarm plan header"),
    (lambda it: it[:-1], MISSION_INVALID, "came"),
    (lambda it: [it[0]] + [PlanItem(16, it[1].fields)] + it[2:], MISSION_UNSUPPORTED, "item 1 is command 16"),
    (lambda it: [PlanItem(it[0].command, (2,) + it[0].fields[1:])] + it[1:], MISSION_UNSUPPORTED, "version 2"),
    (lambda it: [PlanItem(it[0].command, it[0].fields[:5] + ((it[0].fields[5] + 1) & 0xFFFF, 0))] + it[1:],
     MISSION_INVALID, "does not match"),
    (lambda it: it[:3] + [PlanItem(CMD_PLAN_DATA, (1, 2, 3, 4, 5, 6, 7))] + it[4:], MISSION_INVALID, "does not decode"),
])
def test_broken_items_are_refused_with_a_reason(paper_spec, mutate, code, words):
    with pytest.raises(PlanTransferError) as info:
        decode_plan(mutate(encode_plan(paper_spec)))
    assert info.value.ack_code == code and words in str(info.value)


@pytest.mark.parametrize("value", [0.5, -1.0, float(1 << 24), float("nan")])
def test_a_field_must_be_a_24_bit_integer(value):
    with pytest.raises(PlanTransferError):
        field_value(value, "x")


def test_values_json_cannot_hold_are_refused(paper_spec):
    spec = copy.deepcopy(paper_spec)
    spec["leader"]["position_m"] = [float("nan"), 0.0, 0.0]
    with pytest.raises(PlanTransferError, match="cannot be sent"):
        encode_plan(spec)


def _base():
    return ConstantFormation(np.array([[5.0, -5.0, 0.0]]), np.zeros((1, 3)))


def test_leader_goto_starts_where_the_base_is_and_ends_at_rest_on_target():
    moving = QuinticTransfer([0, 0, 0], [1.0, 0, 0], [4.0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], 0.0, 6.0)
    move = LeaderMove(moving, 2.0, (10.0, 3.0, 1.0), 0.3, 2.0)
    before, after = moving.kinematics(2.0), move.kinematics(2.0)
    np.testing.assert_allclose(after.p, before.p, atol=1e-12)
    np.testing.assert_allclose(after.p_dot, before.p_dot, atol=1e-12)
    end = move.kinematics(move.end_s + 0.1)
    np.testing.assert_allclose(end.p[0], [10.0, 3.0, 1.0], atol=1e-12)
    assert end.eta[0, 2] == pytest.approx(0.3) and np.all(end.p_dot == 0)
    assert move.kinematics(1.0).p[0, 0] == pytest.approx(moving.kinematics(1.0).p[0, 0])


def test_leader_goto_keeps_its_peak_speed_and_its_derivatives_are_exact():
    move = LeaderMove(_base(), 1.0, (25.0, -5.0, 0.0), None, 2.0)
    ts = np.linspace(1.0, move.end_s, 2001)
    speeds = [np.linalg.norm(move.kinematics(t).p_dot[0]) for t in ts]
    assert max(speeds) == pytest.approx(2.0, rel=1e-3)  # a quintic peaks at 1.875 d / T, T chosen for it
    h = 1e-6
    for t in (1.5, 3.0, 7.0):
        k = move.kinematics(t)
        fd = (move.kinematics(t + h).p - move.kinematics(t - h).p) / (2 * h)
        np.testing.assert_allclose(k.p_dot, fd, atol=1e-6)
        fd2 = (move.kinematics(t + h).p_dot - move.kinematics(t - h).p_dot) / (2 * h)
        np.testing.assert_allclose(k.p_ddot, fd2, atol=1e-5)


def test_leader_hold_brakes_to_rest_along_its_velocity():
    moving = QuinticTransfer([0, 0, 0], [2.0, 0, 0], [100.0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], 0.0, 100.0)
    stop = LeaderMove(moving, 0.0, None, None, 1.0)
    end = stop.kinematics(stop.end_s)
    assert end.p[0, 0] == pytest.approx(2.0 * 2.0 / 2.0) and np.all(end.p_dot == 0)


@pytest.mark.parametrize("kw", [dict(speed_m_s=0.0), dict(speed_m_s=float("nan")), dict(target_m=(1.0, float("inf"), 0.0)),
                                dict(yaw_rad=float("inf"))])
def test_a_bad_leader_move_is_refused(kw):
    args = dict(base=_base(), at_s=0.0, target_m=(1.0, 0.0, 0.0), yaw_rad=None, speed_m_s=1.0) | kw
    with pytest.raises(ValueError):
        LeaderMove(**args)
