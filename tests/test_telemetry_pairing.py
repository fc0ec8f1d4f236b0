"""The companion's telemetry as autopilots send it (companion/telemetry.py): attitude and position on
streams of their own, at their own rates, with stamps that never coincide. Judged against a known
motion: a drone on a circle (radius 10 m, 1 rad/s: 10 m/s, 10 m/s^2 towards the centre), whose
true position at every tick instant is a closed form."""

import math

import pytest

from triswarm.companion.telemetry import MAX_POSITION_AGE_US, Assembler

R, W = 10.0, 1.0


def truth(t_us: int):
    """Position and velocity on the circle at time t."""
    t = t_us * 1e-6
    return (R * math.sin(W * t), R * math.cos(W * t), 20.0), (R * W * math.cos(W * t), -R * W * math.sin(W * t), 0.0)


def eta(t_us: int):
    return (0.1, -0.2, (W * t_us * 1e-6) % (2 * math.pi) - math.pi)


def fly(att_hz: float, pos_hz: float, pos_offset_us: int = 0, duration_s: float = 2.0, drop=lambda kind, k: False,
        pos_until_us: int | None = None, order=lambda msgs: msgs):
    """Feed both streams in stamp order (or ``order``'s) and take a sample after every message, as
    the loop does after every read. Returns the samples and the assembler."""
    msgs = []
    for k in range(int(duration_s * att_hz)):
        t = round(k * 1e6 / att_hz)
        if not drop("att", k):
            msgs.append((t, "att"))
    for k in range(int(duration_s * pos_hz)):
        t = round(k * 1e6 / pos_hz) + pos_offset_us
        if not drop("pos", k) and (pos_until_us is None or t <= pos_until_us):
            msgs.append((t, "pos"))
    msgs.sort(key=lambda m: (m[0], m[1] == "att"))  # at one instant, the position first
    a, samples = Assembler(), []
    for t, kind in order(msgs):
        if kind == "att":
            a.take_attitude(t, eta(t), (0.01, 0.02, 0.03), t * 1e-6)
        else:
            a.take_position(t, *truth(t), t * 1e-6)
        s = a.sample(t_rx=t * 1e-6)
        if s is not None:
            samples.append(s)
    return samples, a


def position_error(s) -> float:
    p, _ = truth(s.boot_us)
    return math.dist(p, s.position_e_m)


def test_the_same_instant_on_both_streams_is_the_exact_state():
    samples, _ = fly(200, 200)
    assert len(samples) == 400 and all(s.position_lag_us == 0 for s in samples)
    assert max(position_error(s) for s in samples) < 1e-12
    assert [s.boot_us for s in samples] == [round(k * 1e6 / 200) for k in range(400)]


def test_250_hz_attitude_50_hz_position_ticks_on_attitude_with_the_position_brought_to_it():
    samples, a = fly(250, 50)
    # a tick at every attitude instant (after the first position came), in order, none twice
    times = [s.boot_us for s in samples]
    assert times == sorted(set(times)) and len(times) == 500
    assert a.attitude.rate_hz() == pytest.approx(250, rel=1e-3) and a.position.rate_hz() == pytest.approx(50, rel=1e-3)
    # brought forward by up to one position period (20 ms): error 1/2 a dt^2 at most (a = R w^2)
    lags = [s.position_lag_us for s in samples]
    assert max(lags) == 16_000 and min(lags) == 0
    for s in samples:
        dt = s.position_lag_us * 1e-6
        assert position_error(s) <= 0.5 * R * W * W * dt * dt * 1.001 + 1e-12, (s.boot_us, dt)
    assert max(position_error(s) for s in samples) > 1e-4  # (it is an extrapolation, not the truth)


def test_stamps_that_never_coincide_a_position_a_little_newer_is_brought_back():
    samples, _ = fly(200, 100, pos_offset_us=1_300)  # PX4-like: position published 1.3 ms after the attitude
    lags = {s.position_lag_us for s in samples}
    assert min(lags) < 0 < max(lags)  # brought backwards and forwards
    for s in samples:
        dt = s.position_lag_us * 1e-6
        assert position_error(s) <= 0.5 * R * W * W * dt * dt * 1.001 + 1e-12


def test_a_dropped_message_costs_accuracy_not_a_tick():
    samples, a = fly(200, 50, drop=lambda kind, k: kind == "pos" and k % 3 == 1)
    assert len(samples) == 400
    assert max(abs(s.position_lag_us) for s in samples) <= 40_000  # two position periods
    assert max(position_error(s) for s in samples) <= 0.5 * R * (0.04 ** 2) * 1.001
    samples, _ = fly(200, 200, drop=lambda kind, k: kind == "att" and k in (10, 11, 12))
    assert len(samples) == 397  # no tick without an attitude


def test_a_stopped_position_stream_gives_samples_without_position():
    stop = 1_000_000
    samples, a = fly(200, 50, pos_until_us=stop)
    after = [s for s in samples if s.boot_us > stop + MAX_POSITION_AGE_US]
    before = [s for s in samples if s.boot_us <= stop + MAX_POSITION_AGE_US]
    assert after and all(math.isnan(c) for s in after for c in s.position_e_m)
    assert all(not math.isnan(c) for s in before for c in s.position_e_m)
    assert a.counters["samples_without_position"] == len(after)


def test_out_of_order_stamps_are_dropped_and_counted():
    def swap_pairs(msgs):
        out = list(msgs)
        for k in range(0, len(out) - 1, 7):
            out[k], out[k + 1] = out[k + 1], out[k]
        return out

    samples, a = fly(200, 100, order=swap_pairs)
    times = [s.boot_us for s in samples]
    assert times == sorted(times) and len(set(times)) == len(times)  # never a tick back in time
    dropped = a.counters["attitude_out_of_order"] + a.counters["position_out_of_order"]
    assert dropped > 0 and len(samples) == 400 - a.counters["attitude_out_of_order"]


def test_a_restarted_flight_controller_starts_every_stream_again():
    a = Assembler()
    for t in (5_000_000, 5_005_000):
        a.take_position(t, *truth(t), t * 1e-6)
        a.take_attitude(t, eta(t), None, t * 1e-6)
        assert a.sample(0.0).boot_us == t
    a.take_attitude(1_000, eta(1_000), None, 5.01)  # the clock jumped back 5 s: held until the next says
    assert a.counters["fc_clock_restarted"] == 0 and a.sample(0.0) is None
    a.take_attitude(6_000, eta(6_000), None, 5.015)  # it runs on: a reboot
    assert a.counters["fc_clock_restarted"] == 1
    assert a.sample(0.0) is None  # no position of the new clock yet
    a.take_position(6_000, *truth(6_000), 5.015)
    s = a.sample(0.0)
    assert s.boot_us == 6_000 and s.position_lag_us == 0


def test_rates_from_the_attitude_message_else_the_gyro():
    a = Assembler()
    a.take_position(0, *truth(0), 0.0)
    a.take_gyro(0, (0.5, 0.6, 0.7), 0.0)
    a.take_attitude(0, eta(0), None, 0.0)  # (an attitude message without rates)
    assert a.sample(0.0).rate_b_rad_s == (0.5, 0.6, 0.7)
    a.take_attitude(5_000, eta(5_000), (0.1, 0.2, 0.3), 0.005)
    assert a.sample(0.0).rate_b_rad_s == (0.1, 0.2, 0.3)


# -- reading the messages: each carrier of a quantity says the same, in the paper's frames ----------

def _wire(msg):
    """``msg`` packed and parsed again by pymavlink: real MAVLink 2 framing both ways."""
    from triswarm.protocol.mavlink import new_codec
    out = new_codec(1, 1).parse_buffer(msg.pack(new_codec(1, 1)))
    assert out and len(out) == 1
    return out[0]


ATTITUDES_NED = [(0.1, 0.2, 0.3), (-0.4, 0.3, -2.5), (0.5, -0.45, 3.0)]


@pytest.mark.parametrize("roll, pitch, yaw", ATTITUDES_NED)
def test_every_attitude_message_reads_as_the_same_paper_attitude(roll, pitch, yaw):
    """ATTITUDE, ATTITUDE_QUATERNION and ODOMETRY of one FRD-in-NED attitude (quaternion by scipy,
    an independent convention) read as (roll, -pitch, -yaw), with the body rates flipped alike."""
    from scipy.spatial.transform import Rotation

    from triswarm.companion.telemetry import attitude_of, gyro_of, position_of
    from triswarm.protocol.mavlink import mavlink

    rot = Rotation.from_euler("ZYX", [yaw, pitch, roll])  # FRD body -> NED
    x, y, z, w = rot.as_quat()
    q = [w, x, y, z]
    rates, v_frd, p_ned = (0.1, -0.2, 0.3), (3.0, -1.0, 0.5), (4.0, -6.0, -20.0)
    att = _wire(mavlink.MAVLink_attitude_message(1000, roll, pitch, yaw, *rates))
    attq = _wire(mavlink.MAVLink_attitude_quaternion_message(1000, *q, *rates))
    odom = _wire(mavlink.MAVLink_odometry_message(
        1_000_000, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD, *p_ned, q, *v_frd, *rates,
        [math.nan] * 21, [math.nan] * 21))
    want_eta, want_rates = (roll, -pitch, -yaw), (0.1, 0.2, -0.3)
    for msg in (att, attq, odom):
        eta, got_rates = attitude_of(msg)
        assert eta == pytest.approx(want_eta, abs=1e-6), msg.get_type()
        assert got_rates == pytest.approx(want_rates, abs=1e-6), msg.get_type()
    v_ned = rot.apply(v_frd)
    position, velocity = position_of(odom)
    assert position == pytest.approx((4.0, 6.0, 20.0), abs=1e-5)
    assert velocity == pytest.approx((v_ned[0], -v_ned[1], -v_ned[2]), abs=1e-5)
    lpos = _wire(mavlink.MAVLink_local_position_ned_message(1000, *p_ned, *v_ned))
    assert position_of(lpos) == (pytest.approx((4.0, 6.0, 20.0), abs=1e-5),
                                 pytest.approx((v_ned[0], -v_ned[1], -v_ned[2]), abs=1e-5))
    imu = _wire(mavlink.MAVLink_highres_imu_message(1_000_000, 0, 0, -9.8, *rates, 0, 0, 0, 0, 0, 0, 0, 0b111000))
    assert gyro_of(imu) == pytest.approx(want_rates, abs=1e-6)


def test_an_odometry_in_frames_not_flown_on_is_not_read():
    from triswarm.companion.telemetry import position_of
    from triswarm.protocol.mavlink import mavlink

    odom = _wire(mavlink.MAVLink_odometry_message(
        1_000_000, mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD, 1.0, 2.0, 3.0, [1, 0, 0, 0], 0, 0, 0,
        0, 0, 0, [math.nan] * 21, [math.nan] * 21))
    assert position_of(odom) is None


def test_one_stamp_out_of_place_is_held_and_dropped_when_the_clock_goes_on_without_it():
    """A message stamped 0.8 s ahead of its stream (a hostile one, a frame corrupted past its
    checksum) is held, not taken: the next one, on the stream's clock, drops it (counted), and no
    sample is made of it. Taken, it would have made every true message out of order for 0.8 s. So
    is one stamped a reboot's jump behind: taken, it restarted every stream. A stream that truly
    jumps ahead (its next message runs on from the jump) is taken one message late."""
    a = Assembler()
    t_rx = lambda t: t * 1e-6  # noqa: E731  (received as stamped)
    instants = []
    for k, t in enumerate(range(0, 100_000, 5_000)):
        if k == 10:
            a.take_attitude(t + 800_000, eta(t + 800_000), None, t_rx(t))  # the stamp out of place
        a.take_position(t, *truth(t), t_rx(t))
        a.take_attitude(t, eta(t), None, t_rx(t))
        s = a.sample(t_rx(t))
        instants.append(None if s is None else s.boot_us)
    assert instants == list(range(0, 100_000, 5_000))
    assert a.counters["attitude_stamp_out_of_place"] == 1 and not a.counters["attitude_out_of_order"]
    jump = 2_000_000  # a true jump: the clock runs on from it
    for t in (100_000 + jump, 105_000 + jump):
        a.take_position(t, *truth(t), 0.1)
        a.take_attitude(t, eta(t), None, 0.1)
    assert a.sample(0.1).boot_us == 105_000 + jump and a.counters["attitude_stamp_out_of_place"] == 1
    for stray_us in (0, 1_000, 1_100_000):  # stamps a reboot's jump behind, alone, between true ones
        t = a.attitude.t_us + 5_000
        a.take_attitude(stray_us, eta(0), None, 0.1)
        a.take_position(t, *truth(t), 0.1)
        a.take_attitude(t, eta(t), None, 0.1)
        assert a.sample(0.1).boot_us == t
    assert a.counters["attitude_stamp_out_of_place"] == 4 and not a.counters["fc_clock_restarted"]
