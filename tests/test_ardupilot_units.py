"""The pieces of ArduPilot in the loop that need no firmware: the JSON physics' packets and frames,
the plant's accelerometer at rest, the autopilot registry and ArduCopter's modes, the takeoff each
autopilot is asked for, and the firmware launcher's command line and refusals."""

from __future__ import annotations

import json
import math
import struct
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from triswarm.companion.autopilots.ardupilot import ArduCopter
from triswarm.companion.autopilots.base import AutopilotError
from triswarm.companion.autopilots.px4 import Px4
from triswarm.companion.autopilots.registry import pick
from triswarm.companion.autopilots.triswarm import TriswarmSitl
from triswarm.protocol import model
from triswarm.protocol.airframe import TABLE_1
from triswarm.protocol.autopilots import ARDUCOPTER_GUIDED, takeoff_commands
from triswarm.protocol.frames import quaternion_from_euler
from triswarm.protocol.mavlink import mavlink
from triswarm.sitl.firmware import FirmwareError, FirmwareSpec, Firmware, find_firmware
from triswarm.sitl.json_physics import OutputMap, decode_servo_packet, frame_period_s, state_json
from triswarm.sitl.physics import SENSOR_COLUMNS, Plant

G = TABLE_1.gravity_m_s2


def test_servo_packets_of_16_and_32_channels_and_nothing_else():
    pwm = list(range(1000, 1016))
    frame = decode_servo_packet(struct.pack("<HHI16H", 18458, 1000, 7, *pwm))
    assert (frame.frame_rate_hz, frame.frame_count, frame.pwm) == (1000, 7, tuple(pwm))
    frame = decode_servo_packet(struct.pack("<HHI32H", 29569, 400, 8, *(pwm + pwm)))
    assert frame.pwm == tuple(pwm)
    assert decode_servo_packet(struct.pack("<HHI16H", 1234, 1000, 7, *pwm)) is None  # a wrong magic
    assert decode_servo_packet(struct.pack("<HHI15H", 18458, 1000, 7, *pwm[:15])) is None  # short
    assert decode_servo_packet(b"") is None


def test_the_output_map_is_the_shipped_hardware():
    pwm = np.zeros((3, 16))
    pwm[0, :6] = [1000, 1500, 2000, 1500, 2000, 1000]  # stopped, half, top; untilted, +limit, -limit
    pwm[1, :6] = [2500, 500, 1750, 1250, 2500, 500]    # beyond the range: clamped
    omega, alpha = OutputMap().commands(pwm, np.full(3, 100.0), np.full(3, 2.0))  # (row 2: all 0, not live)
    assert np.allclose(omega, [[0, 50, 100], [100, 0, 75], [0, 0, 0]])
    assert np.allclose(alpha, [[0, 2, -2], [-1, 2, -2], [0, 0, 0]])


def test_the_state_is_the_truth_in_the_firmwares_frames():
    """Paper frames (x north, y west, z up; body FLU) in, NED and FRD out: a drone 1 m north, 2 m
    west, 3 m up, rolled 0.3, pitched 0.2 (nose down in NED terms), yawed 0.4 (to the west: -0.4 in
    NED), flying north-west, turning."""
    row = np.zeros(22)
    col = SENSOR_COLUMNS
    eta = np.array([0.3, 0.2, 0.4])
    row[col["position_m"]] = [1, 2, 3]
    row[col["velocity_e_m_s"]] = [4, 5, 6]
    row[col["quaternion"]] = quaternion_from_euler(eta)
    row[col["rate_b_rad_s"]] = [0.1, 0.2, 0.3]
    row[col["specific_force_b"]] = [0.5, 0.6, 9.0]
    text = state_json(12.5, row)
    assert text.startswith(b"\n{") and text.endswith(b"}\n")
    s = json.loads(text)
    assert s["timestamp"] == 12.5
    assert s["position"] == pytest.approx([1, -2, -3]) and s["velocity"] == pytest.approx([4, -5, -6])
    assert s["imu"]["gyro"] == pytest.approx([0.1, -0.2, -0.3])
    assert s["imu"]["accel_body"] == pytest.approx([0.5, -0.6, -9.0])
    w, x, y, z = s["quaternion"]  # FRD to NED, scalar first: its Euler angles are (0.3, -0.2, -0.4)
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(2 * (w * y - z * x))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    assert (roll, pitch, yaw) == pytest.approx((0.3, -0.2, -0.4))
    assert all(k in s["rc"] for k in ("rc_1", "rc_3", "rc_8")) and s["rc"]["rc_3"] == 1000  # throttle low


def test_the_clock_steps_in_whole_microseconds():
    assert frame_period_s(1000.0) == 0.001 and frame_period_s(1200.0) == 833e-6
    with pytest.raises(ValueError):
        frame_period_s(2e6)


def test_at_rest_on_the_ground_the_accelerometer_reads_gravity_whatever_the_rotors_do():
    """A drone spinning up on the ground is not accelerating: its accelerometer reads the ground's
    push against gravity, g up, not that plus the thrust (which the ground takes)."""
    plant = Plant(TABLE_1, 2, dt_s=1e-3)
    plant.reset(np.zeros((2, 3)))
    omega, alpha = model.hover_trim(TABLE_1)
    plant.command(np.stack([0.9 * omega, 0.0 * omega]), np.stack([alpha, alpha]))  # below hover; stopped
    plant.advance(20)
    assert plant.landed.all()
    force = plant.sensors()[:, SENSOR_COLUMNS["specific_force_b"]]
    assert np.allclose(force, [[0, 0, G], [0, 0, G]])


@pytest.mark.parametrize("autopilot,kind", [(mavlink.MAV_AUTOPILOT_GENERIC, TriswarmSitl),
                                            (mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, ArduCopter),
                                            (mavlink.MAV_AUTOPILOT_PX4, Px4)])
def test_the_heartbeat_names_the_autopilot(autopilot, kind):
    assert type(pick("auto", autopilot, mavlink.MAV_TYPE_TRICOPTER)) is kind


def test_configuration_forces_one_and_an_unknown_one_is_said():
    assert type(pick("ardupilot", mavlink.MAV_AUTOPILOT_GENERIC, 0)) is ArduCopter
    with pytest.raises(AutopilotError, match="autopilot 8, which the companion does not know"):
        pick("auto", 8, 0)
    with pytest.raises(AutopilotError, match="--fc-profile must be one of"):
        pick("betaflight", 3, 0)


def test_arducopter_gives_the_vehicle_back_in_another_mode_but_not_in_its_scripts_failsafe():
    ap = ArduCopter()
    assert ap.control_mode == ARDUCOPTER_GUIDED and ap.mode_name(9) == "LAND" and ap.mode_name(250) == "mode 250"
    assert ap.released(ARDUCOPTER_GUIDED, False) is None
    assert ap.released(9, False) == "the flight controller is in LAND"
    assert ap.released(17, False) is None  # BRAKE before the script said why: its word decides
    ap.take(mavlink.MAVLink_named_value_float_message(0, b"TSW_STATE", 2.0))
    assert ap.released(17, False) is None  # its failsafe: fresh commands win it back
    ap.take(mavlink.MAVLink_named_value_float_message(0, b"TSW_STATE", 0.0))
    assert ap.released(17, False) == "the flight controller is in BRAKE"  # an operator's BRAKE
    assert not ArduCopter.COMMANDS_WHILE_IDLE and TriswarmSitl.COMMANDS_WHILE_IDLE


class OriginFc:
    """ArduPilot's EKF origin as its GCS handlers and EKF3 keep it (GCS_Common.cpp set_ekf_origin,
    NavEKF3::setOriginLLH, NavEKF3_core::InitialiseFilterBootstrap): a SET_GPS_GLOBAL_ORIGIN is taken
    while there is none; the EKF starting forgets one set before; its first fix sets one if there is
    none; SYS_STATUS says the AHRS enabled once the EKF has started. ``at_poll`` moves it on."""

    sysid = 1

    def __init__(self, ap, at_poll):
        self.ap, self.at_poll, self.polls, self.origin, self.started, self.sets = ap, at_poll, 0, None, False, 0

    def start(self):
        if not self.started:
            self.started, self.origin = True, None

    def fix(self):
        self.origin = self.origin or FIX

    def send(self, msg):
        if msg.get_type() == "SET_GPS_GLOBAL_ORIGIN":
            self.sets += 1
            self.origin = self.origin or (msg.latitude, msg.longitude, msg.altitude)
        elif msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE and msg.param1 == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            ahrs = mavlink.MAV_SYS_STATUS_AHRS if self.started else 0
            self.ap.take(mavlink.MAVLink_sys_status_message(mavlink.MAV_SYS_STATUS_AHRS, ahrs, 0, *[0] * 10))
        elif msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE and self.origin is not None:
            self.ap.take(mavlink.MAVLink_gps_global_origin_message(*self.origin, 0))

    async def wait(self, what, done, poke, say):
        import asyncio

        for _ in range(500):
            self.polls += 1
            self.at_poll(self, self.polls)
            if done():
                return
            if poke is not None:
                poke()
            await asyncio.sleep(0.002)
        raise AssertionError(f"still waiting for {what}")


HOME = (53.4668, -2.2339, 60.0)
FIX = (round(53.4667887 * 1e7), round(-2.2339188 * 1e7), 60_000)  # 1.26 m south and 1.24 m west of HOME


def _fly_origin(at_poll, monkeypatch):
    import asyncio

    import triswarm.companion.autopilots.ardupilot as ardupilot

    monkeypatch.setattr(ardupilot, "ORIGIN_ASK_S", 0.02)
    ap = ArduCopter(home=HOME)
    fc = OriginFc(ap, at_poll)
    said = []
    asyncio.run(ap._origin(fc, said.append))
    asyncio.run(fc.wait("positions (an EKF started, with an origin)", lambda: fc.started and fc.origin, None, None))
    asyncio.run(ap.ready(fc, said.append))
    return ap, fc, said


def test_the_ekf_origin_is_set_at_home_once_the_ekf_has_started(monkeypatch):
    def ekf(fc, poll):
        if poll > 30:
            fc.start()
        if poll > 60:
            fc.fix()

    ap, fc, said = _fly_origin(ekf, monkeypatch)
    assert fc.origin == (round(HOME[0] * 1e7), round(HOME[1] * 1e7), 60_000) and fc.sets >= 1
    assert ap.position_offset_e_m == pytest.approx((0.0, 0.0, 0.0), abs=1e-6) and not said


@pytest.mark.parametrize("when", ["before the companion came", "after it was set at home"])
def test_an_origin_the_ekf_took_from_its_fix_moves_every_position(monkeypatch, when):
    """The EKF had its origin at its first fix, or forgot the one set at home and took its fix (it
    initialised again): positions are moved by the distance from home, read once they flow."""
    def ekf(fc, poll):
        if when == "before the companion came":
            fc.start()
            fc.fix()
        elif poll > 30:
            fc.start()
            if fc.sets and fc.origin != FIX:
                fc.started = False  # (it initialised again: the origin set at home forgotten)
                fc.start()
                fc.fix()

    ap, fc, said = _fly_origin(ekf, monkeypatch)
    assert ap.position_offset_e_m == pytest.approx((-1.256, 1.25, 0.0), abs=0.01)
    assert said[-1].startswith("its EKF origin is 1.26 m south, 1.24 m west and 0.00 m above the swarm's home")
    assert (fc.sets == 0) == (when == "before the companion came")


def test_px4_over_mavlink_is_refused_with_the_reason():
    import asyncio

    with pytest.raises(AutopilotError, match="direct actuator commands only over its uORB bridge"):
        asyncio.run(Px4().prepare(SimpleNamespace(), print))


def test_each_autopilot_is_asked_for_its_own_takeoff():
    (mode, mode_params), (takeoff, params) = takeoff_commands(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 4.0)
    assert (mode, mode_params[1]) == (mavlink.MAV_CMD_DO_SET_MODE, ARDUCOPTER_GUIDED)
    assert takeoff == mavlink.MAV_CMD_NAV_TAKEOFF and params[6] == 4.0  # above home
    (takeoff, params), = takeoff_commands(mavlink.MAV_AUTOPILOT_GENERIC)
    assert takeoff == mavlink.MAV_CMD_NAV_TAKEOFF and math.isnan(params[6])  # its own TKO_ALT_M


def test_the_firmware_is_named_or_said_missing(tmp_path, monkeypatch):
    monkeypatch.delenv("TRISWARM_ARDUCOPTER", raising=False)
    with pytest.raises(FirmwareError, match="give --firmware PATH or set TRISWARM_ARDUCOPTER"):
        find_firmware(None)
    text = tmp_path / "arducopter"
    text.write_text("not a program")
    with pytest.raises(FirmwareError, match="not an executable file"):
        find_firmware(text)
    text.chmod(0o755)
    monkeypatch.setenv("TRISWARM_ARDUCOPTER", str(text))
    assert find_firmware(None) == text


def test_each_firmware_runs_from_the_shipped_files_in_a_folder_of_its_own(tmp_path):
    spec = FirmwareSpec(tmp_path / "arducopter", tmp_path / "vehicle-3", 3, (53.0, -2.0, 60.0), 1_800_000_000,
                        40123, 12000.0, 120.0, (("SIM_WIND_SPD", 2.0),))
    fw = Firmware(spec)
    fw.prepare()
    assert (spec.run_dir / "scripts" / "triswarm.lua").read_text().startswith("--[[")
    sitl = (spec.run_dir / "sitl.parm").read_text()
    assert "TSW_MAX_RPM 12000" in sitl and "SIM_WIND_SPD 2" in sitl and "FLTMODE_CH 0" in sitl
    cmd = fw.command({0: 5001, 1: 5002, 2: 5003})
    for expected in (["--model", "JSON:127.0.0.1"], ["--sysid", "3"], ["--sim-port-out", "40123"],
                     ["--start-time", "1800000000"], ["--serial0", "tcp:5001"], ["--serial2", "tcp:5003"]):
        assert any(cmd[k:k + 2] == expected for k in range(len(cmd))), (expected, cmd)
    assert cmd[cmd.index("--defaults") + 1].endswith("deploy/ardupilot/triswarm.parm," + str(spec.run_dir / "sitl.parm"))


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "triswarm.gcs.cli", *args], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("args,sentence", [
    (["--autopilot", "ardupilot", "--firmware", "/nonexistent/arducopter"], "/nonexistent/arducopter: not an executable"),
    (["--autopilot", "ardupilot", "--firmware", sys.executable, "--lockstep"], "--lockstep is for triswarm's"),
    (["--autopilot", "ardupilot", "--firmware", sys.executable, "--fc-profile", "px4"], "--fc-profile is for triswarm's"),
    (["--autopilot", "betaflight"], "--autopilot must be triswarm, ardupilot or px4"),
    (["--truth", "t.csv"], "--truth goes with --autopilot ardupilot or px4"),
    (["--autopilot", "px4", "--firmware", "/nonexistent/px4.tar.gz"], "/nonexistent/px4.tar.gz: no such file"),
    (["--autopilot", "px4", "--firmware", sys.executable, "--lockstep"], "--lockstep is for triswarm's"),
])
def test_sitl_up_refuses_what_ardupilot_cannot_do_in_one_sentence(tmp_path, args, sentence):
    result = run_cli("sitl", "up", "--manifest", str(tmp_path / "m.json"), *args)
    assert result.returncode == 2 and sentence in result.stderr and "Traceback" not in result.stderr, result.stderr
