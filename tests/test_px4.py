"""PX4's own firmware in the loop (px4_sitl_zenoh, ``sitl up --autopilot px4``): the companions fly
it in offboard mode with direct actuator setpoints over its Zenoh bridge, from the ground.

PX4 and the plant run at real time and the companions fly them as they would real flight
controllers, so these are real-time tests. The formation is judged with the issue's bounds on
PX4's own telemetry (EKF2, over MAVLink to the ground station) and the plant's truth beside it;
the offboard loss on PX4's modes as its ground-station link says them (HEARTBEAT, once a second)."""

from __future__ import annotations

import math
import os
import signal
import time

import pytest
import tomli_w
import zenoh

from triswarm.companion.flight import LAND_DETECT_S, LAND_SINK_M
from triswarm.gcs.link import GroundLink
from triswarm.gcs.recorder import Recorder
from triswarm.gcs.swarm import command_all
from triswarm.gcs.stack import Stack
from triswarm.protocol import metrics
from triswarm.protocol import px4_msgs as px4
from triswarm.protocol.mavlink import COMP_ONBOARD
from triswarm.protocol.mavlink import mavlink as MAV
from triswarm.protocol.plan import plan_from_dict

from .firmware_helpers import px4_package
from .poll import poll
from .stack_helpers import judge, judge_truth

pytestmark = pytest.mark.realtime
START_DELAY_S = 20.0
"""Launch to the plan's start [s, wall]. The firmwares are ready 4 s after their launch, but with 12 s
two fresh-clone runs of four lost one drone's offboard stream (PX4 heard none of the companion's
commands from 40 ms after its switch to offboard, while its own topics still came) and PX4 ended
that flight; with 20 s no run has. (Two likely causes, found later: the phase change that goes with
the switch saved the companion's state in the control loop, whose fsync took up to 2.3 s on a busy
machine; and the plant, behind the wall clock after a stall of its process (most at start-up),
caught up flat out and ran PX4's clock ahead of the commands. Both are mended (the state's own
thread; a catch-up at 1.25x at most: STALL_S below). The 20 s are kept.)"""
STALL_AT_S, STALL_S = 12.0, 0.8
"""In the climb, the SITL's process (the plant, PX4's clock, and the Zenoh router) is stopped this long
[s, wall]: a starved machine. (A plant that caught up flat out ran PX4's clock 0.8 s ahead of its
companion's commands in milliseconds, and PX4 ended all three flights.)"""
FLIGHT_DRONES = 2
"""The formation flight's drones: three PX4s, their plant and a companion flying all three did not fit
in real time on a two-core machine three times slower than usual (the companion process 40 % late
on its ticks, its latency p99 25 ms against the law's 15 ms of slack, and the formation lost within
10 s, with or without the stall), where each drone's own computers would carry one apiece. Two keep
a formation, its takeoff, stall and landing, at two thirds of the load;
tests/bench/bench_px4.py flies six."""
OFFBOARD_LOSS_S = 1.0
"""COM_OF_LOSS_T of the shipped airframe (deploy/px4/)."""
HEARTBEAT_S = 1.0
LAND_SPEED = 0.5  # the companion's LAND_SPEED default [m/s]
TRUTH_BOUNDS = (0.25, 0.05)
"""The plant's truth of the turning formation: EKF2's estimate error comes on top of the telemetry's
(measured 0.03-0.21 m and 0.01-0.04 rad; docs/flight-controllers.md)."""


def plan_file(tmp_path, spec: dict):
    path = tmp_path / "plan.toml"
    path.write_text(tomli_w.dumps(spec))
    return path, plan_from_dict(spec, str(path))


def modes(rec: Recorder, sysid: int, since_unix: float = -math.inf) -> list[tuple[float, str, bool]]:
    return [(t, px4.mode_name(mode), armed) for t, mode, armed in rec.modes.get(sysid, []) if t >= since_unix]


@pytest.mark.slow
def test_drones_take_off_from_the_ground_fly_a_formation_and_land_on_px4(tmp_path):
    """FLIGHT_DRONES PX4 firmwares, one companion process flying them all with --autostart: each drone
    rests on the ground, the companion switches PX4 to offboard and takes it off with its own
    commands, and they fly a turning formation from the plan's start; in the climb the SITL's
    process is stopped for STALL_S and goes on, and no PX4 ends its flight. Judged on PX4's own
    telemetry with the issue's bounds, and on the plant's truth. The firmware subscribes to what
    the companion publishes with the very type hashes the companion computed from the fields.
    Then the ground station asks the companions to land: each descends (LAND_SPEED, 0.5 m/s) and
    disarms its drone once PX4's land detector says it is down, or by force 5 s on."""
    path, plan = plan_file(tmp_path, {
        "name": "px4-flight", "drones": FLIGHT_DRONES, "duration_s": 40.0, "leader": {"position_m": [0.0, 0.0, 0.0]},
        "formation": {"type": "rotating-polygon", "radius_m": 4.0, "altitude_m": 6.0, "rate_rad_s": 0.3}})
    drones = tuple(range(1, FLIGHT_DRONES + 1))
    with Stack(path, tmp_path / "stack", FLIGHT_DRONES, start_delay_s=START_DELAY_S, rate_hz=100.0, agents_per_process=0,
               autopilot="px4", firmware=px4_package()) as stack, Recorder(stack.manifest) as rec, \
            GroundLink(stack.endpoints()) as link:
        announced = subscriptions(stack.manifest["zenoh_router"])
        start = stack.start_at
        end = start + plan.duration_s
        poll(lambda: rec.now() >= start + STALL_AT_S, START_DELAY_S + STALL_AT_S + 60.0, "the climb", every_s=0.05)
        os.kill(stack.procs["sitl"].pid, signal.SIGSTOP)  # (the plant and the router, as a starved machine stalls them)
        try:
            time.sleep(STALL_S)
        finally:
            os.kill(stack.procs["sitl"].pid, signal.SIGCONT)
        poll(lambda: rec.now() >= end, START_DELAY_S + plan.duration_s + 60.0, "the end of the plan", every_s=0.5)
        # (the ground station has been connected all along, and the flight is judged once the drones are
        # down: nothing of the test's own work competes with the companions as they land)
        t_from = plan.settled_from_s
        asked = rec.now()
        landing = command_all(link, list(drones), COMP_ONBOARD, MAV.MAV_CMD_NAV_LAND, [])
        down_s = (6.0 + LAND_SINK_M) / LAND_SPEED + LAND_DETECT_S + 5.0
        try:
            poll(lambda: all(modes(rec, i) and not modes(rec, i)[-1][2] for i in drones), down_s + 30.0,
                 "every drone disarmed", every_s=0.5)
        except AssertionError as exc:
            _, report = judge(plan, rec, start, t_from, plan.duration_s)
            said = [line for line in stack.log("companion-1").splitlines() if "companion " in line]
            raise AssertionError(f"{exc}; flight over [{t_from}, {plan.duration_s}] s: {report}; "
                                 f"the companions said:\n" + "\n".join(said[-40:]) + "\n" +
                                 firmware_said(tmp_path / "stack", drones)) from None
        disarmed = rec.now()
        history = {i: modes(rec, i) for i in drones}
        heights = {i: rec.samples.tracks(start)[i].position_m[-1][2] for i in drones}
    ok, report = judge(plan, rec, start, t_from, plan.duration_s, position_bound_m=0.25, attitude_bound_rad=0.05)
    truth_ok, truth_report = judge_truth(plan, tmp_path / "stack" / "truth.csv", rec, start, t_from, plan.duration_s,
                                         position_bound_m=TRUTH_BOUNDS[0], attitude_bound_rad=TRUTH_BOUNDS[1])
    print(f"worst over [{t_from}, {plan.duration_s}] s: telemetry {report}, truth {truth_report}")
    for i in drones:
        ns = f"px4_{i}"
        for topic, name in px4.TOPICS_IN.items():
            assert announced.get(px4.topic_path(ns, "in", topic)) == px4.type_hash(name), (ns, topic, announced)
        assert ("OFFBOARD", True) in [(m, a) for _, m, a in history[i]], history[i]
        assert "TERMINATION" not in {m for _, m, _ in history[i]}, history[i]
    assert ok, (f"telemetry over [{t_from}, {plan.duration_s}] s: {report}; the worst position at plan time "
                f"{worst_instants(plan, rec, start, t_from, plan.duration_s)}")  # (computed on a failure only)
    assert truth_ok, f"truth over [{t_from}, {plan.duration_s}] s: {truth_report}"
    assert all(ok for ok, _ in landing.values()), landing
    assert disarmed - asked <= down_s, (asked, disarmed)  # (on PX4's clock)
    assert all(h < 0.1 for h in heights.values()), heights


def worst_instants(plan, rec: Recorder, start: float, t_from: float, t_to: float) -> dict[int, float]:
    """Per drone, the plan time [s] of its worst position error in the telemetry (for a failure's report)."""
    t, pos, eta = rec.arrays(start, t_from=t_from, t_to=t_to)
    pe, _ = metrics.formation_errors(plan, t, pos, eta)
    return {k + 1: round(float(t[pe[:, k].argmax()]), 2) for k in range(pe.shape[1])}


def firmware_said(stack_dir, sysids) -> str:
    """What each PX4 said on its console after it armed (its failsafes among it), for a failure's report."""
    told = []
    for i in sysids:
        lines = (stack_dir / "firmware" / f"vehicle-{i}" / "firmware.log").read_text(errors="replace").splitlines()
        armed = max((k for k, line in enumerate(lines) if "Armed by" in line), default=0)
        told += [f"PX4 {i}: {line}" for line in lines[armed:] if line.strip()][:30]
    return "\n".join(told)


def subscriptions(router: str) -> dict[str, str]:
    """Topic -> type hash of every subscription the firmwares announce (their liveliness tokens)."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", f'["{router}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    found: dict[str, str] = {}
    with zenoh.open(cfg) as session:
        for reply in session.liveliness().get("@ros2_lv/**", timeout=5.0):
            told = px4.announced(str(reply.ok.key_expr)) if reply.ok is not None else None
            if told is not None and "/MS/" in str(reply.ok.key_expr):
                found[told[0]] = told[2]
    return found


def test_a_hover_then_offboard_lost_on_px4(tmp_path):
    """One drone hovers at 4 m. Its companion killed, PX4 terminates the flight (the shipped
    COM_OBL_RC_ACT) within COM_OF_LOSS_T of the last command (said on its next HEARTBEAT:
    MAV_STATE_FLIGHT_TERMINATION): the motors stop and the vehicle comes down, never up (the plant's
    truth)."""
    path, plan = plan_file(tmp_path, {
        "name": "px4-hover", "drones": 1, "duration_s": 120.0, "leader": {"position_m": [0.0, 0.0, 0.0]},
        "formation": {"type": "rotating-polygon", "radius_m": 0.0, "altitude_m": 4.0, "rate_rad_s": 0.0}})
    with Stack(path, tmp_path / "stack", 1, start_delay_s=START_DELAY_S, rate_hz=100.0, autopilot="px4",
               firmware=px4_package()) as stack, Recorder(stack.manifest) as rec:
        start = stack.start_at
        poll(lambda: rec.now() >= start + 22.0, START_DELAY_S + 22.0 + 60.0, "22 s of the hover", every_s=0.2)
        ok, report = judge(plan, rec, start, 15.0, 22.0, position_bound_m=0.10, attitude_bound_rad=0.02)
        assert ok, f"hover over [15, 22] s: {report}"

        killed = time.time()
        stack.procs["companion-1"].kill()
        terminated = lambda: rec.heartbeats[1].system_status == MAV.MAV_STATE_FLIGHT_TERMINATION  # noqa: E731
        poll(terminated, 10.0, "PX4's flight termination")
        bound_s = OFFBOARD_LOSS_S + HEARTBEAT_S + 1.5
        assert time.time() - killed <= bound_s, f"terminated {time.time() - killed:.2f} s on"
        height = lambda: rec.samples.tracks(start)[1].position_m[-1][2]  # noqa: E731
        poll(lambda: height() < 0.1, 30.0, "the vehicle on the ground", every_s=0.2)
    truth = [line.split(",") for line in (tmp_path / "stack" / "truth.csv").read_text().splitlines()[1:]]
    after = [float(r[4]) for r in truth if float(r[1]) >= (killed - stack.manifest["clock"]["boot_unix_s"])]
    assert after and max(after) < 4.5 and after[-1] < 0.1, (max(after, default=None), after[-1:])
