"""ArduPilot's own firmware in the loop (ArduCopter SITL, ``sitl up --autopilot ardupilot``): the
shipped script's gating, and the companions flying it from the ground into a formation.

The firmware paces itself at real time and the companions fly it as they would a real flight
controller, so these are real-time tests: what they judge on the firmware's own clock (its
SERVO_OUTPUT_RAW and telemetry stamps) holds however busy the machine; the formation's bounds are
the issue's hard ones (0.25 m and 0.05 rad in the firmware's telemetry), with the truth's measured
worst beside them (docs/flight-controllers.md)."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pytest
from pymavlink import mavutil

from triswarm.gcs.recorder import Recorder
from triswarm.gcs.stack import Stack
from triswarm.protocol.autopilots import ARDUCOPTER_BRAKE, ARDUCOPTER_GUIDED

from .firmware_helpers import Peer, arducopter
from .stack_helpers import judge, judge_truth
from .poll import poll

pytestmark = pytest.mark.realtime
MAV = mavutil.mavlink
CMD_TIMEOUT_S = 0.2       # TSW_CMD_TOUT's default
READY_S = 150.0           # boot to a position estimate: 40 s of the firmware's clock, longer on a busy machine
START_DELAY_S = 60.0
"""Launch to the plan's start [s, wall]: the three were ready 34-38 s after their launch in make test,
and take off at the start."""
SERVO_HZ = 50.0
RESENT = "No JSON sensor message received"
"""What ArduPilot's JSON backend prints each second it waits for its physics' answer."""
TRUTH_BOUNDS = (0.10, 0.03)
"""The plant's truth of the turning triangle: the paper's position bound; 0.03 rad for EKF3's yaw (measured 0.032-0.038 m
and 0.014 rad; docs/flight-controllers.md)."""


class Commands:
    """A companion's commands at 100 Hz on a thread: SET_ACTUATOR_CONTROL_TARGET stamped with the
    newest ATTITUDE's time, as triswarm's companion stamps them."""

    def __init__(self, peer: Peer, controls: list[float]) -> None:
        self.peer, self.controls = peer, controls
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self.sent = 0

    def __enter__(self) -> "Commands":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while not self._stop.wait(0.01):
            att = self.peer.newest("ATTITUDE")
            stamp_us = att.time_boot_ms * 1000 if att is not None else 0
            self.peer.send(self.peer.conn.mav.set_actuator_control_target_encode(stamp_us, 0, 1, 1, self.controls))
            self.sent += 1


def outputs(msg) -> tuple[int, ...]:
    return (msg.servo1_raw, msg.servo2_raw, msg.servo3_raw, msg.servo4_raw, msg.servo5_raw, msg.servo6_raw)


def test_the_script_drives_the_outputs_only_armed_in_its_mode_and_lets_them_lapse(tmp_path):
    """Disarmed: a companion's commands reach no output. Armed in the companion's mode: they reach
    all six, PWM as the shipped mapping says, and a stranger's do not. Commands stopped: the
    overrides lapse within TSW_CMD_TOUT of the last one applied (the firmware's own clock), and the
    script brakes (its failsafe), saying so."""
    controls = [0.2, 0.2, 0.2, 0.25, 0.25, 0.25, 0.0, 0.0]  # (below hover: it stays on the ground)
    expected = (1200, 1200, 1200, 1625, 1625, 1625)
    with Stack(None, tmp_path, 1, companions=False, autopilot="ardupilot", firmware=arducopter()) as stack:
        links = stack.manifest["vehicles"][0]["links"]
        with Peer(links["companion"]["pymavlink"], 1, MAV.MAV_COMP_ID_ONBOARD_COMPUTER) as companion, \
                Peer(links["gcs"]["pymavlink"], 255, 190) as gcs:
            poll(lambda: companion.heard("HEARTBEAT"), 30, "a heartbeat from the firmware")
            companion.interval(MAV.MAVLINK_MSG_ID_ATTITUDE, 100.0)
            companion.interval(MAV.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, SERVO_HZ)
            poll(lambda: any("triswarm: ready" in t for t in gcs.texts()), 30, "the script's word")

            # disarmed: nothing the companion says reaches an output
            with Commands(companion, controls):
                first = len(companion.heard("SERVO_OUTPUT_RAW"))
                poll(lambda: len(companion.heard("SERVO_OUTPUT_RAW")) > first + 50, 30, "a second of outputs")
            disarmed = {outputs(m) for m in companion.heard("SERVO_OUTPUT_RAW")[first:]}
            assert not any(o[:3] == expected[:3] or o[3:] == expected[3:] for o in disarmed), disarmed

            # armed, in the companion's mode (GUIDED): the commands drive all six outputs
            gcs.set_mode(ARDUCOPTER_GUIDED, timeout_s=READY_S)
            gcs.until_accepted(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1, timeout_s=READY_S)
            with Commands(companion, controls):
                poll(lambda: outputs(companion.heard("SERVO_OUTPUT_RAW")[-1]) == expected, 10,
                         f"the outputs at {expected}")
                # a stranger (the ground station's system) commanding the motors changes nothing
                with Commands(gcs, [0.3, 0.3, 0.3, 0.0, 0.0, 0.0, 0.0, 0.0]):
                    mark = len(companion.heard("SERVO_OUTPUT_RAW"))
                    poll(lambda: len(companion.heard("SERVO_OUTPUT_RAW")) > mark + 25, 10, "half a second of outputs")
                driven = [outputs(m) for m in companion.heard("SERVO_OUTPUT_RAW")[mark:]]
                assert all(o == expected for o in driven), set(driven)
                stopped_at = len(companion.heard("SERVO_OUTPUT_RAW"))

            # commands stopped: the overrides lapse within TSW_CMD_TOUT, and the script brakes
            poll(lambda: any(outputs(m) != expected for m in companion.heard("SERVO_OUTPUT_RAW")[stopped_at:]), 10,
                     "the outputs to lapse")
            after = companion.heard("SERVO_OUTPUT_RAW")[stopped_at - 1:]
            k = next(i for i, m in enumerate(after) if outputs(m) != expected)
            last_driven_us, lapsed_us = after[k - 1].time_usec, after[k].time_usec
            lapse_s = (lapsed_us - last_driven_us) / 1e6
            assert lapse_s <= CMD_TIMEOUT_S + 1.0 / SERVO_HZ + 0.005, f"outputs still driven {lapse_s:.3f} s on"
            poll(lambda: any(h.custom_mode == ARDUCOPTER_BRAKE for h in gcs.heard("HEARTBEAT")
                                 if h.get_srcComponent() == 1), 10, "the failsafe's BRAKE")
            assert any("triswarm: failsafe" in t for t in gcs.texts()), gcs.texts()[-5:]
            assert any(m.name.rstrip("\x00") == "TSW_STATE" and m.value == 2 for m in gcs.heard("NAMED_VALUE_FLOAT"))
            gcs.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)


def test_a_firmware_that_ends_leaves_the_clock_and_the_others_are_not_kept_waiting(tmp_path):
    """Two firmwares on one lockstep plant; the first killed: the plant says so and steps on with
    the second at once. The second never waits for its answer long enough for ArduPilot to resend
    its frame (its log's "No JSON sensor message received", one per second without an answer; the
    plant used to wait 3 s for a silent firmware, and flying firmwares kept waiting that long
    aborted one after another when the answers came again)."""
    with Stack(None, tmp_path, 2, companions=False, autopilot="ardupilot", firmware=arducopter()) as stack:
        first, second = stack.manifest["vehicles"]
        with Peer(second["links"]["gcs"]["pymavlink"], 255, 190) as gcs:
            poll(lambda: gcs.heard("HEARTBEAT"), 60, "a heartbeat from the second firmware")
            second_log = Path(second["run_dir"]) / "firmware.log"
            resent = second_log.read_text(errors="replace").count(RESENT)
            os.kill(first["pid"], signal.SIGKILL)
            poll(lambda: f"vehicle {first['sysid']}: " in stack.log("sitl"), 10, "the plant saying the first left")
            beats = len(gcs.heard("HEARTBEAT"))
            time.sleep(4.0)  # (longer than the 3 s the plant used to wait)
            assert second_log.read_text(errors="replace").count(RESENT) == resent, \
                "the second firmware was kept waiting a second for its physics: " + second_log.read_text()[-300:]
            assert len(gcs.heard("HEARTBEAT")) >= beats + 2  # (the second flies on: 1 Hz)


def three_drone_plan(tmp_path):
    from triswarm.protocol.plan import plan_from_dict

    spec = {"name": "ardupilot-three", "drones": 3, "duration_s": 40.0,
            "leader": {"position_m": [0.0, 0.0, 0.0]},
            "formation": {"type": "rotating-polygon", "radius_m": 4.0, "altitude_m": 6.0, "rate_rad_s": 0.3}}
    import tomli_w

    path = tmp_path / "plan.toml"
    path.write_text(tomli_w.dumps(spec))
    return path, plan_from_dict(spec, str(path))


@pytest.mark.slow
def test_three_drones_take_off_from_the_ground_and_fly_a_formation_on_ardupilot(tmp_path):
    """Three ArduCopter firmwares, one companion process flying all three with --autostart: each
    drone rests on the ground, ArduPilot takes it off (GUIDED) and hands it over, and the three fly
    a turning triangle from the plan's start. Judged on the firmwares' own telemetry (EKF3) with the
    issue's bounds, and on the plant's truth."""
    path, plan = three_drone_plan(tmp_path)
    with Stack(path, tmp_path / "stack", 3, start_delay_s=START_DELAY_S, rate_hz=100.0, agents_per_process=0,
               autopilot="ardupilot", firmware=arducopter()) as stack, Recorder(stack.manifest) as rec:
        start = stack.start_at
        end = start + plan.duration_s
        poll(lambda: rec.now() >= end, START_DELAY_S + plan.duration_s + 60.0, "the end of the plan", every_s=0.5)
        t_from = plan.settled_from_s
        ok, report = judge(plan, rec, start, t_from, plan.duration_s, position_bound_m=0.25, attitude_bound_rad=0.05)
        logs = stack.log("companion-1")
    truth_path = tmp_path / "stack" / "truth.csv"  # (whole once the SITL has stopped)
    truth_ok, truth_report = judge_truth(plan, truth_path, rec, start, t_from, plan.duration_s,
                                         position_bound_m=TRUTH_BOUNDS[0], attitude_bound_rad=TRUTH_BOUNDS[1])
    print(f"worst over [{t_from}, {plan.duration_s}] s: telemetry {report}, truth {truth_report}")
    assert logs.count("taking off to") == 3, logs[-3000:]
    assert ok, f"telemetry over [{t_from}, {plan.duration_s}] s: {report}"
    assert truth_ok, f"truth over [{t_from}, {plan.duration_s}] s: {truth_report}"
    first = {}
    for line in truth_path.read_text().splitlines()[1:]:
        sysid, _, _, _, z = line.split(",")[:5]
        first.setdefault(int(sysid), float(z))
    assert first == {1: 0.0, 2: 0.0, 3: 0.0}, f"every drone starts on the ground: {first}"
