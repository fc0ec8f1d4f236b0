"""Paper frame <-> MAVLink NED/FRD, on known rotations; local <-> geodetic."""

import math

import numpy as np
import pytest

from triswarm.protocol import frames, model
from triswarm.protocol.frames import EARTH_RADIUS_M, LocalProjection
from triswarm.sitl.physics import quaternion_from_euler, rotation_from_quaternion

D = np.diag([1.0, -1.0, -1.0])


def test_positions_and_velocities():
    # 1 m north, 2 m west, 3 m up  ->  N 1, E -2, D -3
    assert np.allclose(frames.flip([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0])
    assert np.allclose(frames.flip(frames.flip([0.3, -0.7, 9.0])), [0.3, -0.7, 9.0])


def test_known_rotations():
    # yaw +90 deg in the paper (counter-clockwise seen from above, z up) turns the nose from north to
    # west; in NED that heading is 270 deg, i.e. yaw -90 deg
    eta = np.array([0.0, 0.0, math.pi / 2])
    nose_paper = model.rotation_body_to_earth(eta) @ [1, 0, 0]
    assert np.allclose(nose_paper, [0, 1, 0], atol=1e-15)                  # west
    assert np.allclose(frames.euler_flip(eta), [0, 0, -math.pi / 2])
    # pitch +0.3 rad in the paper (about y = west) lowers the nose: body x gets a -z (down) part...
    eta = np.array([0.0, 0.3, 0.0])
    nose = model.rotation_body_to_earth(eta) @ [1, 0, 0]
    assert nose[2] < 0
    # ... which NED calls nose-down: pitch -0.3
    assert frames.euler_flip(eta)[1] == pytest.approx(-0.3)
    # roll is the same rotation about the same (north-pointing) axis in both frames
    assert frames.euler_flip([0.4, 0.0, 0.0])[0] == pytest.approx(0.4)


def test_rotations_and_quaternions_agree(rng):
    for eta in rng.uniform([-3, -1.5, -3], [3, 1.5, 3], (50, 3)):
        R_paper = model.rotation_body_to_earth(eta)
        R_ned = model.rotation_body_to_earth(frames.euler_flip(eta))  # same ZYX formula, NED angles
        assert np.allclose(R_ned, D @ R_paper @ D, atol=1e-12)
        q_ned = frames.quaternion_flip(quaternion_from_euler(eta))
        assert np.allclose(rotation_from_quaternion(q_ned), R_ned, atol=1e-12)
        # a body vector (FLU-like) maps to the same physical direction in both conventions
        v_b = rng.normal(size=3)
        assert np.allclose(D @ (R_paper @ v_b), R_ned @ frames.flip(v_b), atol=1e-12)


def test_local_projection():
    home = LocalProjection(53.4668, -2.2339, 60.0)
    lat, lon = home.to_geodetic(1000.0, 0.0)
    assert lat - 53.4668 == pytest.approx(math.degrees(1000.0 / EARTH_RADIUS_M), rel=1e-9)
    assert lon == pytest.approx(-2.2339, abs=1e-12)
    lat, lon = home.to_geodetic(0.0, 1000.0)
    assert (lon + 2.2339) * math.cos(math.radians(53.4668)) == pytest.approx(math.degrees(1000.0 / EARTH_RADIUS_M), rel=1e-6)
    for north, east in [(0, 0), (3.5, -2.1), (-4000, 2500), (120.0, 80.0)]:
        assert np.allclose(home.to_local(*home.to_geodetic(north, east)), [north, east], atol=1e-6)
    with pytest.raises(ValueError, match="latitude"):
        LocalProjection(float("nan"), 0.0)


def test_an_origin_s_offset_from_home_is_the_geodesic_in_the_paper_s_frame():
    home = frames.DEFAULT_HOME
    lat, lon = LocalProjection(*home).to_geodetic(120.0, -35.0)  # 120 m north, 35 m west
    assert frames.origin_offset_e_m(home, (lat, lon, home[2] + 4.0)) == pytest.approx((120.0, 35.0, 4.0), abs=1e-6)
    assert frames.origin_offset_e_m(home, home) == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    # one degree of latitude is the Earth's radius times pi / 180
    north_m = frames.origin_offset_e_m(home, (home[0] + 1.0, home[1], home[2]))[0]
    assert north_m == pytest.approx(EARTH_RADIUS_M * math.pi / 180, rel=1e-9)


def test_a_mavlink_position_that_is_no_place_on_earth_is_none():
    assert frames.geodetic_from_mavlink(534668000, -22339000, 60000) == pytest.approx((53.4668, -2.2339, 60.0))
    assert frames.geodetic_from_mavlink(900000000, 1800000000, 0) == (90.0, 180.0, 0.0)
    for lat_e7, lon_e7 in ((2**31 - 1, 0), (0, -(2**31)), (-900000001, 0), (0, 1800000001)):
        assert frames.geodetic_from_mavlink(lat_e7, lon_e7, 0) is None
