"""The ground-station face of an agent: its link, MAVLink routing between that link and the flight
controller's, the companion's parameters and commands (component 191), the mission server, status
texts, heartbeats and the 1 Hz health values.

With a signing key (``--signing-key``), the ground-station link signs every frame the companion
sends and checks every frame it receives (MAVLink 2 signing, ``protocol.mavlink.setup_signing``).
Of the unsigned ones only HEARTBEAT, PARAM_REQUEST_READ and PARAM_REQUEST_LIST pass: they change
nothing, and let a ground station without the key (a monitor) be heard and read parameters. Every
other unsigned frame, and every frame with a wrong signature or a replayed timestamp, is dropped
before routing (so it reaches neither this component nor the flight controller), counted in the
link's counters by reason, and reported to the ground station once a second. Frames forwarded
from the flight controller, whose link is not signed, reach the ground station as they came. With
a state folder, each ground-station stream's last timestamp is kept there (``signing.json``), so a
frame taken before a restart is still a replay after it.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass

from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink, setup_signing

from .links import MavLink, Router
from .shedding import Episodes, Shedder, TokenBucket

HIGH_RATE = frozenset({mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                       mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mavlink.MAVLINK_MSG_ID_ODOMETRY,
                       mavlink.MAVLINK_MSG_ID_HIGHRES_IMU})
"""Telemetry forwarded to the ground station at GCS_TLM_HZ at most."""
UNSIGNED_FROM_GCS = frozenset({mavlink.MAVLINK_MSG_ID_HEARTBEAT, mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_READ,
                               mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_LIST})
"""With a signing key: what the ground-station link takes unsigned (see the module's text)."""
FROM_GCS_TO_FC = frozenset({mavlink.MAVLINK_MSG_ID_HEARTBEAT, mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_READ,
                            mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_LIST, mavlink.MAVLINK_MSG_ID_PARAM_SET,
                            mavlink.MAVLINK_MSG_ID_PARAM_EXT_REQUEST_READ,
                            mavlink.MAVLINK_MSG_ID_PARAM_EXT_REQUEST_LIST, mavlink.MAVLINK_MSG_ID_PARAM_EXT_SET,
                            mavlink.MAVLINK_MSG_ID_COMMAND_LONG, mavlink.MAVLINK_MSG_ID_COMMAND_INT,
                            mavlink.MAVLINK_MSG_ID_COMMAND_ACK, mavlink.MAVLINK_MSG_ID_MISSION_REQUEST_LIST,
                            mavlink.MAVLINK_MSG_ID_MISSION_COUNT, mavlink.MAVLINK_MSG_ID_MISSION_ITEM,
                            mavlink.MAVLINK_MSG_ID_MISSION_ITEM_INT, mavlink.MAVLINK_MSG_ID_MISSION_REQUEST,
                            mavlink.MAVLINK_MSG_ID_MISSION_REQUEST_INT, mavlink.MAVLINK_MSG_ID_MISSION_ACK,
                            mavlink.MAVLINK_MSG_ID_MISSION_CLEAR_ALL, mavlink.MAVLINK_MSG_ID_MISSION_SET_CURRENT,
                            mavlink.MAVLINK_MSG_ID_MISSION_REQUEST_PARTIAL_LIST,
                            mavlink.MAVLINK_MSG_ID_MISSION_WRITE_PARTIAL_LIST,
                            mavlink.MAVLINK_MSG_ID_FILE_TRANSFER_PROTOCOL, mavlink.MAVLINK_MSG_ID_TIMESYNC,
                            mavlink.MAVLINK_MSG_ID_PING, mavlink.MAVLINK_MSG_ID_REQUEST_DATA_STREAM,
                            mavlink.MAVLINK_MSG_ID_SET_MODE, mavlink.MAVLINK_MSG_ID_LOG_REQUEST_LIST,
                            mavlink.MAVLINK_MSG_ID_LOG_REQUEST_DATA, mavlink.MAVLINK_MSG_ID_LOG_ERASE,
                            mavlink.MAVLINK_MSG_ID_LOG_REQUEST_END, mavlink.MAVLINK_MSG_ID_GPS_RTCM_DATA,
                            mavlink.MAVLINK_MSG_ID_GPS_INJECT_DATA})
"""What the companion forwards from a ground station to its flight controller: what MAVLink's tools
(QGroundControl, MAVProxy, MAVSDK) need to see and configure it (heartbeats, parameters, commands,
missions, MAVLink FTP, time sync, stream requests, logs, GPS corrections). Kept back: anything that
flies the vehicle (setpoints, actuator targets, manual control, RC overrides: the companion flies
it), sets its clock (SYSTEM_TIME: a plan starts on the flight controller's own), its signing
(SETUP_SIGNING) or opens its shell (SERIAL_CONTROL), and everything else (``docs/companion.md``)."""
GCS_LINK_ID = 1  # the ground-station link's id in the signatures it sends
HEALTH_VALUES = (("LOOP_HZ", "loop_rate_hz"), ("JIT_P99MS", "jitter_p99_ms"), ("LAT_P99MS", "latency_p99_ms"),
                 ("MISSES", "deadline_misses"), ("TLM_AGEMS", "telemetry_age_ms"), ("FORM_ERRM", "formation_error_m"),
                 ("FC_PPM", "fc_clock_drift_ppm"), ("FC_RTT_US", "fc_clock_rtt_min_us"),
                 ("FC_RES_US", "fc_clock_residual_us"))
"""NAMED_VALUE_FLOAT names of the health report's values, sent once a second."""
GCS_FRAMES_PER_S, GCS_FRAMES_BURST = 100.0, 200.0
"""Frames of one sender on the ground-station link handled or forwarded, by default
(``--gcs-frames-per-s``, with a burst of twice that: a ground station sends a few a second, a
joystick's MANUAL_CONTROL 50); beyond: dropped, ``shed_frames``."""
FC_FORWARD_PER_S, FC_FORWARD_BURST = 200.0, 400.0
"""Frames from the ground-station link forwarded to the flight controller, all senders together
(its link carries the actuator commands); beyond: not forwarded, ``shed_fc_forward``."""
CHECKED_CMDS_PER_S, CHECKED_CMDS_BURST = 2.0, 5.0
"""Leader commands and plan starts of one sender checked (a leader move is checked against the
airframe's limits along its way: up to a few milliseconds); beyond: MAV_RESULT_TEMPORARILY_REJECTED,
``shed_commands``."""
TEXTS_PER_S, TEXTS_BURST = 5.0, 10.0
"""Refusals of commands and parameters said in STATUSTEXT; beyond: in their answer only, ``shed_texts``."""
SHED_WHAT = {"shed_frames": "frames beyond --gcs-frames-per-s a sender",
             "shed_fc_forward": f"frames to the flight controller beyond {FC_FORWARD_PER_S:g}/s",
             "shed_commands": f"leader commands and plan starts beyond {CHECKED_CMDS_PER_S:g}/s a sender",
             "shed_texts": f"refusals said beyond {TEXTS_PER_S:g}/s"}


CHECKED = frozenset({mavlink.MAV_CMD_TRISWARM_LEADER_GOTO, mavlink.MAV_CMD_TRISWARM_LEADER_HOLD,
                     mavlink.MAV_CMD_TRISWARM_PLAN_START})
"""Commands checked against the plan in force (CHECKED_CMDS_PER_S)."""


def _address(sender) -> str:
    return "the link" if sender is None else ":".join(str(part) for part in sender)


@dataclass
class ParamSpec:
    default: float
    lo: float
    hi: float
    read_only: bool = False


class Params:
    """The companion's parameters (PARAM_* protocol of component 191), each with its range."""

    def __init__(self, rate_hz: float) -> None:
        self.specs = {
            "CTRL_RATE_HZ": ParamSpec(rate_hz, 1.0, 2000.0, read_only=True),  # control (telemetry) rate
            "NB_TIMEOUT_S": ParamSpec(0.2, 0.01, 10.0),  # a neighbour's estimate older than this: absent [s]
            "NB_WAIT_MS": ParamSpec(1.0, 0.0, 4.0),      # longest wait for the neighbours' estimates [ms]
            "REJOIN_S": ParamSpec(1.0, 0.2, 60.0),       # shortest way back into the formation [s]
            "REJOIN_ACCEL": ParamSpec(4.0, 0.5, 20.0),   # peak acceleration on the way back [m/s^2]
            "LAND_SPEED": ParamSpec(0.5, 0.1, 2.0),      # mean descent speed of the companion's landing [m/s]
            "GCS_TLM_HZ": ParamSpec(20.0, 0.0, 1000.0),  # high-rate telemetry forwarded to the GCS [Hz]
            "PLAN_T_S": ParamSpec(math.nan, -math.inf, math.inf, read_only=True),  # plan time when read [s]
        }
        self.values = {k: p.default for k, p in self.specs.items()}

    def declare(self, name: str, value: float, read_only: bool = True) -> None:
        self.specs[name] = ParamSpec(value, -math.inf, math.inf, read_only)
        self.values[name] = value

    def set(self, name: str, value: float) -> str | None:
        """Set ``name``; returns why it was refused, or None."""
        spec = self.specs.get(name)
        if spec is None:
            return f"unknown parameter {name}"
        if spec.read_only:
            return f"{name} is read-only"
        if not (math.isfinite(value) and spec.lo <= value <= spec.hi):
            return f"{name} must be within [{spec.lo:g}, {spec.hi:g}]"
        self.values[name] = value
        return None


class GroundStation:
    """Agent ``agent_id``'s face to the ground station on link ``url``. ``fc``: its flight controller
    (``FlightController``: frames are routed to and from its link, its own are handed to it);
    ``params``: the companion's parameters; ``plans`` and ``plan_server``: its plans and the mission
    protocol; ``ask_to_land()``: its flight's answer to a land command (``Flight.ask_to_land``);
    ``heartbeat()``: the companion's HEARTBEAT now; ``store``: where the signing streams are kept;
    ``say(text, severity)`` and ``log``: its voice; ``frames_per_s``: each sender's share of the
    link (0: no limit); ``on_link_event``: its link's (``links.MavLink``)."""

    def __init__(self, agent_id: int, url: str, signing_key: bytes | None, *, fc, params: Params, plans, plan_server,
                 ask_to_land, heartbeat, store, say, log, frames_per_s: float,
                 on_link_event=lambda text: None) -> None:
        self.id, self.fc, self.params, self.plans, self.plan_server = agent_id, fc, params, plans, plan_server
        self.ask_to_land, self.heartbeat, self.store, self.say, self.log = ask_to_land, heartbeat, store, say, log
        self.link = MavLink("gcs", url, agent_id, COMP_ONBOARD, on_event=on_link_event)
        self.signing_key = signing_key
        if signing_key is not None:
            setup_signing(self.link.codec, signing_key, GCS_LINK_ID, UNSIGNED_FROM_GCS.__contains__, self.link.counters,
                          clock=time.time)
        self.router = Router(agent_id, COMP_ONBOARD)
        self._statustext_id = 0
        self._forwarded_at: dict[int, float] = {}
        self._refusals_told: Counter[str] = Counter()
        self._signing_kept: dict[str, int] = {}
        rate = frames_per_s or math.inf  # (0: no limit, as for a fuzzer or a trusted link)
        self.shed = Shedder(rate, GCS_FRAMES_BURST / GCS_FRAMES_PER_S * rate)
        self._fc_forward = TokenBucket(FC_FORWARD_PER_S, FC_FORWARD_BURST)
        self._checked_cmds = Shedder(CHECKED_CMDS_PER_S, CHECKED_CMDS_BURST)
        self._texts = TokenBucket(TEXTS_PER_S, TEXTS_BURST)
        self._senders_told, self._sheds_told = Episodes(), Episodes()

    # -- routing ----------------------------------------------------------------------------------

    def from_fc(self, msgs: list, t_rx: float) -> None:
        """Frames from the flight-controller link: this agent's flight controller's to its face, and each
        to where it is going."""
        fc, fc_link = self.fc, self.fc.link
        links = (fc_link, self.link)
        for msg in msgs:
            if not fc_link.routes:  # (PX4's Zenoh bridge: its face's alone)
                fc.take(msg, t_rx)
                continue
            self.router.learn(fc_link, msg)
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            if src == (self.id, mavlink.MAV_COMP_ID_AUTOPILOT1):
                fc.take(msg, t_rx)
            for dest in self.router.destinations(fc_link, msg, links):
                if dest is self.link and not self._rate_ok(msg):
                    continue
                dest.write(msg.get_msgbuf())
            if src[0] != self.id and self.router.for_me(msg):
                self._for_me(fc_link, msg)

    def from_gcs(self, link: MavLink, msgs: list, t_rx: float) -> None:
        """Frames from the ground-station link: each sender's within its bucket, the rest shed."""
        fc_link = self.fc.link
        links = (fc_link, self.link) if fc_link.routes else (self.link,)
        now = time.monotonic()
        for msg in msgs:
            if not self.shed.take(link.peer, now):
                link.counters["shed_frames"] += 1
                continue
            if msg.get_srcSystem() == self.id:  # (a ground station speaking as this vehicle: the
                link.counters["refused_own_system"] += 1  # router would send its flight controller's traffic there)
                continue
            self.router.learn(link, msg)
            for dest in self.router.destinations(link, msg, links):
                if dest is fc_link:
                    if msg.get_msgId() not in FROM_GCS_TO_FC:
                        link.counters["kept_from_fc"] += 1
                        continue
                    if not self._fc_forward.take(now):
                        link.counters["shed_fc_forward"] += 1
                        continue
                dest.write(msg.get_msgbuf())
            if self.router.for_me(msg):
                self._for_me(link, msg)

    def _rate_ok(self, msg) -> bool:
        """High-rate telemetry reaches the ground station at GCS_TLM_HZ at most."""
        mid = msg.get_msgId()
        if mid not in HIGH_RATE:
            return True
        rate = self.params.values["GCS_TLM_HZ"]
        if rate <= 0:
            return False
        now = time.monotonic()
        if now - self._forwarded_at.get(mid, -math.inf) < 1.0 / rate:
            return False
        self._forwarded_at[mid] = now
        return True

    # -- component 191 ----------------------------------------------------------------------------

    def _for_me(self, link: MavLink, msg) -> None:
        if self.plan_server.handle(link, msg, time.monotonic()):
            return
        t = msg.get_type()
        params = self.params
        if t == "PARAM_REQUEST_LIST":
            for k in range(len(params.values)):
                link.send(self._param_value(k))
        elif t == "PARAM_REQUEST_READ":
            names = list(params.values)
            name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="replace")
            k = msg.param_index if msg.param_index >= 0 else (names.index(name) if name in names else -1)
            if 0 <= k < len(names):
                link.send(self._param_value(k))
        elif t == "PARAM_SET":
            name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="replace")
            problem = params.set(name, float(msg.param_value))
            if problem:
                self._refusal(problem, mavlink.MAV_SEVERITY_INFO)
            if name in params.values:
                link.send(self._param_value(list(params.values).index(name)))
        elif t in ("COMMAND_LONG", "COMMAND_INT"):
            self._command(link, msg)

    def _param_value(self, k: int):
        values = self.params.values
        name = list(values)[k]
        if name == "PLAN_T_S":  # the plan time now, for commands timed in it (NaN: no plan in force)
            t_plan = self.plans.plan_time_now()
            values[name] = math.nan if t_plan is None else t_plan
        return mavlink.MAVLink_param_value_message(name.encode(), float(values[name]), mavlink.MAV_PARAM_TYPE_REAL32,
                                                   len(values), k)

    def _command(self, link: MavLink, msg) -> None:
        reason = ""
        if msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE and msg.param1 == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            result = mavlink.MAV_RESULT_ACCEPTED
            link.send(self.heartbeat())
        elif msg.command in CHECKED and not self._checked_cmds.take(link.peer, time.monotonic()):
            result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # (a flood of them: not checked, not said)
            self.link.counters["shed_commands"] += 1
        elif msg.command == mavlink.MAV_CMD_TRISWARM_PLAN_START:
            if msg.get_type() != "COMMAND_INT":
                result, reason = mavlink.MAV_RESULT_DENIED, "plan start needs COMMAND_INT (its time is in x and y)"
            elif not all(0 <= half <= 0xFFFF and half == int(half) for half in (msg.param1, msg.param2)):  # (NaN fails)
                result, reason = mavlink.MAV_RESULT_DENIED, "plan start refused: param1 and param2 must be the plan id's halves"
            else:
                result, reason = self.plans.start(int(msg.param1) << 16 | int(msg.param2), msg.x + msg.y / 1000.0)
        elif msg.command in (mavlink.MAV_CMD_TRISWARM_LEADER_GOTO, mavlink.MAV_CMD_TRISWARM_LEADER_HOLD):
            result, reason = self.plans.leader_command(msg)
        elif msg.command == mavlink.MAV_CMD_NAV_LAND:  # (to the companion: it lands the vehicle itself)
            result, reason = self.ask_to_land()
        else:
            result = mavlink.MAV_RESULT_UNSUPPORTED
        if reason:
            self._refusal(reason, mavlink.MAV_SEVERITY_INFO if result == mavlink.MAV_RESULT_ACCEPTED else mavlink.MAV_SEVERITY_WARNING)
        link.send(mavlink.MAVLink_command_ack_message(msg.command, result, 0, 0, msg.get_srcSystem(),
                                                      msg.get_srcComponent()))

    # -- what it tells the ground station -------------------------------------------------------------

    def _refusal(self, text: str, severity: int) -> None:
        """What a command or parameter's answer says, said too (TEXTS_PER_S at most)."""
        if self._texts.take(time.monotonic()):
            self.say(text, severity)
        else:
            self.link.counters["shed_texts"] += 1

    def shed_counts(self) -> dict[str, int]:
        """What was shed so far, by counter (the health report's ``gcs_shed``)."""
        return {k: self.link.counters[k] for k in SHED_WHAT}

    def tell_floods(self) -> None:
        """Once a second: each flood said when it begins and when it ends, by sender and by counter."""
        now = time.monotonic()
        began, ended = self._senders_told.look(self.shed.dropped, now)
        for sender, _ in began:
            self.say(f"ground station at {_address(sender)} floods: frames beyond {self.shed.rate_per_s:g}/s dropped "
                       f"and counted (gcs_shed in the health report) until it stops", mavlink.MAV_SEVERITY_WARNING)
        for sender, n, lasted in ended:
            self.say(f"ground station at {_address(sender)}: flood over, {n} frames dropped in {lasted:.0f} s")
        counts = self.shed_counts()
        began, ended = self._sheds_told.look({k: n for k, n in counts.items() if k != "shed_frames"}, now)
        for key, _ in began:
            self.say(f"shedding {SHED_WHAT[key]} (gcs_shed {key})", mavlink.MAV_SEVERITY_WARNING)
        for key, n, lasted in ended:
            self.say(f"shedding over: {n} {SHED_WHAT[key]} in {lasted:.0f} s")

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        """A text longer than 50 bytes goes in chunks (MAVLink 2 id, chunk_seq)."""
        data = text.encode()
        if len(data) <= 50:
            self.link.send(mavlink.MAVLink_statustext_message(severity, data))
            return
        self._statustext_id = self._statustext_id % 0xFFFF + 1
        for k in range(0, len(data) + 1, 50):  # (a text of a multiple of 50 ends with an empty chunk)
            self.link.send(mavlink.MAVLink_statustext_message(severity, data[k:k + 50], self._statustext_id, k // 50))

    def health_values(self, report: dict) -> None:
        """The health report's values as NAMED_VALUE_FLOAT (a ground station plots them)."""
        boot_ms = int(time.monotonic() * 1000) & 0xFFFFFFFF
        for name, key in HEALTH_VALUES:
            value = report.get(key)
            if value is not None:
                self.link.send(mavlink.MAVLink_named_value_float_message(boot_ms, name.encode(), float(value)))
        self.link.send(mavlink.MAVLink_named_value_float_message(boot_ms, b"GCS_SHED", float(sum(report["gcs_shed"].values()))))
        for j, age in report["neighbour_age_ms"].items():
            if age is not None:
                self.link.send(mavlink.MAVLink_named_value_float_message(boot_ms, f"NB{j}_AGEMS".encode(), age))

    def tell_refusals(self) -> None:
        """The frames from the ground station refused since the last time, by reason (a ground
        station without the key, or with another, learns why it gets no answer)."""
        refused = Counter({k: n for k, n in self.link.counters.items() if k.startswith("refused_")})
        new = refused - self._refusals_told
        if new:
            self._refusals_told = refused
            counts = ", ".join(f"{n} {k.removeprefix('refused_').replace('_', ' ')}" for k, n in sorted(new.items()))
            self.say(f"refused frames from the ground station: {counts}", mavlink.MAV_SEVERITY_WARNING)

    # -- signing streams across restarts --------------------------------------------------------------

    def restore_signing_streams(self) -> None:
        """The ground station's signing streams as they were before a restart: a frame captured
        before it stays a replay after it (a new stream alone would take any frame up to a minute
        old, as the specification allows)."""
        if self.signing_key is None:
            return
        store = self.store
        saved = store.load_signing_streams()
        if store.problem:
            self.log.warning(store.problem)
            store.problem = None
        taken = self.link.codec.signing.restore(saved)
        if taken:
            self.log.info(f"signing: {taken} ground-station stream(s) taken up where they were")
        self._signing_kept = self.link.codec.signing.streams()

    def keep_signing_streams(self) -> None:
        """Save the signing streams if they moved (once a second at most)."""
        if self.signing_key is None:
            return
        streams = self.link.codec.signing.streams()
        if streams != self._signing_kept and self.store.save_signing_streams(streams):  # (a failure: said once)
            self._signing_kept = streams
