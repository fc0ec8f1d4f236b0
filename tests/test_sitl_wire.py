"""The SITL behind real UDP sockets and real MAVLink framing, driven by pymavlink's own client."""

from __future__ import annotations

import time

import numpy as np
import pytest
from pymavlink import mavutil

from triswarm.protocol.mavlink import CustomMode

from .mavlink_pilot import Pilot
from .poll import poll
from .sitl_helpers import command, connect, ports_free, read_param, set_param, sitl_process

M = mavutil.mavlink


def count_messages(conn, seconds: float) -> dict:
    counts: dict[str, int] = {}
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        msg = conn.recv_match(blocking=True, timeout=0.2)
        if msg is not None:
            counts[msg.get_type()] = counts.get(msg.get_type(), 0) + 1
    return counts


@pytest.mark.realtime
def test_streams_commands_and_clean_exit(tmp_path):
    with sitl_process(tmp_path, 2) as (manifest, proc):
        assert [v["sysid"] for v in manifest["vehicles"]] == [1, 2]
        conn = connect(manifest["vehicles"][1]["links"]["companion"]["pymavlink"])
        hb = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=3)
        assert hb.get_srcSystem() == 2 and hb.get_srcComponent() == 1
        assert hb.type == M.MAV_TYPE_TRICOPTER and hb.custom_mode == CustomMode.EXTERNAL
        assert hb.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
        counts = count_messages(conn, 2.0)
        # >= 100 Hz on the companion link by default (with some slack for the wall clock)
        assert counts["ATTITUDE"] >= 180 and counts["LOCAL_POSITION_NED"] >= 180
        for name in ("ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT", "ODOMETRY", "HIGHRES_IMU", "SYS_STATUS",
                     "BATTERY_STATUS", "EXTENDED_SYS_STATE", "ACTUATOR_OUTPUT_STATUS", "SYSTEM_TIME", "HEARTBEAT"):
            assert counts.get(name, 0) >= 1, name
        # every rate is settable: GLOBAL_POSITION_INT from 10 Hz to 50 Hz, ODOMETRY off
        assert command(conn, 2, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 20000).result == M.MAV_RESULT_ACCEPTED
        assert command(conn, 2, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ODOMETRY, -1).result == M.MAV_RESULT_ACCEPTED
        counts = count_messages(conn, 1.0)
        assert 40 <= counts.get("GLOBAL_POSITION_INT", 0) <= 60 and counts.get("ODOMETRY", 0) == 0
        assert read_param(conn, 2, "SC_GPOS_HZ") == pytest.approx(50.0)
        # one-off requests
        conn.mav.command_long_send(2, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
        av = conn.recv_match(type="AUTOPILOT_VERSION", blocking=True, timeout=3)
        assert av.capabilities & M.MAV_PROTOCOL_CAPABILITY_MAVLINK2 and av.capabilities & M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
        assert not av.capabilities & M.MAV_PROTOCOL_CAPABILITY_MISSION_INT  # honest: no mission protocol
        conn.mav.command_long_send(2, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_HOME_POSITION, 0, 0, 0, 0, 0, 0)
        home = conn.recv_match(type="HOME_POSITION", blocking=True, timeout=3)
        assert home.latitude == pytest.approx(manifest["home"]["lat_deg"] * 1e7, abs=500)
        conn.mav.command_long_send(2, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, 0, 0, 0, 0, 0, 0)
        origin = conn.recv_match(type="GPS_GLOBAL_ORIGIN", blocking=True, timeout=3)  # (positions are from home)
        assert (origin.latitude, origin.longitude, origin.altitude) == tuple(
            round(manifest["home"][k] * scale) for k, scale in (("lat_deg", 1e7), ("lon_deg", 1e7), ("alt_m", 1e3)))
        # COMMAND_INT, an unsupported command, TIMESYNC
        conn.mav.command_int_send(2, 1, 0, M.MAV_CMD_REQUEST_MESSAGE, 0, 0, M.MAVLINK_MSG_ID_SYSTEM_TIME, 0, 0, 0, 0, 0, 0)
        ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=3)
        assert ack.command == M.MAV_CMD_REQUEST_MESSAGE and ack.result == M.MAV_RESULT_ACCEPTED
        assert command(conn, 2, M.MAV_CMD_DO_SET_ROI_LOCATION).result == M.MAV_RESULT_UNSUPPORTED
        conn.mav.timesync_send(0, 123456789)
        ts = conn.recv_match(type="TIMESYNC", blocking=True, timeout=3)
        assert ts.ts1 == 123456789 and ts.tc1 > 0
    assert proc.returncode == 0
    assert ports_free(manifest)


def test_parameters_are_per_vehicle_and_validated(tmp_path):
    with sitl_process(tmp_path, 2) as (manifest, _):
        c1 = connect(manifest["vehicles"][0]["links"]["gcs"]["pymavlink"])
        c2 = connect(manifest["vehicles"][1]["links"]["gcs"]["pymavlink"])
        c1.mav.param_request_list_send(1, 1)
        names, count = set(), None
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and (count is None or len(names) < count):
            m = c1.recv_match(type="PARAM_VALUE", blocking=True, timeout=1)
            if m is not None:
                names.add(m.param_id)
                count = m.param_count
        assert count == len(names) and {"MASS_KG", "KF", "SERVO_DELAY_S", "MOT_MAX_RPM", "SERVO_LIM_DEG",
                                        "NOISE_POS_M", "FS_TIMEOUT_S", "SC_ATT_HZ"} <= names
        assert set_param(c1, 1, "MASS_KG", 0.6) == pytest.approx(0.6)
        assert read_param(c2, 2, "MASS_KG") == pytest.approx(0.5)  # vehicle 2 unchanged
        assert set_param(c1, 1, "MASS_KG", -1.0) == pytest.approx(0.6)  # refused: value unchanged
        text = c1.recv_match(type="STATUSTEXT", blocking=True, timeout=3)
        assert "MASS_KG must be within" in text.text


def test_arming_refused_with_a_reason(tmp_path):
    with sitl_process(tmp_path, 1) as (manifest, _):
        conn = connect(manifest["vehicles"][0]["links"]["gcs"]["pymavlink"])
        set_param(conn, 1, "BAT_ARM_PCT", 100.0)
        # (once the avionics have drawn a little since boot, as the battery's report says)
        poll(lambda: conn.recv_match(type="SYS_STATUS", blocking=True, timeout=0.5) is not None
             and conn.messages["SYS_STATUS"].battery_remaining < 100, 10.0, "a battery below 100 %", every_s=0.0)
        assert command(conn, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == M.MAV_RESULT_DENIED
        text = conn.recv_match(type="STATUSTEXT", blocking=True, timeout=3)
        assert text.text.startswith("arming refused: battery")
        assert command(conn, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196).result == M.MAV_RESULT_ACCEPTED  # forced
        hb = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=3)
        assert hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
        assert command(conn, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0).result == M.MAV_RESULT_ACCEPTED


def test_closed_loop_hover_over_mavlink_then_failsafe(tmp_path):
    """The math core flies a SITL vehicle through real sockets and holds a hover setpoint within
    0.05 m; when its commands stop, the vehicle's own failsafe holds position, and resumes. (On
    simulated time: the SITL in lockstep with the pilot.)"""
    with sitl_process(tmp_path, 1, "--lockstep") as (manifest, _):
        conn = connect(manifest["vehicles"][0]["links"]["companion"]["pymavlink"], sysid=1, compid=191)
        pilot = Pilot(conn, 1)
        assert command(conn, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == M.MAV_RESULT_ACCEPTED
        pilot.takeoff_to(2.0, 3.0)
        pilot.fly(8.0)
        t = np.array([row[0] for row in pilot.log])
        pos = np.array([row[1] for row in pilot.log])
        start = pos[0]
        hold = t >= t[-1] - 3.0
        err = np.linalg.norm(pos[hold] - [start[0], start[1], 2.0], axis=1)
        assert err.max() < 0.05, err.max()
        held_at = pos[-1].copy()

        # stop commanding: the failsafe takes over within FS_TIMEOUT_S and holds where it was
        pilot.log.clear()
        pilot.statustexts.clear()
        pilot.fly(3.0, send=False)
        hb = pilot.heartbeat
        assert hb.custom_mode == CustomMode.HOLD and hb.system_status == M.MAV_STATE_CRITICAL
        pos = np.array([row[1] for row in pilot.log])
        assert np.linalg.norm(pos - held_at, axis=1).max() < 0.3
        assert any(s.startswith("failsafe: no actuator command") for s in pilot.statustexts), pilot.statustexts

        # commands come back: the vehicle is flown by its companion again
        pilot.ctrl.reset(np.concatenate([np.zeros(6), pilot.eta, pos[-1]])[None, :])
        pilot.ref = type(pilot.ref)(pos[-1], np.zeros(3), held_at, pilot.eta, np.zeros(3), [0, 0, pilot.eta[2]],
                                    pilot.log[-1][0], 2.0)
        pilot.statustexts.clear()
        pilot.fly(2.5)
        assert pilot.heartbeat.custom_mode == CustomMode.EXTERNAL
        assert "actuator commands back, failsafe cleared" in pilot.statustexts


@pytest.mark.realtime
def test_speedup_keeps_timestamps_consistent(tmp_path):
    with sitl_process(tmp_path, 2, "--speedup", "10") as (manifest, _):
        conn = connect(manifest["vehicles"][0]["links"]["companion"]["pymavlink"])
        att, times = [], []
        wall0 = time.monotonic()
        while time.monotonic() - wall0 < 1.5:
            msg = conn.recv_match(type=["ATTITUDE", "SYSTEM_TIME"], blocking=True, timeout=0.5)
            if msg is None:
                continue
            if msg.get_type() == "ATTITUDE":
                att.append((time.monotonic(), msg.time_boot_ms))
            else:
                times.append((msg.time_unix_usec, msg.time_boot_ms))
        (w0, b0), (w1, b1) = att[0], att[-1]
        assert (b1 - b0) / 1000.0 / (w1 - w0) == pytest.approx(10.0, rel=0.1)  # 10 x real time
        stream = {b for _, b in att if b % 10 == 0}
        assert len(stream) / ((b1 - b0) / 1000.0) >= 97  # still 100 Hz of simulated time
        assert len(times) >= 10
        for (u0, t0), (u1, t1) in zip(times, times[1:]):
            assert (u1 - u0) / 1000.0 == pytest.approx(t1 - t0, abs=1.0)  # unix time runs with boot time
