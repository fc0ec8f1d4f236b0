"""Tracks (gcs/tracks.py) from a known flight: two flight controllers fly a circle, ATTITUDE at 250 Hz
and LOCAL_POSITION_NED at 50 Hz on stamps that never coincide, SYSTEM_TIME at 1 Hz first heard after
the streams began; drone 1's Unix time is set 30 s forwards in flight, drone 2 reboots (its boot
clock starts again at 0) in flight. The same frames (pymavlink's stock MAVLink 2) go to a live
Recorder over loopback UDP and into a .tlog read by read_run_log: both give the same arrays, and
those are the circle to within what linear interpolation and float32 allow."""

import math
import socket
import struct
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from triswarm.gcs.recorder import Recorder
from triswarm.gcs.runlog import read_run_log
from triswarm.gcs.tracks import DroneSamples, track
from triswarm.protocol import frames
from triswarm.protocol.frames import LocalProjection
from triswarm.protocol.metrics import wrap_angle

START_UNIX_S = 1_700_000_000.0
FIRST_S, END_S = -1.0, 11.0  # plan times the streams cover
ATTITUDE_MS, ATTITUDE_PHASE_MS = 4, 1  # 250 Hz at boot times 4k + 1 (+ the boot's own phase)
POSITION_MS, POSITION_PHASE_MS = 20, 7  # 50 Hz at 20k + 7: never an attitude instant
FIRST_SYSTEM_TIME_S = 0.5  # the samples before it are timed by it
LATENCY_S = 0.030  # receive time - sample time: 0.15 m on the circle if a sample were timed by it
CLOCK_STEP_AT_S, CLOCK_STEP_S = 5.0, 30.0  # drone 1's Unix time set forwards in flight
REBOOT_AT_S = 6.0  # drone 2's boot clock starts again; its new SYSTEM_TIME comes 0.7 s later
RADIUS_M, OMEGA_RAD_S = 5.0, 1.0
RATE_HZ = 50.0
TLOG_TIME = struct.Struct(">Q")


def truth(t_s):
    """Drone i's (1, 2) position [m] and Euler angles [rad], paper frame, at plan times t_s: a circle
    flown facing along it, rolling and pitching a little; the yaw passes through +-pi."""
    t_s = np.asarray(t_s, dtype=float)[..., None]
    i = np.array([1.0, 2.0])
    phase = OMEGA_RAD_S * t_s + i * math.pi / 2
    position = np.stack([RADIUS_M * np.cos(phase), RADIUS_M * np.sin(phase), 10.0 + i + 0 * phase], axis=-1)
    euler = np.stack([0.1 * np.sin(2 * t_s + i), 0.05 * np.cos(3 * t_s + i), wrap_angle(phase + math.pi / 2)], axis=-1)
    return position, euler


def bounds() -> tuple[float, float]:
    """Linear interpolation between samples dt apart errs by at most dt^2/8 max|f''|, plus float32
    on the wire."""
    pos = (POSITION_MS / 1000) ** 2 / 8 * RADIUS_M * OMEGA_RAD_S**2 + 2e-6
    att = (ATTITUDE_MS / 1000) ** 2 / 8 * max(0.1 * 2**2, 0.05 * 3**2) + 1e-6  # (the yaw's f'' is 0)
    return pos, att


def boots(sysid: int) -> list[tuple[float, float, float, float]]:
    """(from, to) plan time, the boot's Unix time at boot time 0, and its SYSTEM_TIME's error [s]."""
    boot0 = START_UNIX_S - 60.0 - 7.003 * sysid
    if sysid == 1:
        return [(FIRST_S, CLOCK_STEP_AT_S, boot0, 0.0), (CLOCK_STEP_AT_S, END_S, boot0, CLOCK_STEP_S)]
    return [(FIRST_S, REBOOT_AT_S, boot0, 0.0), (REBOOT_AT_S, END_S, START_UNIX_S + REBOOT_AT_S - 0.006, 0.0)]  # (no gap longer than a period)


def flight() -> list[tuple[float, int, object]]:
    """(receive time [Unix s], system id, message), in the order received."""
    out = []
    for sysid in (1, 2):
        first_system_time_s = FIRST_SYSTEM_TIME_S
        for from_s, to_s, boot_unix_s, clock_error_s in boots(sysid):
            first_ms, last_ms = (math.ceil((START_UNIX_S + s - boot_unix_s) * 1000) for s in (from_s, to_s))
            for period_ms, phase_ms, kind in ((ATTITUDE_MS, ATTITUDE_PHASE_MS, "att"), (POSITION_MS, POSITION_PHASE_MS, "pos")):
                for boot_ms in range(first_ms - first_ms % period_ms + phase_ms, last_ms, period_ms):
                    t_s = boot_unix_s + boot_ms / 1000 - START_UNIX_S
                    if not from_s <= t_s < to_s:
                        continue
                    position, euler = (a[sysid - 1] for a in truth(t_s))
                    if kind == "att":
                        msg = mavlink.MAVLink_attitude_message(boot_ms, *frames.euler_flip(euler), 0.0, 0.0, 0.0)
                    else:
                        msg = mavlink.MAVLink_local_position_ned_message(boot_ms, *frames.flip(position), 0.0, 0.0, 0.0)
                    out.append((START_UNIX_S + t_s + LATENCY_S, sysid, msg))
            for t_s in np.arange(from_s + first_system_time_s, to_s, 1.0):
                boot_ms = round((START_UNIX_S + t_s - boot_unix_s) * 1000)
                unix_us = round((boot_unix_s + boot_ms / 1000 + clock_error_s) * 1e6)
                out.append((START_UNIX_S + t_s + LATENCY_S, sysid, mavlink.MAVLink_system_time_message(unix_us, boot_ms)))
            first_system_time_s = 0.7 if sysid == 2 else 0.0  # (drone 1's clock step is no new boot)
    out.sort(key=lambda r: r[0])
    return out


def frame(sysid: int, msg) -> bytes:
    return msg.pack(mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1))


def write_tlog(path, records) -> None:
    path.write_bytes(b"".join(TLOG_TIME.pack(round(t * 1e6)) + frame(sysid, m) for t, sysid, m in records))


def record_live(records) -> Recorder:
    """A Recorder listening to two loopback 'gcs links' fed the records, every one taken."""
    links = {sysid: socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for sysid in (1, 2)}
    for s in links.values():
        s.bind(("127.0.0.1", 0))
        s.settimeout(5.0)
    manifest = {"vehicles": [{"sysid": i, "links": {"gcs": {"host": "127.0.0.1", "port": s.getsockname()[1]}}}
                             for i, s in links.items()]}
    rec = Recorder(manifest).__enter__()
    try:
        peers = {i: s.recvfrom(4096)[1] for i, s in links.items()}  # its first hello
        sent = {1: 0, 2: 0}
        for k in range(0, len(records), 30):
            for sysid in (1, 2):
                chunk = [frame(sysid, m) for _, i, m in records[k:k + 30] if i == sysid]
                links[sysid].sendto(b"".join(chunk), peers[sysid])
                sent[sysid] += len(chunk)
            deadline = time.monotonic() + 10.0
            while True:  # every message taken before the next (the socket's buffer is bounded)
                got = {i: len(d.attitude.values) + len(d.position.values) + d.system_times
                       for i, d in rec.samples.snapshot().items()}
                if got == sent:
                    break
                assert time.monotonic() < deadline, (got, sent)
                time.sleep(0.002)
    except BaseException:
        rec.__exit__(None, None, None)
        raise
    finally:
        for s in links.values():
            s.close()
    return rec


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    records = flight()
    path = tmp_path_factory.mktemp("tracks") / "gcs.tlog"
    write_tlog(path, records)
    log = read_run_log(path, 2, START_UNIX_S, RATE_HZ)
    rec = record_live(records)
    try:
        live = rec.arrays(START_UNIX_S, 1 / RATE_HZ, t_from=log.t_s[0], t_to=log.t_s[-1] + 0.5 / RATE_HZ)
    finally:
        rec.__exit__(None, None, None)
    return log, live


def test_the_live_recorder_and_the_log_give_the_same_arrays(both):
    log, (t_s, position_m, euler_rad) = both
    assert log.t_s[0] == 0.0 and log.t_s[-1] >= END_S - 0.1
    np.testing.assert_allclose(t_s, log.t_s, rtol=0, atol=1e-9)
    np.testing.assert_allclose(position_m, log.position_m, rtol=0, atol=1e-8)
    np.testing.assert_allclose(wrap_angle(euler_rad - log.euler_rad), 0.0, rtol=0, atol=1e-8)
    assert [d.clock for d in log.drones] == ["SYSTEM_TIME", "SYSTEM_TIME"]


@pytest.mark.parametrize("path", ["log", "live"])
def test_streams_on_their_own_stamps_are_the_circle(both, path):
    log, live = both
    t_s, position_m, euler_rad = (log.t_s, log.position_m, log.euler_rad) if path == "log" else live
    position, euler = truth(t_s)
    pos_bound, att_bound = bounds()
    pos_err = np.abs(position_m - position).max(axis=(0, 2))
    att_err = np.abs(wrap_angle(euler_rad - euler)).max(axis=(0, 2))
    assert (pos_err <= pos_bound).all(), (pos_err, pos_bound)
    assert (att_err <= att_bound).all(), (att_err, att_bound)


def test_bounds_are_tight_enough_to_mean_something():
    pos_bound, att_bound = bounds()
    speed_m_s = RADIUS_M * OMEGA_RAD_S
    # a stream timed 1 ms off, or by its receive times, would be out of bounds
    assert pos_bound < speed_m_s * 1e-3 / 2 and att_bound < OMEGA_RAD_S * 1e-3 / 2
    assert LATENCY_S * speed_m_s > 100 * pos_bound


def _sample(drone: DroneSamples, received_unix_s: float, boot_ms: int, x_m: float) -> None:
    for msg in (mavlink.MAVLink_local_position_ned_message(boot_ms, x_m, 0.0, 0.0, 0.0, 0.0, 0.0),
                mavlink.MAVLink_attitude_message(boot_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)):
        msg.pack(mavlink.MAVLink(None, srcSystem=1, srcComponent=1))
        assert drone.take(received_unix_s, msg)


def _system_time(drone: DroneSamples, unix_s: float, boot_ms: int) -> None:
    msg = mavlink.MAVLink_system_time_message(round(unix_s * 1e6), boot_ms)
    msg.pack(mavlink.MAVLink(None, srcSystem=1, srcComponent=1))
    drone.take(unix_s, msg)


def test_the_clock_rule():
    """Receive times until a boot's first SYSTEM_TIME is heard, then that boot's offset for all of
    it; a step of the Unix time after the plan's start moves nothing, one before it is taken (the
    companions take the clock as it comes until they fly); a reboot takes its own offset."""
    drone = DroneSamples()
    for k in range(3):  # no SYSTEM_TIME yet: received at 100.5, 100.6, 100.7
        _sample(drone, 100.5 + 0.1 * k, 1000 + 100 * k, k)
    assert np.allclose(track(drone, 100.0).position_t_s, [0.5, 0.6, 0.7])
    _system_time(drone, 200.0, 1250)  # Unix 200 at boot 1.25 s: offset 198.75
    _sample(drone, 300.0, 1300, 3.0)
    _system_time(drone, 260.0, 1350)  # the clock set 60 s forwards: nothing moves
    _sample(drone, 300.0, 1400, 4.0)
    _sample(drone, 300.0, 10, 5.0)  # rebooted: samples before its SYSTEM_TIME are timed by it
    _system_time(drone, 400.0, 60)
    _sample(drone, 300.0, 110, 6.0)
    tr = track(drone, 100.0)
    for t_s in (tr.position_t_s, tr.attitude_t_s):
        assert np.allclose(t_s, [99.75, 99.85, 99.95, 100.05, 100.15, 299.95, 300.05])
    assert np.allclose(tr.position_m[:, 0], [0, 1, 2, 3, 4, 5, 6]) and tr.clock == "SYSTEM_TIME"
    assert drone.heard_unix_s == pytest.approx(400.05)
    # a plan that started at 270, after the step: the first boot flew on the stepped clock (258.65)
    later = track(drone, 270.0)
    assert np.allclose(later.position_t_s[:5], [258.65 + b - 270.0 for b in (1.0, 1.1, 1.2, 1.3, 1.4)])


def test_a_step_back_in_flight_to_before_the_start_moves_nothing():
    """In flight means with the plan running on the clock then in force, whatever Unix time a later
    SYSTEM_TIME says: a clock set back to before the start is a step in flight, not a clock of the
    ground."""
    drone = DroneSamples()
    _system_time(drone, 200.0, 1000)  # offset 199
    _sample(drone, 206.0, 7000, 1.0)  # plan time 1 s of a plan started at 205
    _system_time(drone, 190.0, 8000)  # set 17 s back in flight: Unix 190, before the start
    _sample(drone, 208.0, 9000, 2.0)
    assert np.allclose(track(drone, 205.0).position_t_s, [1.0, 3.0])


def _origin(drone: DroneSamples, lat_e7: int, lon_e7: int, alt_mm: int) -> bool:
    msg = mavlink.MAVLink_gps_global_origin_message(lat_e7, lon_e7, alt_mm, 0)
    msg.pack(mavlink.MAVLink(None, srcSystem=1, srcComponent=1))
    return drone.take(0.0, msg)


HOME = frames.DEFAULT_HOME


def _origin_at(north_m: float, east_m: float, up_m: float) -> tuple[int, int, int]:
    lat, lon = LocalProjection(*HOME).to_geodetic(north_m, east_m)
    return round(lat * 1e7), round(lon * 1e7), round((HOME[2] + up_m) * 1000)


def test_a_boot_s_origin_moves_its_positions_from_the_swarm_s_home():
    """ArduPilot's positions are from its EKF origin (its first fix unless told otherwise): with the
    swarm's home, each boot's are moved by the distance from home to the origin that boot said; a
    boot that said none, or said no place on Earth, is left as it came."""
    drone = DroneSamples()
    assert drone.needs_origin()
    _system_time(drone, 200.0, 1000)
    assert _origin(drone, *_origin_at(3.0, 4.0, -1.5)) and not drone.needs_origin()
    _sample(drone, 200.1, 1100, 1.0)
    _sample(drone, 200.2, 10, 2.0)  # rebooted: no origin heard in this boot
    assert drone.needs_origin()
    assert not _origin(drone, 2**31 - 1, 0, 0) and drone.needs_origin()  # (214 degrees north)
    _sample(drone, 200.3, 110, 3.0)
    moved = track(drone, 200.0, home_lla=HOME).position_m
    assert moved[0] == pytest.approx([1.0 + 3.0, -4.0, -1.5], abs=0.012)  # (1e-7 degrees is 1.1 cm)
    assert np.allclose(moved[1:], [[2.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    assert np.allclose(track(drone, 200.0).position_m[:, 0], [1.0, 2.0, 3.0])  # (no home: as sent)


def test_the_recorder_asks_each_vehicle_for_its_origin_until_it_says():
    """Over loopback: the Recorder asks (REQUEST_MESSAGE GPS_GLOBAL_ORIGIN) with its hello while a
    vehicle has not said its origin, takes it, and asks no more."""
    link = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    link.bind(("127.0.0.1", 0))
    link.settimeout(5.0)
    home = {"lat_deg": HOME[0], "lon_deg": HOME[1], "alt_m": HOME[2]}
    manifest = {"home": home, "vehicles": [{"sysid": 1, "links": {"gcs": {"host": "127.0.0.1",
                                                                           "port": link.getsockname()[1]}}}]}
    parser = mavlink.MAVLink(None)

    def hello() -> tuple[list[str], tuple]:
        """What the Recorder sent up to and with its next heartbeat."""
        kinds = []
        while not kinds or kinds[-1] != "HEARTBEAT":
            data, peer = link.recvfrom(4096)
            for m in parser.parse_buffer(data) or []:
                asks = m.get_type() == "COMMAND_LONG" and m.command == mavlink.MAV_CMD_REQUEST_MESSAGE
                kinds.append(f"ask {m.param1:g}" if asks else m.get_type())
        return kinds, peer

    with link, Recorder(manifest) as rec:
        kinds, peer = hello()
        assert f"ask {mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN}" in kinds
        for msg in (mavlink.MAVLink_system_time_message(round(200e6), 1000),
                    mavlink.MAVLink_gps_global_origin_message(*_origin_at(-2.0, 0.0, 0.0), 0),
                    mavlink.MAVLink_local_position_ned_message(1100, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                    mavlink.MAVLink_attitude_message(1100, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)):
            link.sendto(frame(1, msg), peer)
        deadline = time.monotonic() + 10.0
        while rec.samples.needing_origin() or not rec.samples.snapshot()[1].attitude.values:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        hello()  # (one that may have begun before the origin came)
        assert not [k for k in hello()[0] if k.startswith("ask")]
        assert rec.tracks(200.0)[1].position_m[0] == pytest.approx([-1.0, 0.0, 0.0], abs=0.012)
