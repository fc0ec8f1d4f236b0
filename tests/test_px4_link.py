"""The companion's PX4 link (``companion/px4_link.py``) as pure logic: PX4's samples turned into the
MAVLink messages the face reads, and hostile ones (values no MAVLink field holds, another type's
hash, garbage) dropped and counted, never raised. (The link on a real router, with the firmware:
tests/test_px4.py.)"""

from __future__ import annotations

import math

import pytest

from triswarm.companion.px4_link import SIGNAL_HZ, Px4ZenohLink
from triswarm.protocol import px4_msgs as px4
from triswarm.protocol.mavlink import mavlink

NAN = math.nan


@pytest.fixture
def link():
    link = Px4ZenohLink("fc", "px4-zenoh://127.0.0.1:7447/px4_1", 1, 191)
    link.session = object()  # (taken as open: these tests hand it samples themselves)
    link.heard = []
    link._on_receive = lambda _link, msgs, _t: link.heard.extend(msgs)
    return link


def take(link, topic: str, payload: bytes, key: str | None = None) -> None:
    link._take(topic, px4.TOPICS_OUT[topic], key or px4.key(0, "px4_1", "out", topic), payload, 0.0)


def test_samples_become_the_messages_the_face_reads(link):
    take(link, "vehicle_odometry", px4.encode("VehicleOdometry", timestamp_sample=5_000_000, pose_frame=1,
                                              velocity_frame=1, position=[1.0, 2.0, -3.0], q=[1, 0, 0, 0],
                                              velocity=[0.5, 0.0, 0.0]))
    take(link, "vehicle_status", px4.encode("VehicleStatus", nav_state=px4.NAV_STATE_OFFBOARD,
                                            arming_state=px4.ARMING_STATE_ARMED))
    take(link, "vehicle_command_ack", px4.encode("VehicleCommandAck", command=400, result=0, target_system=1,
                                                 target_component=191))
    take(link, "vehicle_command_ack", px4.encode("VehicleCommandAck", command=400, result=4, target_system=255,
                                                 target_component=190))  # (the ground station's: not this link's)
    odo, hb, ack = link.heard
    assert (odo.time_usec, odo.frame_id, odo.child_frame_id, odo.x, odo.z) == \
        (5_000_000, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_NED, 1.0, -3.0)
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4 and hb.custom_mode == 6 << 16
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert (ack.command, ack.result) == (400, 0)


def test_hostile_samples_are_dropped_and_counted(link):
    take(link, "vehicle_local_position", px4.encode("VehicleLocalPosition", xy_global=True, z_global=True,
                                                    ref_lat=47.0, ref_lon=8.0, ref_alt=3e38))
    take(link, "vehicle_local_position", px4.encode("VehicleLocalPosition", xy_global=True, z_global=True,
                                                    ref_lat=NAN, ref_lon=1e300, ref_alt=NAN))
    take(link, "vehicle_gps_position", px4.encode("SensorGps", time_utc_usec=2**64 - 1))
    take(link, "vehicle_status", b"\x00\x01\x00\x00" + bytes(3))
    take(link, "vehicle_status", px4.encode("VehicleStatus"),
         key=px4.key(0, "px4_1", "out", "vehicle_status").rsplit("/", 1)[0] + "/RIHS01_" + "0" * 64)
    take(link, "vehicle_status", px4.encode("VehicleStatus", nav_state=255, arming_state=255, failsafe=True))
    assert [m.get_type() for m in link.heard] == ["HEARTBEAT"]
    assert link.heard[0].custom_mode == 0 and link.heard[0].system_status == mavlink.MAV_STATE_CRITICAL
    assert link.counters["drop_unsayable_vehicle_local_position"] == 1
    assert link.counters["drop_malformed_vehicle_status"] == 1
    assert link.counters["drop_type_vehicle_status"] == 1
    assert link.fatal is not None and "RIHS01_" + "0" * 64 in link.fatal


def test_a_mode_change_is_answered_once_a_status_shows_it(link):
    """PX4 publishes the command's answer and its new status apart: a status from before the change
    that comes after the answer must not tell the face the mode it has just left."""
    link._asked_mode = px4.NAV_STATE_OFFBOARD  # (as ``send`` notes a DO_SET_MODE to offboard)
    take(link, "vehicle_command_ack", px4.encode("VehicleCommandAck", command=mavlink.MAV_CMD_DO_SET_MODE, result=0,
                                                 target_system=1, target_component=191))
    assert link.heard == []
    take(link, "vehicle_status", px4.encode("VehicleStatus", nav_state=4, arming_state=px4.ARMING_STATE_ARMED))
    assert [m.get_type() for m in link.heard] == ["HEARTBEAT"]
    take(link, "vehicle_status", px4.encode("VehicleStatus", nav_state=px4.NAV_STATE_OFFBOARD,
                                            arming_state=px4.ARMING_STATE_ARMED))
    assert [m.get_type() for m in link.heard] == ["HEARTBEAT", "HEARTBEAT", "COMMAND_ACK"]
    assert link.heard[1].custom_mode == px4.custom_mode(px4.NAV_STATE_OFFBOARD)


def test_a_command_carries_the_sample_it_answers(link):
    """The face's actuator command (SET_ACTUATOR_CONTROL_TARGET) becomes actuator_servos,
    actuator_motors and vehicle_thrust_setpoint, each stamped with the odometry sample it answers
    (timestamp_sample, PX4's clock), so PX4's log holds every command's age; offboard_control_mode
    goes with them at most SIGNAL_HZ."""
    put: list[tuple[str, object]] = []
    link._put = lambda topic, payload: put.append((topic, px4.decode(px4.TOPICS_IN[topic], payload)))
    now_s = [0.0]
    link.clock = lambda: now_s[0]  # (the signal's rate is judged on a clock of the test's, not the machine's speed)
    controls = [0.5, 0.6, 0.7, 0.1, -0.2, 0.3, NAN, NAN]
    frame = mavlink.MAVLink_set_actuator_control_target_message(7_250_000, 0, 1, 1, controls).pack(link._parser)
    link.write(frame)
    sent = dict(put)
    assert [t for t, _ in put] == ["offboard_control_mode", "actuator_servos", "actuator_motors",
                                   "vehicle_thrust_setpoint"]
    assert all(sent[t].timestamp_sample == 7_250_000 for t in ("actuator_servos", "actuator_motors",
                                                               "vehicle_thrust_setpoint"))
    assert list(sent["actuator_motors"].control[:3]) == pytest.approx([0.5, 0.6, 0.7])
    assert list(sent["actuator_servos"].control[:3]) == pytest.approx([0.1, -0.2, 0.3])
    assert sent["vehicle_thrust_setpoint"].xyz[2] == pytest.approx(-0.6)
    put.clear()  # the next command, at once: the offboard signal went with the last one (SIGNAL_HZ at most)
    link.write(frame)
    assert [t for t, _ in put] == ["actuator_servos", "actuator_motors", "vehicle_thrust_setpoint"]
    put.clear()  # one signal period later: it goes again
    now_s[0] += 1.0 / SIGNAL_HZ
    link.write(frame)
    assert [t for t, _ in put][0] == "offboard_control_mode"
