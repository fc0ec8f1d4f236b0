"""A minimal onboard pilot for tests: flies one SITL vehicle over MAVLink with the math core
(FormationController + protocol (72) pinned to its own reference), event-driven on telemetry. Every
command carries the time of the state it answers, so it flies a lockstep SITL too (and answers the
states it does not command with NaN controls, which command nothing)."""

from __future__ import annotations

import math
import time

import numpy as np
from pymavlink import mavutil

from triswarm.protocol.agent import no_leader, pinned_input, reference_at
from triswarm.protocol.airframe import TABLE_1
from triswarm.protocol.controller import FormationController
from triswarm.protocol.formation import QuinticTransfer
from triswarm.protocol.mavlink import attitude_to_paper, encode_actuators, local_ned_to_paper
from triswarm.sitl.swarm import autopilot_design

from .sitl_helpers import command, read_param


class Pilot:
    def __init__(self, conn, sysid: int, rate_hz: float = 200.0) -> None:
        self.conn, self.sysid = conn, sysid
        self.design = autopilot_design(TABLE_1)
        self.ctrl = FormationController(self.design, 1, rate_hz)
        self.max_rpm = read_param(conn, sysid, "MOT_MAX_RPM")
        self.servo_deg = read_param(conn, sysid, "SERVO_LIM_DEG")
        for msg_id in (mavutil.mavlink.MAVLINK_MSG_ID_ATTITUDE, mavutil.mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED):
            ack = command(conn, sysid, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / rate_hz)
            assert ack.result == mavutil.mavlink.MAV_RESULT_ACCEPTED
        self.eta = None
        self.ref = None
        self.started = False
        self.log: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.statustexts: list[str] = []
        self.heartbeat = None

    def takeoff_to(self, altitude_m: float, duration_s: float = 3.0) -> None:
        self.target_alt, self.climb_s = altitude_m, duration_s

    def fly(self, sim_seconds: float, send: bool = True, wall_timeout_s: float = 60.0) -> None:
        """Run the loop for this much simulated time (or stop sending commands if send is False,
        still logging telemetry)."""
        t_end = None
        wall_deadline = time.monotonic() + wall_timeout_s
        while time.monotonic() < wall_deadline:
            msg = self.conn.recv_match(type=["ATTITUDE", "LOCAL_POSITION_NED", "STATUSTEXT", "HEARTBEAT"],
                                       blocking=True, timeout=1.0)
            if msg is None:
                continue
            if msg.get_type() == "STATUSTEXT":
                self.statustexts.append(msg.text)
                continue
            if msg.get_type() == "HEARTBEAT":
                self.heartbeat = msg
                continue
            if msg.get_type() == "ATTITUDE":
                self.eta = attitude_to_paper(msg.roll, msg.pitch, msg.yaw)
                continue
            if self.eta is None:
                continue
            t = msg.time_boot_ms / 1000.0
            pos = local_ned_to_paper(msg.x, msg.y, msg.z)
            vel = local_ned_to_paper(msg.vx, msg.vy, msg.vz)
            t_end = t_end if t_end is not None else t + sim_seconds
            if t >= t_end:
                return
            self.log.append((t, pos, self.eta.copy()))
            if not send:
                self.conn.mav.set_actuator_control_target_send(msg.time_boot_ms * 1000, 0, self.sysid, 1, [math.nan] * 8)
                continue
            y = np.concatenate([self.eta, pos])[None, :]
            if not self.started:
                x = np.zeros((1, 12))
                x[0, 6:9], x[0, 9:12] = self.eta, pos
                self.ctrl.reset(x)
                goal = pos.copy()
                goal[2] = self.target_alt
                self.ref = QuinticTransfer(pos, vel, goal, self.eta, np.zeros(3), [0.0, 0.0, self.eta[2]], t,
                                           self.climb_s)
                self.started = True
            xhat = self.ctrl.observe(y)
            ref = reference_at(self.design, self.ref.offsets, no_leader, t, self.ctrl.lead_s, self.ctrl.dt_s)
            v = pinned_input(self.design, xhat - ref.h, ref.x0, ref.gamma)
            act = self.ctrl.actuate(v)
            controls = encode_actuators(act.omega_rad_s[0], act.alpha_rad[0], self.max_rpm * math.pi / 30.0,
                                        math.radians(self.servo_deg))
            self.conn.mav.set_actuator_control_target_send(msg.time_boot_ms * 1000, 0, self.sysid, 1, controls)
        raise TimeoutError("telemetry stopped")
