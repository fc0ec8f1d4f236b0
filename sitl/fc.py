"""The autopilot logic of one simulated tri-rotor: modes, arming, failsafe, the command and
parameter protocols, a battery and counters. What it sends is ``telemetry.py``'s.

No sockets and no clock: the swarm passes sim time and a sensor snapshot; handlers return the
messages to send (pymavlink message objects) and the link layer packs them.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from triswarm.protocol.airframe import Airframe, ParameterError
from triswarm.protocol.frames import LocalProjection
from triswarm.protocol.mavlink import ACTUATOR_GROUP, CustomMode, decode_actuators, mavlink, plausible_unix_us

from . import telemetry
from .params import AIRFRAME_PARAMS, READ_ONLY_PARAMS, airframe_from_params, param_specs
from .profiles import TRISWARM, Profile
from .telemetry import STREAM_CODE, Snapshot, _us

LINKS = ("companion", "gcs")
LINK_PREFIX = {"companion": "SC", "gcs": "SG"}
FORCE_MAGIC = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2: force


@dataclass
class Outgoing:
    msg: object
    link: str | None  # None: every link


class FlightController:
    """One vehicle's autopilot. ``sysid`` from 1; ``start_m`` its resting place (paper frame)."""

    def __init__(self, sysid: int, airframe: Airframe, home: LocalProjection, start_m: np.ndarray,
                 boot_unix_s: float, profile: Profile = TRISWARM) -> None:
        self.sysid = sysid
        self.profile = profile
        """How its companion link streams and honours SET_MESSAGE_INTERVAL (``profiles.py``)."""
        self.nominal = airframe
        self.home = home
        self.start_m = np.asarray(start_m, dtype=float)
        self.boot_unix_s = boot_unix_s
        self.specs = param_specs(airframe, profile)
        self.spec_by_name = {p.name: p for p in self.specs}
        self.params = {p.name: float(p.default) for p in self.specs}
        self.params_version = 0
        """Counts the parameter changes (a reader caches what it derives from them)."""
        self.param_index = {p.name: i for i, p in enumerate(self.specs)}
        self._airframe = self._airframe_from_params()
        self.armed = False
        self.mode = CustomMode.EXTERNAL
        self.failsafe = False
        self.failsafe_since_s = 0.0
        self.landed_since_s = 0.0
        self.ext_omega = np.zeros(3)
        self.ext_alpha = np.zeros(3)
        self.last_command_s = -math.inf
        self.answered_us = -1
        """The newest telemetry time [boot us] the companion has answered (lockstep)."""
        self.takeoff_alt_m: float | None = None
        self.counters: Counter[str] = Counter()
        self.outbox: list[Outgoing] = []
        self.mode_changed = False
        """Set when the swarm must (re)start its own controller for this vehicle."""
        self.actuators_changed = False
        """Set when an actuator command arrived that the plant has not been given yet."""
        self.on_command = lambda: None
        """Called when an actuator command arrived (the swarm learns which vehicles to command)."""
        self.airframe_changed = False
        self.rates_changed = False
        """Set when a stream rate changed: the server reschedules this vehicle's streams."""
        self.battery_used_mah = 0.0
        self.battery_voltage_v = self._open_circuit_voltage()
        self.battery_current_a = 0.0
        self.clock_ppm = 0.0
        """How much faster this autopilot's clock runs than simulated time [ppm]: every stamp it sends
        (telemetry, SYSTEM_TIME, TIMESYNC) is on its clock."""
        self.rx_time_s: float | None = None
        """Simulated time at which the message being handled arrived (the wall clock's, in real time;
        None: the step's)."""

    def clock_s(self, now_s: float) -> float:
        """This autopilot's clock [s since boot] at simulated time ``now_s``."""
        return now_s * (1.0 + self.clock_ppm * 1e-6)

    # -- parameters -------------------------------------------------------------------------

    def airframe(self) -> Airframe:
        """The plant as its parameters say (validated when they were set)."""
        return self._airframe

    def _airframe_from_params(self) -> Airframe:
        return airframe_from_params(self.nominal, self.params)

    def set_param(self, name: str, value: float) -> str | None:
        """Set a parameter; returns None, or the reason it was refused."""
        spec = self.spec_by_name.get(name)
        if spec is None:
            return f"unknown parameter {name}"
        if name in READ_ONLY_PARAMS:
            return f"{name} is read-only"
        if not math.isfinite(value):
            return f"{name} must be a finite number"
        if not spec.lo <= value <= spec.hi:
            return f"{name} must be within [{spec.lo:g}, {spec.hi:g}], got {value:g}"
        old = self.params[name]
        if float(value) == old:
            return None  # (the same value again: nothing changes, nothing to redo)
        self.params[name] = float(value)
        self.params_version += 1
        if name in AIRFRAME_PARAMS:
            try:
                self._airframe = self._airframe_from_params()
            except ParameterError as exc:
                self.params[name] = old
                return str(exc)
            self.airframe_changed = True
        elif name.endswith("_HZ"):
            self.rates_changed = True
        return None

    def stream_rate_hz(self, link: str, msg_id: int) -> float:
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            return 1.0
        code = STREAM_CODE.get(msg_id)
        return 0.0 if code is None else self.params[f"{LINK_PREFIX[link]}_{code}_HZ"]

    @property
    def drops(self) -> int:
        """Frames dropped, all reasons."""
        return sum(v for k, v in self.counters.items() if k.startswith("drop_"))

    def _param_value(self, name: str):
        return mavlink.MAVLink_param_value_message(name.encode(), self.params[name], mavlink.MAV_PARAM_TYPE_REAL32,
                                                   len(self.specs), self.param_index[name])

    # -- state ------------------------------------------------------------------------------

    def announce(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        self.outbox.append(Outgoing(mavlink.MAVLink_statustext_message(severity, text[:50].encode()), None))

    def set_mode(self, mode: CustomMode, now_s: float, failsafe: bool = False) -> None:
        changed = mode != self.mode or failsafe != self.failsafe
        self.mode = mode
        self.failsafe = failsafe
        if changed:
            self.mode_changed = True
            self.outbox.append(Outgoing(self.heartbeat(), None))  # clients learn the state at once

    def arm(self, now_s: float, snap: Snapshot, force: bool) -> tuple[int, str | None]:
        if self.armed:
            return mavlink.MAV_RESULT_ACCEPTED, None
        if not force:
            reason = self._arming_problem(snap)
            if reason:
                return mavlink.MAV_RESULT_DENIED, reason
        self.armed = True
        self.last_command_s = now_s  # the grace period before the failsafe starts counting
        if self.mode != CustomMode.TAKEOFF:
            self.set_mode(CustomMode.EXTERNAL, now_s)
        self.outbox.append(Outgoing(self.heartbeat(), None))
        self.announce("armed")
        return mavlink.MAV_RESULT_ACCEPTED, None

    def _arming_problem(self, snap: Snapshot) -> str | None:
        if self.battery_remaining_pct() < self.params["BAT_ARM_PCT"]:
            return f"arming refused: battery {self.battery_remaining_pct():.0f}% below {self.params['BAT_ARM_PCT']:.0f}%"
        if not snap.landed:
            return "arming refused: not on the ground"
        tilt = math.degrees(max(abs(snap.euler_rad[0]), abs(snap.euler_rad[1])))
        if tilt > 30.0:
            return f"arming refused: tilted {tilt:.0f} deg, more than 30"
        return None

    def disarm(self, now_s: float, snap: Snapshot | None, force: bool, reason: str = "disarmed") -> tuple[int, str | None]:
        if not self.armed:
            return mavlink.MAV_RESULT_ACCEPTED, None
        if not force and not snap.landed:
            return mavlink.MAV_RESULT_DENIED, "disarm refused: in the air (force to kill)"
        self.armed = False
        self.set_mode(CustomMode.EXTERNAL, now_s)
        self.ext_omega[:] = 0.0
        self.outbox.append(Outgoing(self.heartbeat(), None))
        self.announce(reason)
        return mavlink.MAV_RESULT_ACCEPTED, None

    def tick(self, now_s: float, landed: bool, internal_done: bool) -> None:
        """Failsafe timers and automatic mode changes, once per control period (the battery:
        ``drain_batteries``)."""
        if landed:
            if self.landed_since_s < 0:
                self.landed_since_s = now_s
        else:
            self.landed_since_s = -1.0
        if self.armed:
            silent_s = now_s - self.last_command_s
            if self.mode == CustomMode.EXTERNAL and landed:
                # nothing to hold on the ground: disarm when nobody flies the drone (preflight timeout)
                if silent_s > self.params["DISARM_PRFLT_S"]:
                    self.disarm(now_s, None, force=True,
                                reason=f"disarmed: no actuator command for {self.params['DISARM_PRFLT_S']:g} s on ground")
            elif self.mode == CustomMode.EXTERNAL and silent_s > self.params["FS_TIMEOUT_S"]:
                self.set_mode(CustomMode.HOLD, now_s, failsafe=True)
                self.announce(f"failsafe: no actuator command for {self.params['FS_TIMEOUT_S']:g} s, holding",
                              mavlink.MAV_SEVERITY_CRITICAL)
                self.failsafe_since_s = now_s
            elif (self.mode == CustomMode.HOLD and self.failsafe
                  and now_s - self.failsafe_since_s > self.params["FS_LAND_DELAY_S"]):
                self.set_mode(CustomMode.LAND, now_s, failsafe=True)
                self.announce("failsafe: landing", mavlink.MAV_SEVERITY_CRITICAL)
            elif self.mode == CustomMode.TAKEOFF and internal_done:
                self.set_mode(CustomMode.HOLD, now_s)
                self.announce("takeoff complete, holding")
            elif (self.mode == CustomMode.LAND and landed and self.landed_since_s >= 0
                  and now_s - self.landed_since_s >= self.params["DISARM_DELAY_S"]):
                self.disarm(now_s, None, force=True, reason="landed, disarmed")

    # -- battery ----------------------------------------------------------------------------

    def _open_circuit_voltage(self) -> float:
        return float(open_circuit_voltage_v(self.params["BAT_CELLS"], self.battery_used_mah, self.params["BAT_CAP_MAH"]))

    def battery_remaining_pct(self) -> float:
        return max(0.0, 100.0 * (1.0 - self.battery_used_mah / self.params["BAT_CAP_MAH"]))

    # -- incoming messages ------------------------------------------------------------------

    def handle(self, msg, link: str, now_s: float, snap: Snapshot) -> list[Outgoing]:
        """React to one parsed message that came in on ``link``. Returns replies."""
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            reason = str(getattr(msg, "reason", ""))
            self.counters["drop_bad_crc" if "CRC" in reason else "drop_bad_frame"] += 1
            return []
        self.counters["rx_frames"] += 1
        target_sys = getattr(msg, "target_system", 0)
        if target_sys not in (0, self.sysid):
            self.counters["drop_foreign_system"] += 1
            return []
        target_comp = getattr(msg, "target_component", 0)
        if target_comp not in (0, mavlink.MAV_COMP_ID_AUTOPILOT1):
            self.counters["not_for_autopilot"] += 1
            return []
        handler = getattr(self, f"_on_{mtype.lower()}", None)
        if handler is None:
            self.counters["ignored_messages"] += 1
            return []
        return handler(msg, link, now_s, snap)

    def _on_set_actuator_control_target(self, msg, link, now_s, snap):
        if msg.group_mlx != ACTUATOR_GROUP:
            self.counters["drop_actuator_group"] += 1
            return []
        if msg.time_usec > _us(self.clock_s(now_s)) + 1000:  # (1 ms: stamps are whole milliseconds)
            self.counters["drop_actuator_from_the_future"] += 1  # (an answer to a state not yet sent)
            return []
        if link == "companion":
            self.answered_us = max(self.answered_us, msg.time_usec)
        if all(math.isnan(c) for c in msg.controls[:6]):  # an answer that commands nothing (lockstep)
            self.counters["actuator_no_command"] += 1
            return []
        af = self.airframe()
        dec = decode_actuators(msg.controls, af.max_rotor_speed_rad_s, af.servo_limit_rad)
        if dec.dropped_non_finite:
            self.counters["drop_actuator_non_finite"] += 1
            return []
        self.counters["actuator_values_clamped"] += dec.clamped
        if not self.armed:
            self.counters["actuator_ignored_disarmed"] += 1
            return []
        if self.mode != CustomMode.EXTERNAL:
            if not self.failsafe:
                self.counters["actuator_ignored_mode"] += 1
                return []
            self.set_mode(CustomMode.EXTERNAL, now_s)
            self.announce("actuator commands back, failsafe cleared", mavlink.MAV_SEVERITY_WARNING)
        self.ext_omega[:] = dec.omega_rad_s
        self.ext_alpha[:] = dec.alpha_rad
        self.actuators_changed = True
        self.on_command()
        self.last_command_s = now_s
        self.counters["actuator_commands"] += 1
        return []

    def _on_system_time(self, msg, link, now_s, snap):
        """Someone sets the clock (as autopilots take it from a ground station): its Unix time steps
        to ``time_unix_usec`` now, a whole millisecond; its boot time runs on."""
        if msg.time_unix_usec == 0:
            return []  # (the sender has no time)
        if not plausible_unix_us(msg.time_unix_usec):
            self.counters["drop_clock_implausible"] += 1
            return []
        self.boot_unix_s = round(msg.time_unix_usec / 1000.0 - now_s * 1000.0) / 1000.0
        self.counters["clock_set"] += 1
        return []

    def _on_timesync(self, msg, link, now_s, snap):
        if msg.tc1 != 0:
            return []
        # (stamped on arrival, as an autopilot does: in real time, the wall clock's, not the step's)
        fields = dict(tc1=round(self.clock_s(now_s if self.rx_time_s is None else self.rx_time_s) * 1e9), ts1=msg.ts1)
        if "target_system" in msg.get_fieldnames():
            fields.update(target_system=msg.get_srcSystem(), target_component=msg.get_srcComponent())
        return [Outgoing(mavlink.MAVLink_timesync_message(**fields), link)]

    def _on_ping(self, msg, link, now_s, snap):
        if msg.target_system != 0:
            return []  # a reply to somebody's ping, not a request
        return [Outgoing(mavlink.MAVLink_ping_message(msg.time_usec, msg.seq, msg.get_srcSystem(),
                                                      msg.get_srcComponent()), link)]

    def _on_file_transfer_protocol(self, msg, link, now_s, snap):
        """No MAVLink FTP here (and none claimed): answer every request with a NAK so a client that
        tries FTP first (MAVProxy fetching parameters) falls back at once instead of timing out."""
        req = bytes(msg.payload)
        if len(req) < 12:
            return []
        seq, session, opcode = int.from_bytes(req[0:2], "little"), req[2], req[3]
        if opcode >= 128:
            return []  # an ACK or NAK, not a request
        error = 10 if opcode in (4, 5) else 7  # OpenFileRO/OpenFileWO: FileNotFound; else UnknownCommand
        payload = bytearray(251)
        payload[0:2] = ((seq + 1) & 0xFFFF).to_bytes(2, "little")
        payload[2], payload[3], payload[4], payload[5] = session, 129, 1, opcode
        payload[12] = error
        return [Outgoing(mavlink.MAVLink_file_transfer_protocol_message(0, msg.get_srcSystem(), msg.get_srcComponent(),
                                                                        list(payload)), link)]

    def _on_param_request_list(self, msg, link, now_s, snap):
        return [Outgoing(self._param_value(p.name), link) for p in self.specs]

    def _on_param_request_read(self, msg, link, now_s, snap):
        if msg.param_index >= 0:
            if msg.param_index >= len(self.specs):
                self.announce(f"no parameter with index {msg.param_index}", mavlink.MAV_SEVERITY_WARNING)
                return []
            name = self.specs[msg.param_index].name
        else:
            name = _param_name(msg.param_id)
            if name not in self.params:
                self.counters["param_unknown"] += 1
                self.announce(f"unknown parameter {name}", mavlink.MAV_SEVERITY_WARNING)
                return []
        return [Outgoing(self._param_value(name), link)]

    def _on_param_set(self, msg, link, now_s, snap):
        name = _param_name(msg.param_id)
        problem = self.set_param(name, float(msg.param_value))
        if problem:
            self.counters["param_refused"] += 1
            self.announce(f"param refused: {problem}", mavlink.MAV_SEVERITY_WARNING)
            if name not in self.params:
                return []
        return [Outgoing(self._param_value(name), None)]

    def _on_command_long(self, msg, link, now_s, snap):
        params = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7]
        return self._command(msg, msg.command, params, link, now_s, snap)

    def _on_command_int(self, msg, link, now_s, snap):
        params = [msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z]
        return self._command(msg, msg.command, params, link, now_s, snap)

    # Parameters (from 1) that must be finite numbers for a command to mean anything; NaN elsewhere
    # keeps its MAVLink meaning ("unset", e.g. the takeoff altitude).
    REQUIRED_PARAMS = {
        mavlink.MAV_CMD_COMPONENT_ARM_DISARM: (1,),
        mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: (1, 2),
        mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: (1,),
        mavlink.MAV_CMD_REQUEST_MESSAGE: (1,),
        mavlink.MAV_CMD_DO_SET_MODE: (1, 2),
    }

    def _command(self, msg, command: int, p: list[float], link, now_s, snap) -> list[Outgoing]:
        self.counters["commands"] += 1
        replies: list[Outgoing] = []
        reason = None
        bad = [k for k in self.REQUIRED_PARAMS.get(command, ()) if not (math.isfinite(p[k - 1]) and abs(p[k - 1]) < 2**31)]
        if bad:
            self.counters["commands_bad_params"] += 1
            result, reason = mavlink.MAV_RESULT_DENIED, f"command {command} refused: param{bad[0]} is not a usable number"
        elif command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            force = abs(p[1] - FORCE_MAGIC) < 0.5
            if p[0] >= 0.5:
                result, reason = self.arm(now_s, snap, force)
            else:
                result, reason = self.disarm(now_s, snap, force)
        elif command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            result, reason = self._set_interval(int(p[0]), p[1], link)
        elif command == mavlink.MAV_CMD_GET_MESSAGE_INTERVAL and not 0 <= p[0] <= 0xFFFF:
            result, reason = mavlink.MAV_RESULT_DENIED, f"no message id {p[0]:g}"  # (MESSAGE_INTERVAL's is 16 bits)
        elif command == mavlink.MAV_CMD_GET_MESSAGE_INTERVAL:
            msg_id = int(p[0])
            rate = self.stream_rate_hz(link, msg_id)
            interval = -1 if rate <= 0 else int(round(1e6 / rate))
            replies.append(Outgoing(mavlink.MAVLink_message_interval_message(msg_id, interval), link))
            result = mavlink.MAV_RESULT_ACCEPTED
        elif command in (mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            msg_id = (mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION
                      if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES else int(p[0]))
            out = self.build(msg_id, now_s, snap)
            if out is None:
                result, reason = mavlink.MAV_RESULT_UNSUPPORTED, None
            else:
                result = mavlink.MAV_RESULT_ACCEPTED
                replies.append(Outgoing(out, link))
        elif command == mavlink.MAV_CMD_DO_SET_MODE:
            result, reason = self._do_set_mode(p, now_s, snap)
        elif command == mavlink.MAV_CMD_NAV_TAKEOFF:
            result, reason = self._takeoff(p[6], now_s, snap)
        elif command == mavlink.MAV_CMD_NAV_LAND:
            if not self.armed:
                result, reason = mavlink.MAV_RESULT_DENIED, "land refused: not armed"
            else:
                self.set_mode(CustomMode.LAND, now_s)
                result = mavlink.MAV_RESULT_ACCEPTED
        else:
            self.counters["commands_unsupported"] += 1
            result = mavlink.MAV_RESULT_UNSUPPORTED
        if reason:
            self.announce(reason, mavlink.MAV_SEVERITY_WARNING)
        ack = mavlink.MAVLink_command_ack_message(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        return [Outgoing(ack, link)] + replies

    def _set_interval(self, msg_id: int, interval_us: float, link: str) -> tuple[int, str | None]:
        code = STREAM_CODE.get(msg_id)
        companion = link == "companion"
        if code is None or (companion and code in self.profile.not_streamable):
            return getattr(mavlink, f"MAV_RESULT_{self.profile.unknown_result if companion else 'UNSUPPORTED'}"), None
        name = f"{LINK_PREFIX[link]}_{code}_HZ"
        if interval_us == 0:
            rate = self.spec_by_name[name].default
        elif interval_us < 0:
            rate = 0.0
        else:
            rate = 1e6 / (self.profile.interval_us(interval_us) if companion else interval_us)
        problem = self.set_param(name, rate)
        if problem:
            return mavlink.MAV_RESULT_DENIED, f"interval refused: {problem}"
        return mavlink.MAV_RESULT_ACCEPTED, None

    def _do_set_mode(self, p, now_s, snap) -> tuple[int, str | None]:
        if not int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mavlink.MAV_RESULT_UNSUPPORTED, "only custom modes are supported"
        try:
            mode = CustomMode(int(p[1]))
        except ValueError:
            return mavlink.MAV_RESULT_DENIED, f"unknown custom mode {int(p[1])}"
        if mode == CustomMode.TAKEOFF:
            return self._takeoff(float("nan"), now_s, snap)
        self.set_mode(mode, now_s)
        if mode == CustomMode.EXTERNAL:
            self.last_command_s = now_s
        return mavlink.MAV_RESULT_ACCEPTED, None

    def _takeoff(self, alt_amsl_m: float, now_s, snap) -> tuple[int, str | None]:
        if not self.armed:
            return mavlink.MAV_RESULT_DENIED, "takeoff refused: not armed"
        if not snap.landed:
            return mavlink.MAV_RESULT_DENIED, "takeoff refused: already flying"
        rel = alt_amsl_m - self.home.alt_m if math.isfinite(alt_amsl_m) else self.params["TKO_ALT_M"]
        self.takeoff_alt_m = max(0.5, min(100.0, rel))
        self.set_mode(CustomMode.TAKEOFF, now_s)
        return mavlink.MAV_RESULT_ACCEPTED, None

    # -- outgoing telemetry -----------------------------------------------------------------

    def heartbeat(self):
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if self.failsafe and self.armed:
            status = mavlink.MAV_STATE_CRITICAL
        elif self.armed:
            status = mavlink.MAV_STATE_ACTIVE
        else:
            status = mavlink.MAV_STATE_STANDBY
        return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_TRICOPTER, mavlink.MAV_AUTOPILOT_GENERIC, base,
                                                 int(self.mode), status, 3)

    def landed_state(self, snap: Snapshot) -> int:
        if snap.landed:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.mode == CustomMode.TAKEOFF:
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if self.mode == CustomMode.LAND:
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def build(self, msg_id: int, now_s: float, snap: Snapshot):
        """The message ``msg_id`` describing the vehicle now, or None if this autopilot has none."""
        return telemetry.build(self, msg_id, self.clock_s(now_s), snap)


def _param_name(param_id) -> str:
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", errors="replace")
    return param_id.split("\x00", 1)[0]


def open_circuit_voltage_v(cells, used_mah, capacity_mah):
    """A LiPo pack's open-circuit voltage: 3.3 V per cell empty to 4.2 V full, linear in charge."""
    return cells * (3.3 + 0.9 * np.clip(1.0 - used_mah / capacity_mah, 0.0, 1.0))


def drain_batteries(fcs: list[FlightController], rho: np.ndarray, dt_s: float) -> None:
    """One control period of every vehicle's battery: shaft power k_d w^3 per rotor at 70 %
    efficiency, plus 3 W of avionics. ``rho`` (N, 6) is what the rotors applied (29)."""
    p = [fc.params for fc in fcs]
    kd = np.array([q["KD"] for q in p])
    cells = np.array([q["BAT_CELLS"] for q in p])
    cap = np.array([q["BAT_CAP_MAH"] for q in p])
    used = np.array([fc.battery_used_mah for fc in fcs])
    omega2 = np.hypot(rho[:, 0:3], rho[:, 3:6])
    shaft_w = kd * np.sum(omega2 ** 1.5, axis=1)
    ocv = open_circuit_voltage_v(cells, used, cap)
    current = (shaft_w / 0.7 + 3.0) / np.maximum(ocv, 1.0)
    voltage = ocv - 0.015 * cells * current
    used = used + current * dt_s / 3.6
    for fc, a, v, u in zip(fcs, current.tolist(), voltage.tolist(), used.tolist()):
        fc.battery_current_a, fc.battery_voltage_v, fc.battery_used_mah = a, v, u
