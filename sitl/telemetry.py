"""What the simulated flight controllers send: telemetry in MAVLink's frames (NED earth, FRD body),
the streams and their default rates, and the sensor snapshot it is built from.

Each builder converts the paper-frame snapshot to MAVLink's frames here and only here. The
messages a companion link streams at the control rate (ATTITUDE, LOCAL_POSITION_NED) are also
built for every vehicle of a physics step at once (``batch_args``): one conversion of the swarm's
arrays instead of one per vehicle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from triswarm.protocol import frames
from triswarm.protocol.mavlink import mavlink
from triswarm.protocol.model import actuator_inverse

from .physics import rotation_from_quaternion

FIRMWARE_VERSION = (0, 1, 0)

# Messages streamed, with the code used in their rate parameter (SC_<code>_HZ on the companion link,
# SG_<code>_HZ on the ground-station link) and the default rate on the ground-station link [Hz]
# (the companion link's are the flight-controller profile's: ``profiles.py``).
STREAMS = {
    "ATT": (mavlink.MAVLINK_MSG_ID_ATTITUDE, 10.0),
    "ATTQ": (mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, 0.0),
    "LPOS": (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 10.0),
    "GPOS": (mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 5.0),
    "ODOM": (mavlink.MAVLINK_MSG_ID_ODOMETRY, 0.0),
    "IMU": (mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 0.0),
    "SYS": (mavlink.MAVLINK_MSG_ID_SYS_STATUS, 1.0),
    "BATT": (mavlink.MAVLINK_MSG_ID_BATTERY_STATUS, 1.0),
    "EXT": (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 1.0),
    "HOME": (mavlink.MAVLINK_MSG_ID_HOME_POSITION, 0.2),
    "ACT": (mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS, 2.0),
    "TIME": (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, 1.0),
}
STREAM_CODE = {msg_id: code for code, (msg_id, _) in STREAMS.items()}


@dataclass
class Snapshot:
    """What the vehicles' estimators report (truth plus configured noise), paper frames: a leading
    vehicle axis for the swarm (``row(i)`` is vehicle i's), or one vehicle's values."""

    position_m: np.ndarray
    velocity_e_m_s: np.ndarray
    velocity_b_m_s: np.ndarray
    euler_rad: np.ndarray
    quaternion: np.ndarray
    rate_b_rad_s: np.ndarray
    specific_force_b: np.ndarray
    landed: bool
    rho: np.ndarray
    _batches: dict = field(default_factory=dict, repr=False, compare=False)

    def paper_state(self) -> np.ndarray:
        """The state x of (28): body velocity, body rates, Euler angles, position."""
        return np.concatenate([self.velocity_b_m_s, self.rate_b_rad_s, self.euler_rad, self.position_m], axis=-1)

    def row(self, i: int) -> "Snapshot":
        return Snapshot(self.position_m[i], self.velocity_e_m_s[i], self.velocity_b_m_s[i], self.euler_rad[i],
                        self.quaternion[i], self.rate_b_rad_s[i], self.specific_force_b[i], bool(self.landed[i]),
                        self.rho[i])


def batch_args(msg_id: int, now_s: float, rows: Snapshot) -> list[tuple] | None:
    """The arguments of message ``msg_id`` for every vehicle of the swarm snapshot ``rows`` (kept
    with it: one conversion per step), or None for a message built vehicle by vehicle."""
    found = rows._batches.get(msg_id)
    if found is None:
        make = _BATCH.get(msg_id)
        if make is None:
            return None
        found = rows._batches[msg_id] = make(_ms(now_s), rows)
    return found


def _attitude_batch(ms: int, r: Snapshot) -> list[tuple]:
    ned = np.concatenate([frames.euler_flip(r.euler_rad), frames.flip(r.rate_b_rad_s)], axis=1)
    return [(ms, *row) for row in ned.tolist()]


def _local_position_batch(ms: int, r: Snapshot) -> list[tuple]:
    ned = np.concatenate([frames.flip(r.position_m), frames.flip(r.velocity_e_m_s)], axis=1)
    return [(ms, *row) for row in ned.tolist()]


_BATCH = {mavlink.MAVLINK_MSG_ID_ATTITUDE: _attitude_batch, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: _local_position_batch}
CONSTRUCTORS = {mavlink.MAVLINK_MSG_ID_ATTITUDE: mavlink.MAVLink_attitude_message,
                mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: mavlink.MAVLink_local_position_ned_message}
"""The message class of each batch-built message."""


def build(fc, msg_id: int, now_s: float, snap: Snapshot):
    """The message ``msg_id`` describing vehicle ``fc`` now, or None if this autopilot has none."""
    builder = _BUILDERS.get(msg_id)
    return None if builder is None else builder(fc, now_s, snap)


def _ms(now_s: float) -> int:
    return round(now_s * 1000.0) & 0xFFFFFFFF  # (round: a time of whole steps is no float error below it)


def _us(now_s: float) -> int:
    return round(now_s * 1e6)


def _attitude(fc, now_s, s):
    r, p, y = frames.euler_flip(s.euler_rad)
    wr, wp, wy = frames.flip(s.rate_b_rad_s)
    return mavlink.MAVLink_attitude_message(_ms(now_s), r, p, y, wr, wp, wy)


def _attitude_quaternion(fc, now_s, s):
    q = frames.quaternion_flip(s.quaternion)
    wr, wp, wy = frames.flip(s.rate_b_rad_s)
    return mavlink.MAVLink_attitude_quaternion_message(_ms(now_s), q[0], q[1], q[2], q[3], wr, wp, wy, [0.0] * 4)


def _local_position(fc, now_s, s):
    x, y, z = frames.flip(s.position_m)
    vx, vy, vz = frames.flip(s.velocity_e_m_s)
    return mavlink.MAVLink_local_position_ned_message(_ms(now_s), x, y, z, vx, vy, vz)


def _global_position(fc, now_s, s):
    north, east, down = frames.flip(s.position_m)
    lat, lon = fc.home.to_geodetic(north, east)
    vx, vy, vz = frames.flip(s.velocity_e_m_s)
    yaw = frames.euler_flip(s.euler_rad)[2]
    hdg = int(round(math.degrees(yaw) * 100.0)) % 36000
    return mavlink.MAVLink_global_position_int_message(
        _ms(now_s), int(round(lat * 1e7)), int(round(lon * 1e7)), int(round((fc.home.alt_m - down) * 1000.0)),
        int(round(-down * 1000.0)), _clamp16(vx * 100), _clamp16(vy * 100), _clamp16(vz * 100), hdg)


def _odometry(fc, now_s, s):
    x, y, z = frames.flip(s.position_m)
    q = frames.quaternion_flip(s.quaternion)
    vx, vy, vz = frames.flip(s.velocity_b_m_s)
    wr, wp, wy = frames.flip(s.rate_b_rad_s)
    unknown = [float("nan")] + [0.0] * 20
    return mavlink.MAVLink_odometry_message(
        _us(now_s), mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD, x, y, z, list(q), vx, vy, vz, wr, wp, wy,
        unknown, unknown, 0, mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT, 100)


MAG_NED_GAUSS = np.array([0.19, 0.0, 0.45])


def _highres_imu(fc, now_s, s):
    ax, ay, az = frames.flip(s.specific_force_b)
    gx, gy, gz = frames.flip(s.rate_b_rad_s)
    R_ned_frd = _rotation_ned_frd(s.quaternion)
    mx, my, mz = R_ned_frd.T @ MAG_NED_GAUSS
    alt = fc.home.alt_m + float(s.position_m[2])
    pressure_hpa = 1013.25 * (1.0 - 2.25577e-5 * alt) ** 5.25588
    return mavlink.MAVLink_highres_imu_message(_us(now_s), ax, ay, az, gx, gy, gz, mx, my, mz, pressure_hpa, 0.0, alt,
                                               15.0 - 0.0065 * alt, 0x1FFF, 0)


def _rotation_ned_frd(q_paper):
    return rotation_from_quaternion(frames.quaternion_flip(q_paper))


SENSORS = (mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
           | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
           | mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
           | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY)


def _sys_status(fc, now_s, s):
    c = fc.counters
    drops = fc.drops
    total = drops + c["rx_frames"]
    drop_rate = int(10000 * drops / total) if total else 0
    return mavlink.MAVLink_sys_status_message(
        SENSORS, SENSORS, SENSORS, 100, _clamp_u16(fc.battery_voltage_v * 1000), _clamp16(fc.battery_current_a * 100),
        int(fc.battery_remaining_pct()), min(drop_rate, 10000), min(drops, 65535),
        min(c["drop_bad_crc"], 65535), min(c["drop_bad_frame"], 65535), min(c["drop_foreign_system"], 65535),
        min(c["drop_actuator_non_finite"], 65535))


def _battery_status(fc, now_s, s):
    cells = int(fc.params["BAT_CELLS"])
    per_cell = _clamp_u16(fc.battery_voltage_v / cells * 1000)
    voltages = [per_cell if i < cells else 65535 for i in range(10)]
    return mavlink.MAVLink_battery_status_message(
        0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 32767, voltages,
        _clamp16(fc.battery_current_a * 100), int(min(fc.battery_used_mah, 2**31 - 1)), -1, int(fc.battery_remaining_pct()))


def _extended_sys_state(fc, now_s, s):
    return mavlink.MAVLink_extended_sys_state_message(mavlink.MAV_VTOL_STATE_UNDEFINED, fc.landed_state(s))


def _home_position(fc, now_s, s):
    north, east, down = frames.flip(fc.start_m)
    lat, lon = fc.home.to_geodetic(north, east)
    return mavlink.MAVLink_home_position_message(
        int(round(lat * 1e7)), int(round(lon * 1e7)), int(round((fc.home.alt_m - down) * 1000)), north, east, down,
        [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, _us(now_s))


def _gps_global_origin(fc, now_s, s):
    """Its local positions are from the swarm's home."""
    return mavlink.MAVLink_gps_global_origin_message(int(round(fc.home.lat_deg * 1e7)), int(round(fc.home.lon_deg * 1e7)),
                                                     int(round(fc.home.alt_m * 1000)), _us(now_s))


def _actuator_output_status(fc, now_s, s):
    af = fc.airframe()
    omega, alpha = actuator_inverse(s.rho)
    values = list(omega / af.max_rotor_speed_rad_s) + list(alpha / af.servo_limit_rad) + [0.0] * 26
    return mavlink.MAVLink_actuator_output_status_message(_us(now_s), 0b111111, values)


def _system_time(fc, now_s, s):
    return mavlink.MAVLink_system_time_message(round(fc.boot_unix_s * 1e6) + _us(now_s), _ms(now_s))


def _autopilot_version(fc, now_s, s):
    # Honest: what this autopilot implements (no missions, no FTP, no position/attitude targets;
    # the actuator-target capability bit has been retired from MAVLink, so it is not claimed).
    caps = (mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2)
    major, minor, patch = FIRMWARE_VERSION
    version = (major << 24) | (minor << 16) | (patch << 8) | 255  # 255: official release
    return mavlink.MAVLink_autopilot_version_message(caps, version, 0, 0, 0, b"triswarm", b"\0" * 8, b"\0" * 8,
                                                     0x7157, 0x0003, 0x74730000 + fc.sysid)


def _heartbeat(fc, now_s, s):
    return fc.heartbeat()


def _clamp16(v: float) -> int:
    """An int16 field (a diverged plant's current or acceleration says "off the scale", not a crash)."""
    return int(max(-32767, min(32767, round(v)))) if math.isfinite(v) else -1


def _clamp_u16(v: float) -> int:
    return int(max(0, min(65534, round(v)))) if math.isfinite(v) else 65535


_BUILDERS = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: _heartbeat,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: _attitude,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: _attitude_quaternion,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: _local_position,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: _global_position,
    mavlink.MAVLINK_MSG_ID_ODOMETRY: _odometry,
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: _highres_imu,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: _sys_status,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: _battery_status,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: _extended_sys_state,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: _home_position,
    mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: _gps_global_origin,
    mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS: _actuator_output_status,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: _system_time,
    mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: _autopilot_version,
}
