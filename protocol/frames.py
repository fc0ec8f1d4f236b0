"""Frame conversions at the MAVLink boundary, and local <-> geodetic coordinates.

Inside triswarm everything is in the paper's frames: earth x north, y west, z up; body x along arm
1, z along the untilted thrust (FLU-like). MAVLink uses NED (earth) and FRD (body). With
D = diag(1, -1, -1) (a half turn about x):

    p_ned = D p_paper,   v_frd = D v_body,   R_ned_frd = D R_b2e D,
    roll unchanged, pitch and yaw change sign, quaternion (w, x, y, z) -> (w, x, -y, -z).

D is its own inverse, so every function here converts both ways.
"""

from __future__ import annotations

import math

import numpy as np

EARTH_RADIUS_M = 6371000.0
DEFAULT_HOME = (53.4668, -2.2339, 60.0)  # lat, lon [deg], alt [m]: Manchester, where the paper's drone flew

_D = np.array([1.0, -1.0, -1.0])


def flip(vec: np.ndarray) -> np.ndarray:
    """Paper earth <-> NED for positions and velocities, body <-> FRD for body vectors and rates."""
    return np.asarray(vec, dtype=float) * _D


euler_flip = flip
"""ZYX Euler angles, paper (body to earth) <-> MAVLink (FRD to NED): (r, p, y) -> (r, -p, -y),
the same sign change as for vectors."""


def quaternion_flip(q: np.ndarray) -> np.ndarray:
    """Body-to-earth quaternion (w, x, y, z), paper <-> MAVLink (FRD to NED)."""
    return np.asarray(q, dtype=float) * np.array([1.0, 1.0, -1.0, -1.0])


def quaternion_from_euler(eta: np.ndarray) -> np.ndarray:
    """ZYX Euler angles (..., 3) [rad] to the body-to-earth quaternion (..., 4), scalar first."""
    h = 0.5 * np.asarray(eta, dtype=float)
    cf, sf = np.cos(h[..., 0]), np.sin(h[..., 0])
    ct, st = np.cos(h[..., 1]), np.sin(h[..., 1])
    cp, sp = np.cos(h[..., 2]), np.sin(h[..., 2])
    return np.stack([cp * ct * cf + sp * st * sf, cp * ct * sf - sp * st * cf,
                     cp * st * cf + sp * ct * sf, sp * ct * cf - cp * st * sf], axis=-1)


def euler_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Body-to-earth quaternion (..., 4) to ZYX Euler angles (..., 3) [rad]."""
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    roll = np.arctan2(2.0 * (qw * qx + qy * qz), 1.0 - 2.0 * (qx * qx + qy * qy))
    pitch = np.arcsin(np.clip(2.0 * (qw * qy - qz * qx), -1.0, 1.0))
    yaw = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return np.stack([roll, pitch, yaw], axis=-1)


def rotation_from_quaternion(q: np.ndarray) -> np.ndarray:
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (qy * qy + qz * qz)
    R[..., 0, 1] = 2 * (qx * qy - qz * qw)
    R[..., 0, 2] = 2 * (qx * qz + qy * qw)
    R[..., 1, 0] = 2 * (qx * qy + qz * qw)
    R[..., 1, 1] = 1 - 2 * (qx * qx + qz * qz)
    R[..., 1, 2] = 2 * (qy * qz - qx * qw)
    R[..., 2, 0] = 2 * (qx * qz - qy * qw)
    R[..., 2, 1] = 2 * (qy * qz + qx * qw)
    R[..., 2, 2] = 1 - 2 * (qx * qx + qy * qy)
    return R


def attitude_from_mavlink(q_ned_frd) -> tuple[float, float, float]:
    """A MAVLink attitude quaternion (w, x, y, z; FRD body in NED) as the paper's Euler angles."""
    qw, qx, qy, qz = (float(c) for c in q_ned_frd)
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if not n > 0.0:
        return (math.nan, math.nan, math.nan)
    return tuple(euler_from_quaternion(np.array([qw, qx, -qy, -qz]) / n).tolist())


def body_velocity_to_earth(q_ned_frd, v_frd) -> tuple[float, float, float]:
    """A body-frame (FRD) velocity as the paper's earth-frame one, for the attitude q_ned_frd."""
    q = np.array([float(c) for c in q_ned_frd])
    R = rotation_from_quaternion(q / np.linalg.norm(q))
    return tuple((flip(R @ np.asarray(v_frd, dtype=float))).tolist())


def parse_home(text: str) -> tuple[float, float, float]:
    """A home written LAT,LON,ALT_M (degrees, degrees, metres) as three numbers; ValueError saying
    what is wrong (not three numbers, or not a place on Earth)."""
    try:
        lat, lon, alt = (float(p) for p in str(text).split(","))
    except ValueError:  # not numbers, or not three of them
        raise ValueError(f"--home must be LAT,LON,ALT_M (three numbers), got {text!r}") from None
    LocalProjection(lat, lon, alt)  # validates
    return lat, lon, alt


class LocalProjection:
    """Azimuthal equidistant projection around a home point (as PX4's map_projection): local
    north/east metres <-> latitude/longitude degrees. Exact along great circles through home;
    errors stay below a millimetre within a few kilometres."""

    def __init__(self, lat_deg: float, lon_deg: float, alt_m: float = 0.0) -> None:
        if not (math.isfinite(lat_deg) and -90.0 < lat_deg < 90.0):
            raise ValueError(f"home latitude must be a number between -90 and 90 degrees, got {lat_deg!r}")
        if not (math.isfinite(lon_deg) and -180.0 <= lon_deg <= 180.0):
            raise ValueError(f"home longitude must be a number between -180 and 180 degrees, got {lon_deg!r}")
        if not math.isfinite(alt_m):
            raise ValueError(f"home altitude must be a finite number of metres, got {alt_m!r}")
        self.lat_deg, self.lon_deg, self.alt_m = float(lat_deg), float(lon_deg), float(alt_m)
        self._lat0 = math.radians(lat_deg)
        self._lon0 = math.radians(lon_deg)
        self._sin0, self._cos0 = math.sin(self._lat0), math.cos(self._lat0)

    def to_geodetic(self, north_m: float, east_m: float) -> tuple[float, float]:
        x, y = north_m / EARTH_RADIUS_M, east_m / EARTH_RADIUS_M
        c = math.hypot(x, y)
        if c == 0.0:
            return self.lat_deg, self.lon_deg
        sc, cc = math.sin(c), math.cos(c)
        lat = math.asin(cc * self._sin0 + x * sc * self._cos0 / c)
        lon = self._lon0 + math.atan2(y * sc, c * self._cos0 * cc - x * self._sin0 * sc)
        return math.degrees(lat), math.degrees(lon)

    def to_local(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        lat, dlon = math.radians(lat_deg), math.radians(lon_deg) - self._lon0
        sl, cl = math.sin(lat), math.cos(lat)
        arg = min(1.0, max(-1.0, self._sin0 * sl + self._cos0 * cl * math.cos(dlon)))
        c = math.acos(arg)
        k = 1.0 if c == 0.0 else c / math.sin(c)
        north = k * (self._cos0 * sl - self._sin0 * cl * math.cos(dlon)) * EARTH_RADIUS_M
        east = k * cl * math.sin(dlon) * EARTH_RADIUS_M
        return north, east


def geodetic_from_mavlink(lat_e7: int, lon_e7: int, alt_mm: int) -> tuple[float, float, float] | None:
    """A MAVLink position (degE7, degE7, mm) as latitude, longitude [deg], altitude [m]; None if it
    is no place on Earth (a bad or hostile message)."""
    lat_deg, lon_deg = lat_e7 / 1e7, lon_e7 / 1e7
    if not (-90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 180.0):
        return None
    return lat_deg, lon_deg, alt_mm / 1000.0


def origin_offset_e_m(home_lla, origin_lla) -> tuple[float, float, float]:
    """Where a flight controller's local origin (its EKF origin: latitude, longitude [deg], altitude
    [m]) is from the swarm's home, in the paper's earth frame [m] (x north, y west, z up): what to add
    to its local positions to have them from home."""
    north_m, east_m = LocalProjection(*home_lla).to_local(origin_lla[0], origin_lla[1])
    return north_m, -east_m, float(origin_lla[2]) - float(home_lla[2])
