"""The simulated flight controllers' logic without sockets: telemetry in MAVLink's frames, the
actuator mapping, arming, failsafe and mode changes on a simulated clock."""

import math

import numpy as np
import pytest

from triswarm.protocol.airframe import TABLE_1
from triswarm.protocol.mavlink import CustomMode, decode_actuators, encode_actuators, mavlink
from triswarm.sitl.physics import QUAT, quaternion_from_euler
from triswarm.sitl.swarm import SitlSwarm, ground_grid

M = mavlink


def msg_from(msg, sysid=255, compid=190):
    msg._header = M.MAVLink_header(msg.id, 0, 0, 0, sysid, compid)
    return msg


def test_ground_grid_spacing():
    g = ground_grid(7, 2.5)
    d = np.linalg.norm(g[:, None, :] - g[None, :, :], axis=2) + np.eye(7) * 99
    assert d.min() == pytest.approx(2.5) and np.all(g[:, 2] == 0)


def test_telemetry_is_in_ned_and_frd():
    sw = SitlSwarm(1)
    sw.plant.state[0, 0:3] = [1.0, 2.0, 3.0]              # 1 m north, 2 m west, 3 m up
    sw.plant.state[0, 3:6] = [0.5, 0.0, 0.0]              # moving along the body x axis
    sw.plant.state[0, QUAT] = quaternion_from_euler([0.1, 0.2, math.pi / 2])
    sw.plant.state[0, 10:13] = [0.01, 0.02, 0.03]
    sw.plant.landed[:] = False
    fc, snap = sw.fcs[0], sw.snapshot(0)
    att = fc.build(M.MAVLINK_MSG_ID_ATTITUDE, 1.0, snap)
    assert (att.roll, att.pitch, att.yaw) == pytest.approx((0.1, -0.2, -math.pi / 2))
    assert (att.rollspeed, att.pitchspeed, att.yawspeed) == pytest.approx((0.01, -0.02, -0.03))
    lpos = fc.build(M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 1.0, snap)
    assert (lpos.x, lpos.y, lpos.z) == pytest.approx((1.0, -2.0, -3.0))
    v_e = snap.velocity_e_m_s
    assert (lpos.vx, lpos.vy, lpos.vz) == pytest.approx((v_e[0], -v_e[1], -v_e[2]))
    q = fc.build(M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, 1.0, snap)
    # the quaternion and the Euler angles describe the same attitude
    roll = math.atan2(2 * (q.q1 * q.q2 + q.q3 * q.q4), 1 - 2 * (q.q2**2 + q.q3**2))
    yaw = math.atan2(2 * (q.q1 * q.q4 + q.q2 * q.q3), 1 - 2 * (q.q3**2 + q.q4**2))
    assert (roll, yaw) == pytest.approx((att.roll, att.yaw))
    gpos = fc.build(M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 1.0, snap)
    lat, lon = sw.home.to_geodetic(1.0, -2.0)
    assert gpos.lat == round(lat * 1e7) and gpos.lon == round(lon * 1e7)
    assert gpos.relative_alt == 3000 and gpos.alt == round((sw.home.alt_m + 3.0) * 1000)
    assert gpos.hdg == 27000  # heading west
    odom = fc.build(M.MAVLINK_MSG_ID_ODOMETRY, 1.0, snap)
    assert (odom.vx, odom.vy, odom.vz) == pytest.approx((0.5, 0.0, 0.0))  # body FRD
    assert odom.frame_id == M.MAV_FRAME_LOCAL_NED and odom.child_frame_id == M.MAV_FRAME_BODY_FRD


def test_accelerometer_reads_minus_g_at_rest():
    sw = SitlSwarm(1)
    imu = sw.fcs[0].build(M.MAVLINK_MSG_ID_HIGHRES_IMU, 0.0, sw.snapshot(0))
    assert (imu.xacc, imu.yacc, imu.zacc) == pytest.approx((0.0, 0.0, -TABLE_1.gravity_m_s2))
    assert imu.abs_pressure == pytest.approx(1013.25 * (1 - 2.25577e-5 * sw.home.alt_m) ** 5.25588)


def test_actuator_mapping_round_trip_and_bad_values():
    wmax, alim = TABLE_1.max_rotor_speed_rad_s, TABLE_1.servo_limit_rad
    controls = encode_actuators([300.0, 600.0, 900.0], [0.1, -1.5, 2.0], wmax, alim)
    dec = decode_actuators(controls, wmax, alim)
    assert np.allclose(dec.omega_rad_s, [300, 600, 900]) and np.allclose(dec.alpha_rad, [0.1, -1.5, 2.0])
    dec = decode_actuators([1.5, -0.2, 0.5, 0.0, 2.0, -1.0, 0, 0], wmax, alim)
    assert dec.clamped == 3 and np.allclose(dec.omega_rad_s, [wmax, 0, wmax / 2]) and dec.alpha_rad[1] == alim
    for bad in (float("nan"), float("inf")):
        assert decode_actuators([0.5, bad, 0.5, 0, 0, 0, 0, 0], wmax, alim).dropped_non_finite


def arm(sw, i=0, force=False):
    cmd = msg_from(M.MAVLink_command_long_message(i + 1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1,
                                                  21196 if force else 0, 0, 0, 0, 0, 0))
    return sw.fcs[i].handle(cmd, "gcs", sw.time_s, sw.snapshot(i))[0].msg.result


def run(sw, seconds):
    for _ in range(int(round(seconds / sw.dt_s))):
        sw.step()


def test_failsafe_timeline_and_recovery():
    sw = SitlSwarm(1)
    fc = sw.fcs[0]
    assert arm(sw) == M.MAV_RESULT_ACCEPTED
    # a companion flies it up with actuator targets: a hover thrust 5 % above weight
    from triswarm.protocol.model import hover_trim
    w, a = hover_trim(TABLE_1)
    target = msg_from(M.MAVLink_set_actuator_control_target_message(
        0, 0, 1, 1, encode_actuators(w * 1.05**0.5, a, TABLE_1.max_rotor_speed_rad_s, TABLE_1.servo_limit_rad)), 1, 191)
    for _ in range(400):  # 2 s of commands at 200 Hz
        fc.handle(target, "companion", sw.time_s, sw.snapshot(0))
        run(sw, 0.005)
    assert sw.snapshot(0).position_m[2] > 0.5 and fc.mode == CustomMode.EXTERNAL
    fc.outbox.clear()
    t_stop = sw.time_s
    run(sw, 0.25)
    assert fc.mode == CustomMode.EXTERNAL  # within FS_TIMEOUT_S (0.3 s)
    run(sw, 0.1)
    assert fc.mode == CustomMode.HOLD and fc.failsafe
    texts = [o.msg.text for o in fc.outbox if o.msg.get_type() == "STATUSTEXT"]
    assert any(t.startswith("failsafe: no actuator command for 0.3 s") for t in texts)
    # it brakes to rest at its stopping point (climbing at ~1 m/s, so a little higher) and stays there
    run(sw, 3.0)
    held = sw.snapshot(0).position_m.copy()
    run(sw, 1.0)
    assert np.linalg.norm(sw.snapshot(0).position_m - held) < 0.02
    assert np.linalg.norm(sw.snapshot(0).velocity_e_m_s) < 0.05
    # commands come back: EXTERNAL again
    fc.handle(target, "companion", sw.time_s, sw.snapshot(0))
    assert fc.mode == CustomMode.EXTERNAL and not fc.failsafe
    # silence again, long enough: hold, then land after FS_LAND_DELAY_S, then disarm on the ground
    run(sw, 0.4 + fc.params["FS_LAND_DELAY_S"] + 0.2)
    assert fc.mode == CustomMode.LAND
    run(sw, 15.0)
    assert not fc.armed and sw.snapshot(0).landed and sw.snapshot(0).position_m[2] == 0.0
    assert sw.time_s - t_stop > fc.params["FS_LAND_DELAY_S"]


def test_disarm_in_the_air_is_refused_unless_forced():
    sw = SitlSwarm(1)
    fc = sw.fcs[0]
    arm(sw)
    take = msg_from(M.MAVLink_command_long_message(1, 1, M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, float("nan"), 0, 0,
                                                   float("nan")))
    assert fc.handle(take, "gcs", 0.0, sw.snapshot(0))[0].msg.result == M.MAV_RESULT_ACCEPTED
    run(sw, 3.0)
    assert not sw.snapshot(0).landed
    off = msg_from(M.MAVLink_command_long_message(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0))
    assert fc.handle(off, "gcs", sw.time_s, sw.snapshot(0))[0].msg.result == M.MAV_RESULT_DENIED
    kill = msg_from(M.MAVLink_command_long_message(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0))
    assert fc.handle(kill, "gcs", sw.time_s, sw.snapshot(0))[0].msg.result == M.MAV_RESULT_ACCEPTED
    run(sw, 2.0)
    assert sw.snapshot(0).landed  # it fell


def test_commands_with_unusable_numbers_are_refused():
    sw = SitlSwarm(1)
    fc = sw.fcs[0]
    for cmd, p1 in ((M.MAV_CMD_REQUEST_MESSAGE, float("nan")), (M.MAV_CMD_DO_SET_MODE, float("inf")),
                    (M.MAV_CMD_COMPONENT_ARM_DISARM, float("nan"))):
        m = msg_from(M.MAVLink_command_long_message(1, 1, cmd, 0, p1, 1, 0, 0, 0, 0, 0))
        assert fc.handle(m, "gcs", 0.0, sw.snapshot(0))[0].msg.result == M.MAV_RESULT_DENIED
    assert not fc.armed


@pytest.mark.parametrize("current_a, voltage_v", [(1e6, 25.0), (float("nan"), float("nan")), (-1e6, 1e9)])
def test_a_diverged_vehicles_battery_is_reported_not_a_crash(current_a, voltage_v):
    """A plant flown off the scale (a diverged controller draws any current) still packs its
    SYS_STATUS and BATTERY_STATUS: the 16-bit fields saturate, the flight controller keeps talking."""
    sw = SitlSwarm(1)
    fc, snap = sw.fcs[0], sw.snapshot(0)
    fc.battery_current_a, fc.battery_voltage_v = current_a, voltage_v
    codec = M.MAVLink(None, 1, 1)
    for msg_id in (M.MAVLINK_MSG_ID_SYS_STATUS, M.MAVLINK_MSG_ID_BATTERY_STATUS):
        msg = fc.build(msg_id, 1.0, snap)
        back = codec.parse_buffer(msg.pack(codec))[0]
        assert back.current_battery in (-1, 32767, -32767)
