"""`triswarm sitl up --fc-profile`: the companion link streams as the named autopilot does, over real
UDP and MAVLink, in lockstep with the test as the companion (it answers every attitude stamp). The
expectations are the autopilots' documented behaviour (sitl/profiles.py cites the source lines):
PX4's Onboard mode streams by default, stamps each message with its estimator product's instant and
sends a position only when its filter made a new one (every 10 ms); ArduPilot Copter streams nothing
until asked, stamps each message when it sends it, keeps intervals in whole milliseconds no shorter
than 3 ms, and refuses ODOMETRY."""

from __future__ import annotations

import time
from collections import defaultdict

import numpy as np
import pytest
from pymavlink import mavutil

from triswarm.sitl.profiles import PROFILES, product_step

from .sitl_helpers import command, sitl_process
from .test_lockstep import Companion

M = mavutil.mavlink


def fly(c: Companion, attitudes: int, timeout_s: float = 120.0) -> dict[str, list[int]]:
    """Answer every attitude until ``attitudes`` of them have come (simulated time: in lockstep the
    clock runs as fast as the test answers, however busy the machine; ``timeout_s`` of wall time
    bounds it); each message type's stamps [us]. (A state the simulator offers again, its answer
    overdue on a starved machine (``LockstepOptions.reoffer_s``), is the same message again:
    counted once.)"""
    stamps: dict[str, list[int]] = defaultdict(list)
    deadline = time.monotonic() + timeout_s
    while len(stamps["ATTITUDE"]) < attitudes:
        assert time.monotonic() < deadline, f"{attitudes} attitudes within {timeout_s:g} s: {len(stamps['ATTITUDE'])}"
        m = c.conn.recv_match(blocking=True, timeout=0.2)
        if m is None:
            c.hello()
            continue
        t = m.get_type()
        if t in ("ATTITUDE", "LOCAL_POSITION_NED", "ODOMETRY", "ATTITUDE_QUATERNION", "HIGHRES_IMU"):
            stamp = m.time_boot_ms * 1000 if hasattr(m, "time_boot_ms") else m.time_usec
            if not stamps[t] or stamps[t][-1] != stamp:  # (else offered again: answered again below)
                stamps[t].append(stamp)
        if t == "ATTITUDE":
            c.answer(m.time_boot_ms)
        elif t == "HEARTBEAT" and not stamps:
            c.hello()
    return stamps


def interval_us(conn, sysid: int, msg_id: int) -> int:
    command(conn, sysid, M.MAV_CMD_GET_MESSAGE_INTERVAL, msg_id)
    m = conn.recv_match(type="MESSAGE_INTERVAL", blocking=True, timeout=3.0)
    return m.interval_us


def test_px4_streams_by_default_at_its_estimators_instants(tmp_path):
    with sitl_process(tmp_path, 1, "--lockstep", "--fc-profile", "px4") as (manifest, _):
        c = Companion(manifest["vehicles"][0]["links"]["companion"]["pymavlink"], 1)
        try:
            c.hello()
            before = fly(c, 100)  # (1 s at 100 Hz)
            # Onboard mode's defaults, unasked: ATTITUDE 100 Hz, LOCAL_POSITION_NED and ODOMETRY 30 Hz
            for t, hz in (("ATTITUDE", 100), ("LOCAL_POSITION_NED", 30), ("ODOMETRY", 30)):
                s = np.array(before[t])
                assert len(s) > 20, (t, len(s))
                assert (s[-1] - s[0]) / (len(s) - 1) == pytest.approx(1e6 / hz, rel=0.1), t
            for msg_id, us in ((M.MAVLINK_MSG_ID_ATTITUDE, 5000), (M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 5000),
                               (M.MAVLINK_MSG_ID_ODOMETRY, -1)):
                assert command(c.conn, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, us).result == M.MAV_RESULT_ACCEPTED
            after = fly(c, 125)  # (0.6 s at 200 Hz, once it is asked for)
        finally:
            c.close()
    att, pos = np.array(after["ATTITUDE"][5:]), np.array(after["LOCAL_POSITION_NED"][5:])
    # the attitude every 5 ms as asked (its 200 Hz product); the position only every 10 ms however
    # fast it is asked for, each stamped with its filter update's instant (a multiple of 10 ms)
    assert len(att) > 50 and set(np.diff(att)) == {5000}
    assert len(pos) > 25 and set(np.diff(pos)) == {10000} and set(pos % 10000) == {0}
    assert len(after.get("ODOMETRY", [])) <= 3  # stopped when asked (at 30 Hz: 18 in the window)


def test_ardupilot_streams_nothing_until_asked_and_stamps_when_it_sends(tmp_path):
    with sitl_process(tmp_path, 1, "--lockstep", "--fc-profile", "ardupilot", "--seed", "3") as (manifest, _):
        c = Companion(manifest["vehicles"][0]["links"]["companion"]["pymavlink"], 1)
        try:
            c.hello()
            assert c.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=10.0) is not None
            assert not any(m.get_type() in ("ATTITUDE", "LOCAL_POSITION_NED") for m in c.drain())
            assert command(c.conn, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ODOMETRY, 5000).result \
                == M.MAV_RESULT_DENIED
            assert command(c.conn, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_HIGHRES_IMU, 5000).result \
                == M.MAV_RESULT_DENIED
            # 1.5 ms: whole milliseconds, and no faster than 80 % of the 400 Hz loop: 3 ms
            assert command(c.conn, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE, 1500).result \
                == M.MAV_RESULT_ACCEPTED
            assert interval_us(c.conn, 1, M.MAVLINK_MSG_ID_ATTITUDE) == 3000
            # 7.9 ms: 7 ms
            assert command(c.conn, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 7900).result \
                == M.MAV_RESULT_ACCEPTED
            assert interval_us(c.conn, 1, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED) == 7000
            got = fly(c, 300)  # (0.9 s at 333 Hz)
        finally:
            c.close()
    att = np.array(got["ATTITUDE"][5:])
    assert len(att) > 100 and "ODOMETRY" not in got
    # due every 3 ms, each stamped when the 400 Hz loop sent it: 0-2 ms late, never out of order
    gaps = np.diff(att)
    assert (gaps > 0).all() and gaps.mean() == pytest.approx(3000, rel=0.02)
    assert set(gaps) > {3000} and set(gaps) <= {1000, 2000, 3000, 4000, 5000}
    assert set(att % 3000) > {0}


def test_send_delays_are_the_seeds_and_the_autopilots_loop():
    dt = 1e-3
    px4, ap = PROFILES["px4"], PROFILES["ardupilot"]
    a, b = px4.jitter_steps(0, "ATT", dt), px4.jitter_steps(0, "ATT", dt)
    assert (a == b).all() and not (a == px4.jitter_steps(1, "ATT", dt)).all()  # the seed's, and only the seed's
    assert set(a) == {0, 1} and abs(a.mean() - 1 / 3) < 0.03  # U[0, 1.5 ms) on 1 ms steps
    assert set(ap.jitter_steps(0, "ATT", dt)) == {0, 1, 2}
    assert PROFILES["triswarm"].jitter_steps(0, "ATT", dt) is None
    assert [product_step(k, 400.0, dt) for k in range(8)] == [0, 0, 0, 2, 2, 5, 5, 5]
    assert [product_step(k, 100.0, dt) for k in (0, 9, 10, 19)] == [0, 0, 10, 10]
