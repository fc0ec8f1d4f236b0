"""`plan check` knows the air: what the design air asks of the rotors and servos against closed forms
of a level hover in wind (the tri-rotor's geometry, (3), (13), (14)), the margin it leaves
shrinking as the wind grows, and a plan that passes in calm air refused in a strong design wind,
naming the drone, the instant, the limit and the air."""

import copy
import json
import math

import numpy as np
import pytest

from triswarm.gcs import plan_flight
from triswarm.protocol import air_margin
from triswarm.protocol.airframe import Airframe
from triswarm.protocol.errors import PlanError
from triswarm.protocol.formation import ConstantFormation
from triswarm.protocol.plan import plan_from_dict
from triswarm.protocol.rfl import RFL
from triswarm.protocol.wind import Gust, Wind

from .conftest import paper_plan_variant
from .test_plan_check import plan_check

AF = Airframe(k_d_N_m_s2=0.0)  # no rotor drag torque: the closed forms below are then exact
WEIGHT_N = AF.mass_kg * AF.gravity_m_s2
DRAG_N_S2_M2 = 0.5 * 1.225 * AF.drag_coefficient * AF.frontal_area_m2  # 1/2 rho C_d A


def hover_demand(winds_e_m_s, af=AF):
    """One drone hovering level at 10 m, in the given winds (the worst of them)."""
    still = ConstantFormation(np.zeros((1, 3)), np.zeros((1, 3)))
    at = ConstantFormation(np.array([[0.0, 0.0, 10.0]]), np.zeros((1, 3)))
    return air_margin.actuator_demand(RFL.from_airframe(af), still, at, np.array([0.0]), 1.225, winds_e_m_s)


def level_hover_tilts_rad(force_n):
    """Closed form: the servo angles of a level tri-rotor (k_d = 0) whose rotors together push the
    body force ``force_n`` (3,) [N]. By (3) the body force over k_f is (sqrt3/2 (rho2 - rho1),
    rho0 - (rho1 + rho2)/2, rho3 + rho4 + rho5) with rho_i = omega_i^2 sin(alpha_i),
    rho_(i+3) = omega_i^2 cos(alpha_i); zero torque with k_d = 0 makes the three shaft components
    equal and the three tilting components sum to zero."""
    fx, fy, fz = np.moveaxis(np.asarray(force_n, dtype=float), -1, 0)
    tangential = np.stack([2.0 * fy / 3.0, -fy / 3.0 - fx / math.sqrt(3.0), -fy / 3.0 + fx / math.sqrt(3.0)], axis=-1)
    return np.arctan2(np.abs(tangential), fz[..., None] / 3.0)


@pytest.mark.parametrize("from_deg,tan_tilt_per_drag", [(0.0, math.sqrt(3.0)), (90.0, 2.0)])
def test_tilt_and_rotor_speed_of_a_hover_in_steady_wind_are_the_closed_form(from_deg, tan_tilt_per_drag):
    """Wind along body x (from the north): rotors 2 and 3 tilt, tan = sqrt3 D / (m g); along body y
    (from the east): rotor 1 tilts, tan = 2 D / (m g); D = 1/2 rho C_d A W^2."""
    for speed in (4.0, 8.0, 16.0):
        drag_n = DRAG_N_S2_M2 * speed**2
        d = hover_demand(Wind(speed_m_s=speed, from_deg=from_deg).steady_e_m_s[None, :])
        assert np.tan(d.tilt_max_rad[0, 0]) == pytest.approx(tan_tilt_per_drag * drag_n / WEIGHT_N, rel=1e-9)
        tangential = tan_tilt_per_drag * drag_n / 3.0  # each rotor's share of the weight is m g / 3
        omega = (math.hypot(tangential, WEIGHT_N / 3.0) / AF.k_f_N_s2) ** 0.5
        assert d.omega_max_rad_s[0, 0] == pytest.approx(omega, rel=1e-9)
        assert d.tilt_margin_rad(AF)[0] == pytest.approx(AF.servo_limit_rad - math.atan(tan_tilt_per_drag * drag_n / WEIGHT_N))
        assert d.rotor_speed_margin_pct(AF)[0] == pytest.approx(100.0 * (1.0 - omega / AF.max_rotor_speed_rad_s))


@pytest.mark.parametrize("from_deg", [0.0, 17.0, 45.0])
def test_turbulence_is_taken_from_its_worst_direction(from_deg):
    """3 sigma of moderate turbulence on a hovering drone: the largest tilt the sampled directions
    find is within 0.25 deg under the largest over 200,000 directions of the closed form (and not over it)."""
    wind = Wind(turbulence_sigma_w_m_s=1.54, from_deg=from_deg)
    sigma = 3.0 * wind.intensities_m_s()
    d = hover_demand(air_margin.design_winds_e_m_s(wind, 3.0))
    unit = np.random.default_rng(0).normal(size=(200_000, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    air_m_s = unit * sigma  # (along, across, up): sigma_u = sigma_v, so x, y, z alike
    push_n = -DRAG_N_S2_M2 * np.linalg.norm(air_m_s, axis=1, keepdims=True) * air_m_s + [0.0, 0.0, WEIGHT_N]
    truth = math.degrees(level_hover_tilts_rad(push_n).max())  # the drag k |w| w of the moving air, taken up by the rotors
    found = math.degrees(d.tilt_max_rad[0, 0])
    assert truth - 0.25 < found <= truth + 0.01
    assert found > 15.0  # (8.3 m/s across, 3 sigma_v: it is the air, not the hover's 3.6 deg)


def test_gusts_and_turbulence_add_to_the_steady_wind():
    steady = Wind(speed_m_s=6.0, from_deg=90.0)
    gust = Wind(speed_m_s=6.0, from_deg=90.0, gusts=(air_margin_gust(4.0),))
    assert air_margin.design_winds_e_m_s(steady) == pytest.approx(np.array([[0.0, 6.0, 0.0]]))
    assert air_margin.design_winds_e_m_s(gust) == pytest.approx(np.array([[0.0, 6.0, 0.0], [0.0, 10.0, 0.0]]))
    tilt = [hover_demand(air_margin.design_winds_e_m_s(w)).tilt_max_rad[0, 0] for w in (steady, gust)]
    assert math.tan(tilt[1]) == pytest.approx(2.0 * DRAG_N_S2_M2 * 100.0 / WEIGHT_N, rel=1e-9) and tilt[1] > tilt[0]
    turbulent = Wind(speed_m_s=6.0, from_deg=90.0, turbulence_sigma_w_m_s=0.77)
    assert len(air_margin.design_winds_e_m_s(turbulent)) == air_margin.TURBULENCE_DIRECTIONS
    assert hover_demand(air_margin.design_winds_e_m_s(turbulent)).tilt_max_rad[0, 0] > tilt[0]
    assert hover_demand(air_margin.design_winds_e_m_s(turbulent, 0.0)).tilt_max_rad[0, 0] == tilt[0]


def air_margin_gust(speed_m_s):
    return Gust(speed_m_s, 2.0, 40.0)


@pytest.fixture
def still_spec(paper_spec):
    """The case study's hexagon held still."""
    spec = copy.deepcopy(paper_spec)
    spec["formation"]["rate_rad_s"] = 0.0
    return spec


def test_margins_shrink_as_the_wind_grows(still_spec):
    times = np.arange(0.0, 30.0, 0.1)
    speed, tilt = [], []
    for w in range(0, 26, 2):
        plan = plan_from_dict({**still_spec, "wind": {"speed_m_s": float(w), "from_deg": 30.0}}, "still.toml")
        d = plan.design_demand(times)
        speed.append(d.rotor_speed_margin_pct(plan.airframe).min())
        tilt.append(d.tilt_margin_rad(plan.airframe).min())
    assert np.all(np.diff(speed) < 0) and np.all(np.diff(tilt) < 0), (speed, tilt)
    calm = plan_from_dict(still_spec, "still.toml").design_demand(times)  # no air: the paper's model
    assert calm.tilt_margin_rad(plan.airframe).min() == pytest.approx(tilt[0], abs=1e-9)




STILL = [("rate_rad_s = 1.0", "rate_rad_s = 0.0")]


def with_wind(table):
    return [("thrust_adaptation_rate_1_s = 3.0\n", "thrust_adaptation_rate_1_s = 3.0\n\n[wind]\n" + table)]


@pytest.mark.parametrize("extra,limit", [
    ([], "a rotor tilted"),  # the case study, circling
    (STILL + [("[leader]", "[airframe]\nmax_rotor_speed_rad_s = 420.0\n\n[leader]")], "a rotor at"),
], ids=["tilt", "thrust"])
def test_a_plan_that_passes_in_calm_air_is_refused_in_a_strong_design_wind(tmp_path, extra, limit):
    calm = paper_plan_variant(tmp_path, extra)
    r = plan_check(calm, "--no-simulate", "--json")
    assert r.returncode == 0, r.stderr
    path = paper_plan_variant(tmp_path, with_wind("speed_m_s = 14.0\nturbulence = \"moderate\"\n") + extra)
    r = plan_check(path, "--no-simulate")
    assert r.returncode == 2 and r.stdout == "", (r.stdout, r.stderr)
    line, = r.stderr.splitlines()
    assert line.startswith(f"triswarm: error: {path}: drone ") and f"needs {limit}" in line
    assert " at t = " in line and "in its design air (a steady 14 m/s from 0 deg" in line
    assert "3 sigma of its turbulence" in line and "in still air it would leave" in line
    what = "check.rotor_speed_margin_pct" if limit == "a rotor at" else "check.tilt_margin_deg"
    assert f"short of the 10{' %' if 'rotor' in what else ' deg'} {what}".replace(" %", "%") in line


def test_plan_check_reports_the_margins(tmp_path):
    path = paper_plan_variant(tmp_path, STILL + with_wind("speed_m_s = 8.0\nturbulence = \"light\"\n"))
    r = plan_check(path, "--no-simulate", "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    air, rows = summary["design_air"], summary["actuators"]
    assert air["tilt_margin_deg"] == min(row["tilt_margin_deg"] for row in rows) >= air["required_tilt_margin_deg"] == 10
    assert air["rotor_speed_margin_pct"] == min(row["rotor_speed_margin_pct"] for row in rows) >= 10
    for row in rows:
        assert row["tilt_margin_deg"] == pytest.approx(row["servo_range_deg"] - row["tilt_max_deg"], abs=0.02)
        assert row["rotor_speed_margin_pct"] == pytest.approx(
            100.0 * (1.0 - row["rotor_speed_rpm"][1] / row["motor_limit_rpm"]), abs=0.02)
    assert "3 sigma of its turbulence" in air["air"] and air["largest_steady_wind_m_s"] is None


def test_largest_steady_wind_holds_from_every_direction_and_one_step_more_does_not(still_spec):
    plan = plan_from_dict({**still_spec, "wind": {"speed_m_s": 0.0}}, "p.toml")
    times = np.arange(0.0, 30.0, 0.1)
    largest = air_margin.largest_steady_wind_m_s(plan.rfl, plan.leader, plan.formation, times, plan.wind, 3.0, 10.0, 10.0)
    assert 10.0 < largest < 64.0

    def problems(speed):
        return [plan_from_dict({**still_spec, "wind": {"speed_m_s": speed, "from_deg": float(d)}}, "p.toml")
                .margin_problem(29.95) for d in air_margin.STEADY_WIND_DIRECTIONS_DEG]
    assert problems(largest) == [None] * len(air_margin.STEADY_WIND_DIRECTIONS_DEG)
    assert any(p is not None for p in problems(largest + 0.1))


def test_required_margins_are_check_settings(still_spec):
    spec = {**still_spec, "wind": {"speed_m_s": 14.0}}
    plan = plan_from_dict(spec, "p.toml")
    tilt = np.degrees(plan.design_demand(np.arange(0.0, 30.0, 0.1)).tilt_margin_rad(plan.airframe).min())
    assert plan.margin_problem(30.0) is None
    spec["check"] = {**spec.get("check", {}), "tilt_margin_deg": float(tilt) + 0.5}
    problem = plan_from_dict(spec, "p.toml").margin_problem(30.0)
    assert problem is not None and f"0.5 deg short of the {tilt + 0.5:g} deg check.tilt_margin_deg" in problem
    with pytest.raises(PlanError, match="check.turbulence_sigmas must not be negative|check.turbulence_sigmas"):
        plan_from_dict({**spec, "check": {"turbulence_sigmas": -1.0}}, "p.toml")


def test_the_flight_of_plan_check_is_flown_in_the_plans_air(still_spec):
    plan = plan_from_dict({**still_spec, "wind": {"speed_m_s": 5.0, "from_deg": 270.0}}, "p.toml")
    flight = plan_flight.fly(plan, 1.0)
    assert flight.wind == plan.wind and flight.summary()["wind"]["speed_m_s"] == 5.0
    assert plan_flight.fly(plan_from_dict(still_spec, "p.toml"), 1.0).summary()["wind"] is None
