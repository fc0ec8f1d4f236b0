"""A PX4 flight controller over its own Zenoh bridge, as the flight-controller face's link.

PX4 gives an onboard computer its motors and servos only through offboard mode with direct actuator
setpoints on its uORB bridge (SET_ACTUATOR_CONTROL_TARGET left MAVLink in v1.14). This link carries
what the face says and hears over that bridge, in the face's own terms, so that one face
(``flight_controller.FlightController``) flies every kind of flight controller:

- heard (``/fmu/out/...``), handed to the face as the MAVLink message that carries the same:
  vehicle_odometry as ODOMETRY (local NED, velocity in NED), vehicle_local_position's global
  reference (EKF2's origin) as GPS_GLOBAL_ORIGIN (when it changes, and each second), vehicle_status as HEARTBEAT (PX4's
  MAVLink custom mode, armed flag, MAV_STATE_CRITICAL in a failsafe), vehicle_land_detected as
  EXTENDED_SYS_STATE, vehicle_gps_position as SYSTEM_TIME (its UTC time, once it has one),
  vehicle_command_ack as COMMAND_ACK (the acks of this companion's commands only);
- said: COMMAND_LONG as vehicle_command; SET_ACTUATOR_CONTROL_TARGET (the face's output, group 0:
  three rotor speeds 0..1 and three tilts -1..1) as offboard_control_mode (direct_actuator),
  actuator_servos, actuator_motors and vehicle_thrust_setpoint (the mean of the motor outputs:
  the collective thrust in PX4's linear thrust model, THR_MDL_FAC 0). PX4 bypasses its allocation
  in this mode and uses the thrust setpoint only to know the vehicle flies: its land detector,
  which without one takes a hover for a landing (and a failsafe then idles the motors). Asking for offboard mode first streams
  offboard_control_mode for PRESTREAM_S (PX4 enters offboard only with its signal present) and on
  until the companion's commands flow (HANDOVER_S at most); after that the signal goes with the
  companion's commands, at most SIGNAL_HZ (PX4 wants it at 2 Hz or more): when they stop, PX4's
  offboard-loss failsafe acts.

What the bridge cannot carry (parameters, message intervals, TIMESYNC, a ground station's frames) is
dropped and counted (``not_carried_<type>``). The ground station keeps its own MAVLink link to PX4.

URL: ``px4-zenoh://HOST:PORT/NAMESPACE[?domain=N][&simulator=1]``: the Zenoh router PX4 is a client
of, the namespace its bridge tables put before ``/fmu/`` (empty: none), its ZENOH_DOMAIN_ID (default
0), and whether it flies a simulator (whose clock is the simulator's, not one to hold the
companion's against: ``sitl up`` says so in the links it gives).

Types: every sample's key ends in its type hash. A sample whose hash is not the one computed here
from PX4's message definitions (``protocol.px4_msgs``), and a PX4 subscription announced with
another hash, mean the firmware's messages are not the companion's: said once, in ``fatal``, which
ends the face's set-up with that sentence, rather than a silent link.
"""

from __future__ import annotations

import asyncio
import math
import struct
import time
from collections import Counter
from collections.abc import Callable
from urllib.parse import parse_qs, urlsplit

import zenoh

from triswarm.protocol import px4_msgs as px4
from triswarm.protocol.mavlink import mavlink, new_codec, plausible_unix_us

from .zenoh_session import close_session, open_session, peer_config

SCHEME = "px4-zenoh"
PRESTREAM_S = 0.3
"""Before asking for offboard mode, offboard_control_mode is sent this long [s, wall] at PRESTREAM_HZ."""
PRESTREAM_HZ = 20.0
HANDOVER_S = 3.0
"""After asking for offboard, its signal goes on until the face commands, for at most this long [s]."""
SIGNAL_HZ = 20.0
"""offboard_control_mode goes with the commands at most this often [Hz, wall]: it only says that
offboard control lives (PX4 wants it at 2 Hz or more), and every message costs the companion a put."""
ORIGIN_EVERY_S = 1.0
"""EKF2's origin is handed to the face when it changes, and this often [s, wall] besides."""
NAN_CONTROLS = float("nan")


def is_px4_zenoh(url: str) -> bool:
    return url.startswith(f"{SCHEME}://")


def parse_url(url: str) -> tuple[str, str, int, bool]:
    """(Zenoh endpoint, namespace, domain, simulator) of a ``px4-zenoh://`` URL (ValueError: not one)."""
    parts = urlsplit(url)
    if parts.scheme != SCHEME or not parts.hostname or parts.port is None:
        raise ValueError(f"{url}: a PX4 Zenoh link is {SCHEME}://HOST:PORT/NAMESPACE[?domain=N][&simulator=1]")
    query = parse_qs(parts.query)
    try:
        domain = int(query.get("domain", ["0"])[0])
    except ValueError:
        raise ValueError(f"{url}: domain must be a whole number") from None
    simulator = query.get("simulator", ["0"])[0]
    if simulator not in ("0", "1"):
        raise ValueError(f"{url}: simulator must be 0 or 1")
    host = f"[{parts.hostname}]" if ":" in parts.hostname else parts.hostname
    return f"tcp/{host}:{parts.port}", parts.path.strip("/"), domain, simulator == "1"


class Px4ZenohLink:
    """The face's link to PX4 system ``sysid`` over its Zenoh bridge; speaks as ``compid``."""

    routes = False
    """Nothing is routed through it: the ground station has its own link to PX4."""

    def __init__(self, name: str, url: str, sysid: int, compid: int, after_read: Callable[[], None] | None = None,
                 on_event: Callable[[str], None] = lambda text: None) -> None:
        self.name, self.url = name, url
        self.endpoint, self.namespace, self.domain, self.simulator = parse_url(url)
        self.sysid, self.compid = sysid, compid
        self.codec = new_codec(sysid, compid)  # (packs what is handed to the face)
        self._parser = new_codec(sysid, compid)  # (reads the face's own frames)
        self.counters: Counter[str] = Counter()
        self.after_read = after_read
        self.on_event = on_event
        self.peer = None
        self.fatal: str | None = None
        """Why PX4 cannot be flown over this link (its message types are not the companion's), once known."""
        self.session: zenoh.Session | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._on_receive: Callable | None = None
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._subs: list = []
        self._prestream: asyncio.Task | None = None
        self._signal_at = -math.inf
        self.clock: Callable[[], float] = time.monotonic
        """The wall clock the offboard signal's and the origin's rates are kept on [s]."""
        self._origin: tuple | None = None
        self._origin_said = 0.0
        self._asked_mode: int | None = None
        """The navigation state the face's newest DO_SET_MODE asked for."""
        self._odometry_at: tuple[float, int] | None = None
        """(time received [Unix s], PX4's stamp [us]) of the newest odometry."""
        self._mode_ack = None
        """(its accepted COMMAND_ACK, the navigation state) until a vehicle_status shows that state."""

    @property
    def up(self) -> bool:
        return self.session is not None

    # -- opening and closing ----------------------------------------------------------------------

    def open(self, loop: asyncio.AbstractEventLoop, on_receive: Callable) -> None:
        self._loop, self._on_receive = loop, on_receive
        # (a peer, not a client: a router not up yet is tried again and waited for, where a client fails)
        self.session = open_session(peer_config([], [self.endpoint]))
        for topic, name in px4.TOPICS_OUT.items():
            prefix = f"{self.domain}{px4.topic_path(self.namespace, 'out', topic)}/{px4.dds_type(name)}"
            self._subs.append(self.session.declare_subscriber(
                f"{prefix}/*", lambda sample, t=topic, n=name: self._heard(t, n, sample)))
        for topic in px4.TOPICS_IN:
            self._pubs[topic] = self.session.declare_publisher(
                px4.key(self.domain, self.namespace, "in", topic), congestion_control=zenoh.CongestionControl.DROP)
        self._subs.append(self.session.liveliness().declare_subscriber(
            f"@ros2_lv/{self.domain}/**", self._announced, history=True))

    def close(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        if self._prestream is not None:
            self._prestream.cancel()
        session, self.session = self.session, None
        if session is not None:
            for sub in self._subs:
                sub.undeclare()
            self._subs.clear()
            self._pubs.clear()
            close_session(session)

    # -- what PX4 says ----------------------------------------------------------------------------

    def _heard(self, topic: str, name: str, sample: zenoh.Sample) -> None:
        """A sample, on Zenoh's thread: to the loop."""
        t_rx = time.time()
        key, payload = str(sample.key_expr), sample.payload.to_bytes()
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._take, topic, name, key, payload, t_rx)

    def _announced(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        told = px4.announced(str(sample.key_expr))
        if told is None:
            return
        path, dds, hash_ = told
        for direction, topics in (("in", px4.TOPICS_IN), ("out", px4.TOPICS_OUT)):
            for topic, name in topics.items():
                if path == px4.topic_path(self.namespace, direction, topic) and hash_ != px4.type_hash(name):
                    loop = self._loop
                    if loop is not None and not loop.is_closed():
                        loop.call_soon_threadsafe(self._mismatch, path, dds, hash_, name)

    def _mismatch(self, path: str, dds: str, hash_: str, name: str) -> None:
        if self.fatal is None:
            self.fatal = (f"PX4 announces {path} as {dds} {hash_}, the companion speaks {name} "
                          f"{px4.type_hash(name)}: the firmware's message definitions are not the companion's "
                          f"(another PX4 version); the link would be silent")
            self.on_event(self.fatal)

    def _take(self, topic: str, name: str, key: str, payload: bytes, t_rx: float) -> None:
        if self.session is None:
            return
        hash_ = key.rsplit("/", 1)[-1]
        if hash_ != px4.type_hash(name):
            self.counters[f"drop_type_{topic}"] += 1
            self._mismatch(key.rsplit("/", 2)[0], px4.dds_type(name), hash_, name)
            return
        try:
            msg = px4.decode(name, payload)
        except ValueError:
            self.counters[f"drop_malformed_{topic}"] += 1
            return
        if topic == "vehicle_odometry":
            self._note_gap(t_rx, msg.timestamp_sample)
        try:
            out = getattr(self, f"_{topic}")(msg)
            out = [] if out is None else out if isinstance(out, list) else [out]
            for m in out:
                m.pack(self.codec)  # (a frame of its own: what the face reads of a message is all there)
        except (struct.error, ValueError, OverflowError):  # (values no MAVLink field holds: NaN counts, huge ones)
            self.counters[f"drop_unsayable_{topic}"] += 1
            return
        if not out:
            return
        self.counters["rx"] += len(out)
        try:
            self._on_receive(self, out, t_rx)
        finally:
            if self.after_read is not None:
                self.after_read()

    def _note_gap(self, t_rx: float, stamp_us: int) -> None:
        """The longest wait between two odometries [ms, wall, as Zenoh handed them over], with how far
        PX4's stamps moved across it [ms] and when it ended [Unix ms]: a silent PX4 (the stamps
        moved as far) or a held link (they moved one period). In the link's counters."""
        last, self._odometry_at = self._odometry_at, (t_rx, stamp_us)
        if last is not None and (gap_ms := round(1e3 * (t_rx - last[0]))) > self.counters["odometry_gap_max_ms"]:
            self.counters["odometry_gap_max_ms"] = gap_ms
            self.counters["odometry_gap_stamps_ms"] = round((stamp_us - last[1]) / 1e3)
            self.counters["odometry_gap_end_unix_ms"] = round(1e3 * t_rx)

    def _vehicle_odometry(self, m):
        frame = mavlink.MAV_FRAME_LOCAL_NED if m.pose_frame == px4.POSE_FRAME_NED else mavlink.MAV_FRAME_LOCAL_FRD
        child = mavlink.MAV_FRAME_LOCAL_NED if m.velocity_frame == px4.VELOCITY_FRAME_NED else mavlink.MAV_FRAME_BODY_FRD
        nan21 = [float("nan")] * 21
        return mavlink.MAVLink_odometry_message(
            m.timestamp_sample, frame, child, *(float(v) for v in m.position), [float(v) for v in m.q],
            *(float(v) for v in m.velocity), *(float(v) for v in m.angular_velocity), nan21, nan21,
            m.reset_counter, mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT, max(0, int(m.quality)))

    def _vehicle_local_position(self, m):
        """Its global reference as GPS_GLOBAL_ORIGIN, when it is one, has changed or was last said
        ORIGIN_EVERY_S ago (the odometry carries the position itself)."""
        if not (m.xy_global and m.z_global and abs(m.ref_lat) <= 90.0 and abs(m.ref_lon) <= 180.0
                and math.isfinite(m.ref_alt)):
            return None
        origin = (round(m.ref_lat * 1e7), round(m.ref_lon * 1e7), round(m.ref_alt * 1000), m.ref_timestamp)
        now = self.clock()
        if origin == self._origin and now - self._origin_said < ORIGIN_EVERY_S:
            return None
        self._origin, self._origin_said = origin, now
        return mavlink.MAVLink_gps_global_origin_message(*origin[:3], origin[3])

    def _vehicle_status(self, m):
        """HEARTBEAT, and after it the acceptance of a mode change it shows (held back until then)."""
        heartbeat = self._heartbeat(m)
        held, self._mode_ack = self._mode_ack, None
        if held is None:
            return heartbeat
        if m.nav_state == held[1]:
            return [heartbeat, held[0]]
        self._mode_ack = held  # (a status from before the change: the answer waits for one after it)
        return heartbeat

    def _heartbeat(self, m):
        armed = m.arming_state == px4.ARMING_STATE_ARMED
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
        state = mavlink.MAV_STATE_CRITICAL if m.failsafe else \
            mavlink.MAV_STATE_ACTIVE if armed else mavlink.MAV_STATE_STANDBY
        return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_TRICOPTER, mavlink.MAV_AUTOPILOT_PX4, base,
                                                 px4.custom_mode(m.nav_state), state, 3)

    def _vehicle_land_detected(self, m):
        landed = mavlink.MAV_LANDED_STATE_ON_GROUND if m.landed else mavlink.MAV_LANDED_STATE_IN_AIR
        return mavlink.MAVLink_extended_sys_state_message(mavlink.MAV_VTOL_STATE_UNDEFINED, landed)

    def _vehicle_gps_position(self, m):
        if not plausible_unix_us(m.time_utc_usec):  # (no fix time yet)
            return None
        return mavlink.MAVLink_system_time_message(m.time_utc_usec, ((m.timestamp_sample or m.timestamp) // 1000) & 0xFFFFFFFF)

    def _vehicle_command_ack(self, m):
        """COMMAND_ACK of this companion's commands; a mode change accepted is said once a
        vehicle_status shows it: PX4 publishes the two apart, and a status from before the change
        arriving after its answer would tell the face the mode it has just left."""
        if m.target_system != self.sysid or m.target_component != self.compid:
            return None  # (another's command: the ground station's, over MAVLink)
        ack = mavlink.MAVLink_command_ack_message(m.command & 0xFFFF, m.result)
        asked = self._asked_mode
        if m.command == mavlink.MAV_CMD_DO_SET_MODE and m.result == mavlink.MAV_RESULT_ACCEPTED and asked is not None:
            self._mode_ack = (ack, asked)
            return None
        return ack

    # -- what the face says -----------------------------------------------------------------------

    def send(self, msg) -> None:
        if self.session is None:
            return
        if msg.get_type() != "COMMAND_LONG":
            self.counters[f"not_carried_{msg.get_type()}"] += 1
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        if msg.command == mavlink.MAV_CMD_DO_SET_MODE:
            self._asked_mode = px4.nav_state_of((int(msg.param2) << 16) | (int(msg.param3) << 24))
        if msg.command == mavlink.MAV_CMD_DO_SET_MODE and int(msg.param2) == px4.OFFBOARD_MAIN_MODE:
            self._offboard_then(lambda: self._command(msg.command, params))
        else:
            self._command(msg.command, params)

    def _command(self, command: int, params) -> None:
        self._put("vehicle_command", px4.encode(
            "VehicleCommand", param1=params[0], param2=params[1], param3=params[2], param4=params[3],
            param5=params[4], param6=params[5], param7=params[6], command=command, target_system=self.sysid,
            target_component=1, source_system=self.sysid, source_component=self.compid, from_external=True))

    def _offboard_then(self, then: Callable[[], None]) -> None:
        """offboard_control_mode at PRESTREAM_HZ: PRESTREAM_S, then ``then`` (the mode asked for), and on
        until the face's commands carry it or HANDOVER_S have passed (an answer to the mode, or the
        first command, that is late must not lose offboard on the way in)."""
        async def prestream():
            period = 1.0 / PRESTREAM_HZ
            for _ in range(max(1, round(PRESTREAM_S * PRESTREAM_HZ))):
                self._offboard_signal()
                await asyncio.sleep(period)
            then()
            commands = self.counters["tx_commands"]
            for _ in range(round(HANDOVER_S * PRESTREAM_HZ)):
                if self.counters["tx_commands"] > commands:
                    return
                self._offboard_signal()
                await asyncio.sleep(period)
        if self._prestream is not None and not self._prestream.done():
            self._prestream.cancel()
        self._prestream = asyncio.ensure_future(prestream())

    def _offboard_signal(self) -> None:
        self._put("offboard_control_mode", _DIRECT_ACTUATOR)

    def write(self, frame: bytes) -> None:
        """The face's actuator frames; anything else is not carried."""
        if self.session is None:
            return
        msgs = self._parser.parse_buffer(frame) or []
        for msg in msgs:
            if msg.get_type() != "SET_ACTUATOR_CONTROL_TARGET":
                self.counters[f"not_carried_{msg.get_type()}"] += 1
                continue
            controls = [float(c) for c in msg.controls]
            if all(c != c for c in controls[:6]):  # (an answer that commands nothing)
                continue
            if (now := self.clock()) - self._signal_at >= 1.0 / SIGNAL_HZ:
                self._signal_at = now
                self._offboard_signal()
            # (servos first: PX4 sends its outputs on when the motors come). timestamp_sample: the
            # odometry sample the command answers, on PX4's clock, as PX4's own controllers stamp
            # theirs: its log then holds each command's age (tests/bench/bench_px4.py).
            sample_us = msg.time_usec
            self._put("actuator_servos", px4.encode("ActuatorServos", timestamp_sample=sample_us,
                                                    control=controls[3:6] + [NAN_CONTROLS] * 5))
            self._put("actuator_motors", px4.encode("ActuatorMotors", timestamp_sample=sample_us,
                                                    control=controls[0:3] + [NAN_CONTROLS] * 9))
            collective = sum(min(max(c, 0.0), 1.0) for c in controls[0:3]) / 3.0
            self._put("vehicle_thrust_setpoint", px4.encode("VehicleThrustSetpoint", timestamp_sample=sample_us,
                                                            xyz=[0.0, 0.0, -collective]))
            self.counters["tx_commands"] += 1

    def _put(self, topic: str, payload: bytes) -> None:
        try:
            self._pubs[topic].put(payload)
        except zenoh.ZError:
            self.counters[f"tx_errors_{topic}"] += 1


_DIRECT_ACTUATOR = px4.encode("OffboardControlMode", direct_actuator=True)
