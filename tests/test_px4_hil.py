"""What PX4 reads from triswarm's plant (``sitl/px4_hil.py``): its magnetometer against PX4's own
world magnetic model tables, its barometer against the International Standard Atmosphere, and the
frames of every reading against geometry. Pure: no firmware, no socket."""

from __future__ import annotations

import datetime
import math

import numpy as np
import pytest

from triswarm.protocol import frames
from triswarm.protocol.airframe import TABLE_1
from triswarm.sitl.physics import Plant
from triswarm.sitl.px4_hil import HilPhysics, SensorNoise, earth_field_ned_gauss, isa_pressure_hpa

NO_NOISE = SensorNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
HOME = (47.397742, 8.545594, 488.0)


@pytest.mark.parametrize("place, declination_deg, inclination_deg, strength_gauss", [
    ((47.397742, 8.545594, 488.0), 3.406, 63.157, 0.4824),   # PX4's SITL home (Zurich)
    ((42.2936, -83.7166, 270.0), -7.009, 68.324, 0.5269),    # Ann Arbor
])
def test_the_field_is_the_one_px4_expects(place, declination_deg, inclination_deg, strength_gauss):
    """PX4 checks its magnetometer against its own tables of the World Magnetic Model
    (src/lib/world_magnetic_model, interpolated on a 10-degree grid): the simulated one agrees to a
    fraction of a degree and of a percent."""
    b = earth_field_ned_gauss(*place, datetime.date(2026, 3, 1))
    assert math.degrees(math.atan2(b[1], b[0])) == pytest.approx(declination_deg, abs=0.5)
    assert math.degrees(math.atan2(b[2], math.hypot(b[0], b[1]))) == pytest.approx(inclination_deg, abs=0.5)
    assert np.linalg.norm(b) == pytest.approx(strength_gauss, rel=0.02)


def test_isa_pressure():
    assert isa_pressure_hpa(0.0) == pytest.approx(1013.25)
    assert isa_pressure_hpa(1000.0) == pytest.approx(898.76, abs=0.05)  # (the ISA table)
    assert isa_pressure_hpa(3000.0) == pytest.approx(701.12, abs=0.1)  # (geopotential height: 1.4 m apart there)


def physics(position_m, euler_rad) -> tuple[HilPhysics, np.ndarray]:
    plant = Plant(TABLE_1, 1, dt_s=0.001)
    plant.reset(np.array([position_m]), np.array([euler_rad]))
    hil = HilPhysics(plant, [1], HOME, datetime.datetime(2026, 3, 1, tzinfo=datetime.UTC).timestamp(), NO_NOISE,
                     unix_clock=lambda: 1.7e9)
    return hil, plant.sensors()[0]


@pytest.mark.parametrize("yaw_rad, expect", [(0.0, lambda b: b), (math.pi / 2, lambda b: (-b[1], b[0], b[2]))])
def test_at_rest_the_imu_feels_gravity_and_the_compass_points_north(yaw_rad, expect):
    """On the ground, level: the accelerometer reads -g along its z (FRD: down), the gyro nothing,
    the magnetometer the earth's field turned into the body (the paper's yaw counts anticlockwise
    from north: at pi/2 the nose points west, north is to the right)."""
    hil, row = physics([0.0, 0.0, 0.0], [0.0, 0.0, yaw_rad])
    m = hil.hil_sensor(row, 1000)
    np.testing.assert_allclose([m.xacc, m.yacc, m.zacc], [0.0, 0.0, -TABLE_1.gravity_m_s2], atol=1e-9)
    np.testing.assert_allclose([m.xgyro, m.ygyro, m.zgyro], 0.0, atol=1e-12)
    np.testing.assert_allclose([m.xmag, m.ymag, m.zmag], expect(hil.field_ned), atol=1e-9)
    assert m.abs_pressure == pytest.approx(isa_pressure_hpa(HOME[2]))
    assert m.time_usec == 1000


def test_gps_says_where_the_drone_is():
    """10 m north and 5 m west of home, 3 m up: PX4's projection of that back is that place."""
    hil, row = physics([10.0, 5.0, 3.0], [0.0, 0.0, 0.0])
    g = hil.hil_gps(row, 1000)
    north, east = frames.LocalProjection(*HOME).to_local(g.lat / 1e7, g.lon / 1e7)
    assert (north, east) == (pytest.approx(10.0, abs=0.01), pytest.approx(-5.0, abs=0.01))
    assert g.alt == round((HOME[2] + 3.0) * 1000)
    assert g.time_usec == int(1.7e15) and g.fix_type == 3


def test_a_plant_behind_the_wall_clock_catches_up_at_most_at_the_catch_up_pace():
    """The plant's process starved for 0.6 s (a real stall: the loop blocked), the plant, behind by
    that, catches up no faster than CATCH_UP simulated seconds per wall second over any stretch,
    never in a burst (which would run a firmware's clock away from its companion's commands), and
    it says how far behind it fell. A bound on speed only: a slow machine cannot break it."""
    import asyncio
    import time

    from triswarm.sitl.px4_hil import CATCH_UP

    hil, _ = physics([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    seen: list[tuple[float, float]] = []  # (wall [s], plant [s])

    async def fly():
        stop = asyncio.Event()
        task = asyncio.create_task(hil.run(stop))
        await asyncio.sleep(0.2)
        time.sleep(0.6)  # (the stall: nothing of the loop runs)
        for _ in range(200):  # (2 s at most)
            seen.append((time.monotonic(), hil.t_s))
            await asyncio.sleep(0.01)
        stop.set()
        await asyncio.wait_for(task, 5.0)
    asyncio.run(fly())
    step_s = 1.0 / 250.0
    for (w0, s0), (w1, s1) in zip(seen, seen[1:]):
        assert s1 - s0 <= CATCH_UP * (w1 - w0) + step_s, (w1 - w0, s1 - s0)
    assert seen[-1][1] - seen[0][1] <= CATCH_UP * (seen[-1][0] - seen[0][0]) + step_s
    assert hil.counters["behind_max_ms"] >= 500
