"""Wind in the plant: the drag of a steady wind against its closed form, the Dryden turbulence's
variance and correlation against MIL-F-8785C's, the 1-cosine gust at known instants, still air that
changes nothing, and the same seed giving the same wind."""

import math

import numpy as np
import pytest

from triswarm.protocol import model
from triswarm.protocol.airframe import ParameterError
from triswarm.protocol.wind import (TURBULENCE_SIGMA_W_M_S, Dryden, Gust, Wind, one_minus_cosine, wind_from_table,
                                    wind_vector_e)
from triswarm.sitl.physics import Plant


def dryden_correlation(sigma_m_s, time_constants_s, lag_s):
    """MIL-F-8785C's correlations of u, v, w at a time lag t (x = V t along the frozen turbulence):
    sigma_u^2 e^(-t/T_u), and sigma^2 e^(-t/T) (1 - t/2T) for v and w, T = L / V."""
    x = lag_s / np.asarray(time_constants_s)
    return np.asarray(sigma_m_s) ** 2 * np.exp(-x) * np.array([1.0, 1.0 - x[1] / 2.0, 1.0 - x[2] / 2.0])


def hovering(airframe, n, wind, seed=0, z_m=50.0):
    """n drones in the air at hover trim, commands held, no servo delay."""
    omega, alpha = model.hover_trim(airframe)
    plant = Plant(airframe, n, dt_s=1e-3, servo_delay_s=0.0, wind=wind, wind_seed=seed)
    plant.reset(np.tile([0.0, 0.0, z_m], (n, 1)), servo_rad=alpha)
    plant.landed[:] = False
    plant.command(np.tile(omega, (n, 1)), np.tile(alpha, (n, 1)))
    return plant


def test_directions_are_meteorological():
    assert wind_vector_e(5.0, 0.0) == pytest.approx([-5.0, 0.0, 0.0])     # from the north: blows south
    assert wind_vector_e(5.0, 90.0) == pytest.approx([0.0, 5.0, 0.0])     # from the east: blows west (+y)
    assert wind_vector_e(5.0, 270.0) == pytest.approx([0.0, -5.0, 0.0])


def test_steady_wind_sweeps_a_hovering_drone_as_the_closed_form(airframe):
    """Hover trim in a steady wind W from the east: no torque and no vertical force, so the drone
    drifts west with m dv/dt = k (W - v)^2, k = 1/2 rho C_d A: the air-relative speed falls as
    W / (1 + k W t / m), and y(t) = W t - (m / k) ln(1 + k W t / m). At rest the force is k W^2."""
    W, rho_air = 8.0, 1.225
    plant = hovering(airframe, 1, Wind(speed_m_s=W, from_deg=90.0, air_density_kg_m3=rho_air))
    k, m = 0.5 * rho_air * airframe.drag_coefficient * airframe.frontal_area_m2, airframe.mass_kg
    assert k * W**2 == pytest.approx(0.784, abs=1e-3)  # [N]: 1/2 1.225 1.0 0.02 64
    plant.advance(1)
    assert plant.observe().velocity_e_m_s[0, 1] == pytest.approx(k * W**2 / m * 1e-3, rel=1e-3)
    plant.advance(2999)
    t = 3.0
    obs = plant.observe()
    assert obs.velocity_e_m_s[0] == pytest.approx([0.0, W - W / (1 + k * W * t / m), 0.0], abs=1e-9)
    assert obs.position_m[0] == pytest.approx([0.0, W * t - m / k * math.log(1 + k * W * t / m), 50.0], abs=1e-8)
    assert np.abs(obs.euler_rad).max() < 1e-9
    assert plant.wind_e_m_s[0] == pytest.approx([0.0, W, 0.0])


def test_still_air_changes_nothing_for_a_drone_at_rest_and_no_drag_area_changes_nothing(airframe):
    """A hovering drone in still air feels no drag: the run without any air, but for the drag of its
    rounding drift (1e-15 m/s, squared). A drone with no drag area in a gusty, turbulent wind is bit
    for bit the drone in no air, whatever it does."""
    none, still = hovering(airframe, 2, None), hovering(airframe, 2, Wind())
    none.advance(500)
    still.advance(500)
    assert np.abs(none.state - still.state).max() < 1e-25
    bare = airframe.replace(frontal_area_m2=0.0)
    rough = Wind(speed_m_s=7.0, turbulence_sigma_w_m_s=2.0, gusts=(Gust(4.0, 1.0, 0.1),))
    runs = [Plant(bare, 2, wind=w, wind_seed=3) for w in (None, rough)]
    for plant in runs:
        plant.reset([[0, 0, 20.0], [5, 0, 20.0]], euler_rad=[[0.2, -0.1, 1.0]] * 2)
        plant.landed[:] = False
        plant.command([[250.0, 300.0, 280.0]] * 2, [[0.3, -0.2, 0.1]] * 2)
        plant.advance(700)
    assert np.array_equal(runs[0].state, runs[1].state)
    assert np.abs(runs[1].wind_e_m_s).max() > 1.0  # (the wind was there)


def test_dryden_discretisation_is_exact():
    """The discrete filters' variance and correlation (from their stationary covariance) equal
    MIL-F-8785C's closed forms: sigma_u^2 e^(-t/T_u), sigma^2 e^(-t/T) (1 - t/2T) for v and w."""
    wind = Wind(speed_m_s=10.0, from_deg=30.0, turbulence_sigma_w_m_s=TURBULENCE_SIGMA_W_M_S["moderate"])
    d = Dryden.of(wind, 0.01)
    sigma = wind.intensities_m_s()
    # 8785C at 20 m (65.6 ft): sigma_u = 1.54 / (0.177 + 0.000823 * 65.6)^0.4, L_u = 65.6 ft / (...)^1.2
    assert sigma == pytest.approx([2.7734, 2.7734, 1.5433], abs=1e-4)
    assert wind.length_scales_m() == pytest.approx([116.06, 116.06, 20.0], abs=0.01)
    assert d.time_constants_s == pytest.approx([11.606, 11.606, 2.0], abs=1e-3)
    for lag in (0, 1, 37, 200, 1000, 3000):
        assert d.correlation(lag) == pytest.approx(dryden_correlation(sigma, d.time_constants_s, lag * 0.01),
                                                   rel=1e-9, abs=1e-12)


def test_dryden_turbulence_in_the_plant_has_the_closed_forms_variance_and_correlation():
    """A long seeded run of 400 drones resting on the ground (the turbulence runs whether they fly or
    not), 5 m up in a 20 m/s wind (T_u = 1.82 s, T_w = 0.25 s). The drones' realisations are
    independent, so the spread of the 400 per-drone estimates gives each estimate's standard error:
    every one must lie within 4 standard errors of the closed form (a chance of 6e-5 each to fail
    if the process is right), and the standard error must be small enough (< 2.5 % of sigma^2) that
    a wrong variance or time constant would show."""
    wind = Wind(speed_m_s=20.0, from_deg=0.0, turbulence_sigma_w_m_s=TURBULENCE_SIGMA_W_M_S["severe"],
                turbulence_altitude_m=5.0)
    n, dt, steps = 400, 0.01, 6000
    plant = Plant(model.Airframe(), n, dt_s=dt, wind=wind, wind_seed=11)
    plant.reset(np.zeros((n, 3)))
    series = np.empty((steps, n, 3))
    for k in range(steps):
        plant.advance(1)
        series[k] = plant.wind_e_m_s
    assert plant.landed.all()
    turb = series - wind.steady_e_m_s
    # the wind blows from the north: u along -x, v across (y), w up
    comps = np.stack([-turb[..., 0], turb[..., 1], turb[..., 2]], axis=-1)  # (steps, n, 3)
    h_ft = 5.0 / 0.3048  # MIL-F-8785C at 5 m: L_w = h, L_u = L_v = h / (0.177 + 0.000823 h)^1.2 [ft]
    T = np.array([1.0, 1.0, (0.177 + 0.000823 * h_ft) ** 1.2]) * h_ft / (0.177 + 0.000823 * h_ft) ** 1.2 * 0.3048 / 20.0
    sigma_w = 0.1 * 45 * 1852 / 3600  # severe: 0.1 W20, W20 = 45 kt
    sigma = sigma_w * np.array([1.0 / (0.177 + 0.000823 * h_ft) ** 0.4] * 2 + [1.0])
    assert T == pytest.approx([1.82, 1.82, 0.25], abs=0.01)
    for lag_s in (0.0, 0.25, 1.0, 2.0):
        lag = int(round(lag_s / dt))
        per_drone = (comps[: steps - lag] * comps[lag:]).mean(axis=0)  # (n, 3)
        estimate, se = per_drone.mean(axis=0), per_drone.std(axis=0, ddof=1) / math.sqrt(n)
        truth = dryden_correlation(sigma, T, lag_s)
        assert np.all(se < 0.025 * sigma**2), (lag_s, se / sigma**2)
        assert np.all(np.abs(estimate - truth) < 4 * se), (lag_s, estimate, truth, se)


def test_one_minus_cosine_gust_at_known_instants(airframe):
    """A 5 m/s gust from the south (blowing north, +x) lasting 2 s from t = 1 s, on a 3 m/s wind from
    the east: zero before and after, half its peak a quarter and three quarters through, its peak
    halfway."""
    for t, share in ((0.0, 0.0), (0.999, 0.0), (1.0, 0.0), (1.5, 0.5), (2.0, 1.0), (2.5, 0.5), (3.0, 0.0), (4.0, 0.0)):
        assert one_minus_cosine(t, 1.0, 2.0) == pytest.approx(share, abs=1e-12)
    wind = Wind(speed_m_s=3.0, from_deg=90.0, gusts=(Gust(5.0, 2.0, 1.0, from_deg=180.0),))
    plant = hovering(airframe, 1, wind)
    seen = {}
    for k in range(3500):
        plant.advance(1)  # the wind of step k, taken at t = k dt
        seen[k] = plant.wind_e_m_s[0].copy()
    for t, share in ((0.5, 0.0), (1.5, 0.5), (2.0, 1.0), (2.5, 0.5), (3.2, 0.0)):
        assert seen[int(round(t * 1000))] == pytest.approx([5.0 * share, 3.0, 0.0], abs=1e-9)
    assert max(v[0] for v in seen.values()) == pytest.approx(5.0, abs=1e-9)


def test_same_seed_same_wind_however_the_steps_are_grouped(airframe):
    wind = Wind(speed_m_s=6.0, from_deg=200.0, turbulence_sigma_w_m_s=1.5, gusts=(Gust(4.0, 1.0, 0.2),))
    a, b, c = hovering(airframe, 3, wind, seed=5), hovering(airframe, 3, wind, seed=5), hovering(airframe, 3, wind, seed=6)
    a.advance(1000)
    for _ in range(200):
        b.advance(5)
    c.advance(1000)
    assert np.array_equal(a.wind_e_m_s, b.wind_e_m_s) and np.array_equal(a.state, b.state)
    assert not np.allclose(a.wind_e_m_s, c.wind_e_m_s)
    assert not np.allclose(a.wind_e_m_s[0], a.wind_e_m_s[1])  # each drone its own turbulence


@pytest.mark.parametrize("table,message", [
    ({"speed_m_s": -2.0}, r"wind.speed_m_s must not be negative, got -2.0"),
    ({"speed_m_s": "fast"}, r"wind.speed_m_s must be a finite number, got 'fast'"),
    ({"from_deg": float("nan")}, r"wind.from_deg must be a finite number, got nan"),
    ({"turbulence": "stormy"}, r"wind.turbulence must be none, light, moderate, severe or sigma_w in m/s, got 'stormy'"),
    ({"turbulence": -1.0}, r"wind.turbulence must be .* \(not negative\), got -1.0"),
    ({"turbulence_altitude_m": 1000.0}, r"wind.turbulence_altitude_m must be between 3 and 300, got 1000.0"),
    ({"air_density_kg_m3": 0.0}, r"wind.air_density_kg_m3 must be positive, got 0.0"),
    ({"gust": {}}, r"wind.gust is not a known field"),
    ({"gusts": {"speed_m_s": 1.0}}, r"wind.gusts must be a list of tables"),
    ({"gusts": [{"speed_m_s": 3.0, "start_s": 1.0}]}, r"wind.gusts\[0\].duration_s is required"),
    ({"gusts": [{"speed_m_s": 3.0, "start_s": 1.0, "duration_s": 0.0}]}, r"wind.gusts\[0\].duration_s must be positive"),
    ({"gusts": [{"speed_m_s": 3.0, "start_s": 1.0, "duration_s": 1.0, "form_deg": 3}]},
     r"wind.gusts\[0\].form_deg is not a known field"),
])
def test_bad_wind_fields_are_refused_with_one_sentence(table, message):
    with pytest.raises(ParameterError, match=message) as exc:
        wind_from_table(table)
    assert "\n" not in str(exc.value)


def test_wind_table():
    w = wind_from_table({"speed_m_s": 6, "from_deg": 270, "turbulence": "light",
                         "gusts": [{"speed_m_s": 4, "duration_s": 2, "start_s": 30}]})
    assert w.steady_e_m_s == pytest.approx([0.0, -6.0, 0.0])
    assert w.turbulence_sigma_w_m_s == pytest.approx(0.1 * 15 * 1852 / 3600)
    assert w.gust_table() == pytest.approx(np.array([[30.0, 2.0, 0.0, -4.0, 0.0]]))
    assert wind_from_table({"turbulence": 0.8}).turbulence_sigma_w_m_s == 0.8


def test_a_plans_wind_is_flown_and_a_configs_wind_replaces_it(paper_spec):
    from triswarm.protocol.plan import plan_from_dict
    from triswarm.sitl.simulation import SimConfig, flown_wind, simulate

    # (without the accelerometer, which would measure the wind and leave the drones within 1 mm)
    spec = dict(paper_spec, controller=dict(paper_spec["controller"], accelerometer=False))
    plan = plan_from_dict(dict(spec, wind={"speed_m_s": 9.0, "from_deg": 90.0}), "windy.toml")
    assert plan.wind == Wind(speed_m_s=9.0, from_deg=90.0)
    other = Wind(speed_m_s=2.0)
    assert flown_wind(plan, SimConfig()) is plan.wind and flown_wind(plan, SimConfig(wind=other)) is other
    calm = plan_from_dict(spec, "calm.toml")
    assert calm.wind is None and flown_wind(calm, SimConfig()) is None
    windy, still = (simulate(p, SimConfig(duration_s=4.0, log_hz=10)) for p in (plan, calm))
    # blown towards +y (west) while they climb, the controllers pull them back: never exactly where
    # the drones in no air are
    assert np.abs(windy.position_m[-1] - still.position_m[-1]).max() > 1e-3


def test_the_sitl_swarm_flies_in_its_wind():
    from triswarm.sitl.swarm import SitlSwarm

    swarm = SitlSwarm(2, wind=Wind(speed_m_s=5.0, from_deg=90.0), seed=4)
    for _ in range(20):
        swarm.step()
    assert swarm.plant.wind_e_m_s == pytest.approx(np.tile([0.0, 5.0, 0.0], (2, 1)))
    assert SitlSwarm(1).plant.wind is None
