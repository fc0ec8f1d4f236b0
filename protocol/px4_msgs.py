"""PX4's uORB messages as its Zenoh bridge carries them: their fields, their ROS 2 type hashes, their
key expressions and their bytes. Pure: no I/O.

PX4 builds with a Zenoh bridge (``px4_sitl_zenoh``, and boards with ``CONFIG_MODULES_ZENOH``) publish
uORB topics under rmw_zenoh's key expressions::

    <domain>/<namespace>/fmu/out/<topic>/px4_msgs::msg::dds_::<Type>_/RIHS01_<sha256>

(and subscribe to ``.../fmu/in/<topic>/...`` alike), each sample a 4-byte CDR encapsulation header
(``00 01 00 00``: little endian) and the message in XCDR1, in the order of its ``.msg`` file. The
hash is ROS 2's type-description hash (REP 2011) of the message's fields: a subscriber whose hash
differs by a bit hears nothing, so the hashes are computed here from the fields (``FIELDS``, PX4's
``msg/`` definitions at the firmware's version, constants left out as the hash leaves them out) and
checked against the ones the firmware announces in its liveliness tokens (``announced``).

PX4 sends its sample buffer whole (the uORB struct's size + 28 bytes, of which only the CDR is
meaningful): ``decode`` reads the message and ignores what follows, up to ``TRAILING_MAX`` bytes, as
PX4's own bridge does with what it receives.
"""

from __future__ import annotations

import functools

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

PACKAGE = "px4_msgs"
FIELDS: dict[str, str] = {
    "VehicleOdometry": (
        "uint64 timestamp; uint64 timestamp_sample; uint8 pose_frame; float32[3] position;"
        "float32[4] q; uint8 velocity_frame; float32[3] velocity; float32[3] angular_velocity;"
        "float32[3] position_variance; float32[3] orientation_variance; float32[3] velocity_variance;"
        "uint8 reset_counter; int8 quality"),
    "VehicleLocalPosition": (
        "uint64 timestamp; uint64 timestamp_sample; bool xy_valid; bool z_valid; bool v_xy_valid;"
        "bool v_z_valid; float32 x; float32 y; float32 z; float32[2] delta_xy; uint8 xy_reset_counter;"
        "float32 delta_z; uint8 z_reset_counter; float32 vx; float32 vy; float32 vz; float32 z_deriv;"
        "float32[2] delta_vxy; uint8 vxy_reset_counter; float32 delta_vz; uint8 vz_reset_counter;"
        "float32 ax; float32 ay; float32 az; float32 heading; float32 heading_var;"
        "float32 unaided_heading; float32 delta_heading; uint8 heading_reset_counter;"
        "bool heading_good_for_control; float32 tilt_var; bool xy_global; bool z_global;"
        "uint64 ref_timestamp; float64 ref_lat; float64 ref_lon; float32 ref_alt;"
        "bool dist_bottom_valid; float32 dist_bottom; float32 dist_bottom_var;"
        "float32 delta_dist_bottom; uint8 dist_bottom_reset_counter;"
        "uint8 dist_bottom_sensor_bitfield; float32 eph; float32 epv; float32 evh; float32 evv;"
        "bool dead_reckoning; float32 vxy_max; float32 vz_max; float32 hagl_min; float32 hagl_max_z;"
        "float32 hagl_max_xy"),
    "VehicleStatus": (
        "uint64 timestamp; uint64 armed_time; uint64 takeoff_time; uint8 arming_state;"
        "uint8 latest_arming_reason; uint8 latest_disarming_reason; uint64 nav_state_timestamp;"
        "uint8 nav_state_user_intention; uint8 nav_state; uint8 executor_in_charge;"
        "uint8 nav_state_display; uint32 valid_nav_states_mask; uint32 can_set_nav_states_mask;"
        "uint16 failure_detector_status; uint8 hil_state; uint8 vehicle_type; bool failsafe;"
        "bool failsafe_and_user_took_over; uint8 failsafe_defer_state; bool gcs_connection_lost;"
        "uint8 gcs_connection_lost_counter; bool high_latency_data_link_lost; bool is_vtol;"
        "bool is_vtol_tailsitter; bool in_transition_mode; bool in_transition_to_fw;"
        "uint8 system_type; uint8 system_id; uint8 component_id; bool safety_button_available;"
        "bool safety_off; bool power_input_valid; bool usb_connected;"
        "bool open_drone_id_system_present; bool open_drone_id_system_healthy;"
        "bool parachute_system_present; bool parachute_system_healthy;"
        "bool traffic_avoidance_system_present; bool rc_calibration_in_progress;"
        "bool calibration_enabled; bool pre_flight_checks_pass"),
    "VehicleLandDetected": (
        "uint64 timestamp; bool freefall; bool ground_contact; bool maybe_landed; bool landed;"
        "bool in_ground_effect; bool in_descend; bool has_low_throttle; bool vertical_movement;"
        "bool horizontal_movement; bool rotational_movement; bool close_to_ground_or_skipped_check;"
        "bool at_rest"),
    "SensorGps": (
        "uint64 timestamp; uint64 timestamp_sample; uint32 device_id; float64 latitude_deg;"
        "float64 longitude_deg; float64 altitude_msl_m; float64 altitude_ellipsoid_m;"
        "float32 s_variance_m_s; float32 c_variance_rad; uint8 fix_type; float32 eph; float32 epv;"
        "float32 hdop; float32 vdop; int32 noise_per_ms; uint16 automatic_gain_control;"
        "uint8 jamming_state; int32 jamming_indicator; uint8 spoofing_state;"
        "uint8 authentication_state; float32 vel_m_s; float32 vel_n_m_s; float32 vel_e_m_s;"
        "float32 vel_d_m_s; float32 cog_rad; bool vel_ned_valid; int32 timestamp_time_relative;"
        "uint64 time_utc_usec; uint8 satellites_used; uint32 system_error; float32 heading;"
        "float32 heading_offset; float32 heading_accuracy; float32 rtcm_injection_rate;"
        "uint8 selected_rtcm_instance; bool rtcm_crc_failed; uint8 rtcm_msg_used"),
    "VehicleCommandAck": (
        "uint64 timestamp; uint32 command; uint8 result; uint8 result_param1; int32 result_param2;"
        "uint8 target_system; uint16 target_component; bool from_external"),
    "OffboardControlMode": (
        "uint64 timestamp; bool position; bool velocity; bool acceleration; bool attitude;"
        "bool body_rate; bool thrust_and_torque; bool direct_actuator"),
    "ActuatorMotors": (
        "uint64 timestamp; uint64 timestamp_sample; uint16 reversible_flags; float32[12] control"),
    "ActuatorServos": (
        "uint64 timestamp; uint64 timestamp_sample; float32[8] control"),
    "VehicleThrustSetpoint": (
        "uint64 timestamp; uint64 timestamp_sample; float32[3] xyz"),
    "VehicleCommand": (
        "uint64 timestamp; float32 param1; float32 param2; float32 param3; float32 param4;"
        "float64 param5; float64 param6; float32 param7; uint32 command; uint8 target_system;"
        "uint8 target_component; uint8 source_system; uint16 source_component; uint8 confirmation;"
        "bool from_external"),
}
"""Each message's fields, in order, as PX4's ``msg/`` files at main 02e73e3b6f (2026-03) give them."""

TOPICS_OUT = {"vehicle_odometry": "VehicleOdometry", "vehicle_local_position": "VehicleLocalPosition",
              "vehicle_status": "VehicleStatus",
              "vehicle_land_detected": "VehicleLandDetected", "vehicle_gps_position": "SensorGps",
              "vehicle_command_ack": "VehicleCommandAck"}
"""What the companion reads of PX4 (``/fmu/out/<topic>``) and their types."""
TOPICS_IN = {"offboard_control_mode": "OffboardControlMode", "actuator_motors": "ActuatorMotors",
             "actuator_servos": "ActuatorServos", "vehicle_thrust_setpoint": "VehicleThrustSetpoint",
             "vehicle_command": "VehicleCommand"}
"""What the companion publishes to PX4 (``/fmu/in/<topic>``) and their types."""

TRAILING_MAX = 64
"""Bytes after the message a sample may carry (PX4 sends its buffer: the uORB struct's padding and
28 bytes more); a longer sample is not one of PX4's."""

# VehicleStatus
ARMING_STATE_ARMED = 2
NAV_STATE_OFFBOARD = 14
NAV_STATE_NAMES = {0: "MANUAL", 1: "ALTCTL", 2: "POSCTL", 3: "AUTO_MISSION", 4: "AUTO_LOITER", 5: "AUTO_RTL",
                   6: "POSITION_SLOW", 8: "ALTITUDE_CRUISE", 10: "ACRO", 12: "DESCEND", 13: "TERMINATION",
                   14: "OFFBOARD", 15: "STAB", 17: "AUTO_TAKEOFF", 18: "AUTO_LAND", 19: "AUTO_FOLLOW_TARGET",
                   20: "AUTO_PRECLAND", 21: "ORBIT", 22: "AUTO_VTOL_TAKEOFF",
                   **{23 + k: f"EXTERNAL{k + 1}" for k in range(8)}}
"""PX4's navigation states (``VehicleStatus.NAVIGATION_STATE_*``)."""
_MAIN_SUB = {0: (1, 0), 1: (2, 0), 2: (3, 0), 3: (4, 4), 4: (4, 3), 5: (4, 5), 6: (3, 2), 8: (11, 0), 10: (5, 0),
             12: (4, 6), 13: (10, 0), 14: (6, 0), 15: (7, 0), 17: (4, 2), 18: (4, 6), 19: (4, 8), 20: (4, 9),
             21: (3, 1), 22: (4, 10), **{23 + k: (4, 11 + k) for k in range(8)}}
"""Navigation state -> (main mode, sub mode) of PX4's MAVLink custom mode (commander's
``get_px4_custom_mode``)."""
OFFBOARD_MAIN_MODE = 6

# OdometryFrame
POSE_FRAME_NED = 1
VELOCITY_FRAME_NED = 1


def custom_mode(nav_state: int) -> int:
    """The HEARTBEAT custom mode PX4 says over MAVLink in navigation state ``nav_state``: main mode
    in bits 16-23, sub mode in bits 24-31 (0 for a state it has no mode for)."""
    main, sub = _MAIN_SUB.get(nav_state, (0, 0))
    return (main << 16) | (sub << 24)


def nav_state_of(custom: int) -> int | None:
    """The navigation state a custom mode says (the inverse of ``custom_mode``; None if none)."""
    pair = ((custom >> 16) & 0xFF, (custom >> 24) & 0xFF)
    return next((nav for nav, ms in _MAIN_SUB.items() if ms == pair), None)


def mode_name(custom: int) -> str:
    nav = nav_state_of(custom)
    return NAV_STATE_NAMES[nav] if nav is not None else f"custom mode {custom:#x}"


@functools.cache
def _store():
    store = get_typestore(Stores.EMPTY)
    types = {}
    for name, fields in FIELDS.items():
        types.update(get_types_from_msg(fields.replace(";", "\n"), f"{PACKAGE}/msg/{name}"))
    store.register(types)
    return store


def _typename(name: str) -> str:
    if name not in FIELDS:
        raise KeyError(f"{name}: not a message this module knows ({', '.join(FIELDS)})")
    return f"{PACKAGE}/msg/{name}"


@functools.cache
def type_hash(name: str) -> str:
    """``RIHS01_<64 hex digits>``: the ROS 2 type hash of message ``name``."""
    return _store().hash_rihs01(_typename(name))


def dds_type(name: str) -> str:
    return f"{PACKAGE}::msg::dds_::{name}_"


def topic_path(namespace: str, direction: str, topic: str) -> str:
    """``/<namespace>/fmu/<direction>/<topic>`` (no namespace: ``/fmu/...``): the topic's name in
    PX4's bridge tables (``zenoh/pub.csv``, ``zenoh/sub.csv``)."""
    if direction not in ("in", "out"):
        raise ValueError(f"direction must be in or out, got {direction!r}")
    ns = namespace.strip("/")
    return f"/{ns}/fmu/{direction}/{topic}" if ns else f"/fmu/{direction}/{topic}"


def key(domain: int, namespace: str, direction: str, topic: str) -> str:
    """The key expression PX4's bridge uses for ``topic`` (of a type ``TOPICS_OUT``/``TOPICS_IN`` names)."""
    name = {**TOPICS_OUT, **TOPICS_IN}[topic]
    return f"{domain}{topic_path(namespace, direction, topic)}/{dds_type(name)}/{type_hash(name)}"


def announced(token: str) -> tuple[str, str, str] | None:
    """(topic path, type, hash) of an rmw_zenoh liveliness token of a publisher or subscriber
    (``@ros2_lv/<domain>/<zid>/<nid>/<eid>/MP|MS/<enclave>/<ns>/<node>/<%topic>/<type>/<hash>/...``),
    or None for another token."""
    chunks = token.split("/")
    if len(chunks) < 12 or chunks[0] != "@ros2_lv" or chunks[5] not in ("MP", "MS"):
        return None
    return chunks[9].replace("%", "/"), chunks[10], chunks[11]


def encode(name: str, **fields) -> bytes:
    """Message ``name`` with ``fields`` (the others zero, arrays of zeros) as PX4 takes it."""
    store = _store()
    typename = _typename(name)
    values = {}
    for field, (_, spec) in store.fielddefs[typename][1]:
        given = fields.pop(field, None)
        if isinstance(spec[0], tuple):  # an array: ((kind, (base type, 0)), length)
            base, length = spec[0][1][0], spec[1]
            values[field] = np.zeros(length, dtype=_DTYPES[base]) if given is None else \
                np.asarray(given, dtype=_DTYPES[base]).reshape(length)
        else:
            base = spec[0]
            values[field] = _zero(base) if given is None else _python(base, given)
    if fields:
        raise KeyError(f"{name} has no field {', '.join(fields)}")
    return bytes(store.serialize_cdr(store.types[typename](**values), typename, little_endian=True))


def decode(name: str, payload: bytes):
    """The message in a sample of type ``name`` (ValueError: not one; the reason in one line)."""
    store = _store()
    typename = _typename(name)
    if len(payload) < 4 or payload[:2] != b"\x00\x01":
        raise ValueError(f"{name}: not a little-endian CDR sample (header {payload[:4].hex() or 'missing'})")
    msgdef = store.get_msgdef(typename)
    try:
        msg, end = msgdef.deserialize_cdr_le(memoryview(payload)[4:], 0, msgdef.cls, store)
    except Exception as exc:  # noqa: BLE001 (struct.error, IndexError: too short; the library's own)
        raise ValueError(f"{name}: {len(payload)} bytes do not hold one ({type(exc).__name__})") from None
    if len(payload) - 4 - end > TRAILING_MAX:
        raise ValueError(f"{name}: {len(payload) - 4 - end} bytes after the message (at most {TRAILING_MAX})")
    return msg


_DTYPES = {"bool": np.bool_, "int8": np.int8, "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16,
           "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
           "float32": np.float32, "float64": np.float64}


def _zero(base: str):
    return False if base == "bool" else 0.0 if base.startswith("float") else 0


def _python(base: str, value):
    if base == "bool":
        return bool(value)
    if base.startswith("float"):
        return float(value)
    value = int(value)
    info = np.iinfo(_DTYPES[base])
    if not info.min <= value <= info.max:
        raise ValueError(f"{value} does not fit {base}")
    return value
