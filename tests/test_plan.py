"""Plan files: the paper scenario, and every kind of bad input refused with one sentence."""

import copy

import numpy as np
import pytest

from triswarm.gcs.scenarios import builtin_names, load_plan
from triswarm.protocol.plan import PlanError, in_flight_change_problem, plan_from_dict
from triswarm.protocol.wind import Wind


def test_paper_plan_is_the_papers_case_study(paper_plan):
    assert paper_plan.n_agents == 6
    x0, x0_dot = paper_plan.leader_state(0.0)
    assert np.allclose(x0[9:12], [5, -5, 0]) and np.allclose(x0[:9], 0) and np.allclose(x0_dot, 0)
    ref, _ = paper_plan.reference(0.0)
    assert np.allclose(ref[:, 11], 20.0)
    assert np.allclose(np.linalg.norm(ref[:, 9:11] - [5, -5], axis=1), 10.0)
    assert np.allclose(ref[:, 6:9], [[-0.5 * (-1) ** i, -0.5 * (-1) ** i, 0.5 * (-1) ** i] for i in range(1, 7)])
    assert paper_plan.schedule.period_s == 5.0
    paper_plan.check(horizon_s=60)


def test_builtin_scenario_is_the_example_file(paper_spec):
    assert "paper-hexagon" in builtin_names()
    assert load_plan("paper-hexagon").spec == paper_spec


def test_plan_resizes_for_another_number_of_drones(paper_plan):
    p = paper_plan.with_agents(12)
    assert p.n_agents == 12 and p.schedule.n_agents == 12
    p.check(horizon_s=10)


def spec_with(paper_spec, path, value):
    spec = copy.deepcopy(paper_spec)
    node = spec
    for key in path[:-1]:
        node = node.setdefault(key, {})
    node[path[-1]] = value
    return spec


@pytest.mark.parametrize("path,value,message", [
    (("airframe", "mass_kg"), -0.5, r"\[airframe\] airframe parameter mass_kg must be positive, got -0.5"),
    (("airframe", "mass_kg"), float("nan"), r"airframe.mass_kg must be a finite number, got nan"),
    (("formation", "radius_m"), float("nan"), r"formation.radius_m must be a finite number"),
    (("formation", "altitude_m"), "high", r"formation.altitude_m must be a finite number, got 'high'"),
    (("formation", "type"), "spiral", r"formation.type must be"),
    (("formation", "colour"), "red", r"formation.colour is not a known field"),
    (("drones",), 0, r"drones must be a whole number of at least 1"),
    (("leader", "position_m"), [1.0, 2.0], r"leader.position_m must have shape"),
    (("design", "R_diag"), [1e-6, 1e-6, 1e-6, 1e-6, 1e-6, -1.0], r"design weight R must be positive definite"),
    (("design", "coupling_margin"), 0.5, r"coupling margin must be a number >= 1 so that \(91\) holds"),
    (("topology", "families"), ["ring"], r"unknown family 'ring'"),
    (("topology", "switch_period_s"), 0.0, r"topology.switch_period_s must be positive"),
    (("entry", "blend_s"), -1.0, r"entry.blend_s must be positive"),
    (("controller", "rate_hz"), float("inf"), r"controller.rate_hz must be a finite number"),
    (("controller", "accelerometer"), 1, r"controller.accelerometer must be true or false, got 1"),
    (("design", "R_bar_accel_diag"), [0.01, 0.0, 0.01], r"design weight R_bar_accel must be 3 positive numbers"),
    (("controller", "air_density_kg_m3"), -1.2, r"controller.air_density_kg_m3 must not be negative, got -1.2"),
    (("controller", "latency_s"), -0.01, r"controller.latency_s must not be negative, got -0.01"),
    (("controller", "latency_s"), 2.0, r"controller.latency_s must be at most 1 s, got 2"),
    (("wind", "speed_m_s"), -4.0, r"wind.speed_m_s must not be negative, got -4.0"),
    (("wind", "turbulence"), "gale", r"wind.turbulence must be none, light, moderate, severe or sigma_w in m/s"),
    (("wind", "gusts"), [{"speed_m_s": 3.0, "duration_s": 2.0}], r"wind.gusts\[0\].start_s is required"),
    (("wind",), 5.0, r"\[wind\] must be a table"),
])
def test_bad_plan_fields_are_refused_with_one_sentence(paper_spec, path, value, message):
    with pytest.raises(PlanError, match=message) as exc:
        plan_from_dict(spec_with(paper_spec, path, value), "my.toml")
    text = str(exc.value)
    assert text.startswith("my.toml: ") and "\n" not in text


def test_graph_without_path_from_leader_is_refused(paper_spec):
    spec = copy.deepcopy(paper_spec)
    spec["topology"] = {"switch_period_s": 5.0, "graphs": [
        {"name": "broken", "pinned": [1], "edges": [[1, 2], [2, 3], [4, 5], [5, 6]]}]}
    with pytest.raises(PlanError, match=r"my.toml: \[topology\] topology broken violates Assumption 1: no directed path from the leader to agents 4, 5, 6"):
        plan_from_dict(spec, "my.toml")


def test_infeasible_formation_is_refused_naming_the_drone(paper_spec):
    spec = copy.deepcopy(paper_spec)
    offsets = [[0.0] * 9 + [float(i), 0.0, 10.0] for i in range(6)]
    offsets[3][0] = 1.5  # drone 4 asks for 1.5 m/s while its position offset stays constant
    spec["formation"] = {"type": "constant", "offsets": offsets}
    plan = plan_from_dict(spec, "my.toml")
    with pytest.raises(PlanError, match=r"my.toml: formation fails the feasibility condition \(76\): drone 4 position rows 10-12"):
        plan.check(horizon_s=5)


def test_actuator_demand_of_the_case_study_is_the_erratas(paper_plan):
    """errata: on the exact reference (x = x0 + h_i(t), v = gamma_i) some rotor of every drone
    tilts to about 90-91 deg once per revolution, and rotor speeds range from about 124 to 486 rad/s."""
    revolution = 2.0 * np.pi  # [s] at 1 rad/s
    d = paper_plan.actuator_demand(np.arange(30.0, 30.0 + 2.0 * revolution, 0.01))
    assert d.omega_min_rad_s.min() == pytest.approx(124.0, abs=1.0)
    assert d.omega_max_rad_s.max() == pytest.approx(486.0, abs=1.0)
    for half in (d.tilt_max_rad[: d.times_s.size // 2], d.tilt_max_rad[d.times_s.size // 2:]):
        peak_deg = np.degrees(half.max(axis=0))  # each revolution, each drone
        assert np.all((peak_deg > 90.0) & (peak_deg < 91.5)), peak_deg


def test_actuator_demand_of_a_still_level_formation_is_hover(paper_spec):
    """errata: hovering level, each rotor turns at 288.38 rad/s tilted 3.637 deg."""
    spec = copy.deepcopy(paper_spec)
    spec["formation"] = {"type": "constant", "offsets": [[0.0] * 9 + [3.0 * i, 0.0, 10.0] for i in range(6)]}
    d = plan_from_dict(spec, "still.toml").actuator_demand(np.arange(0.0, 2.0, 0.5))
    for series in (d.omega_min_rad_s, d.omega_max_rad_s):
        assert series == pytest.approx(np.full((4, 6), 288.38), abs=0.01)
    assert np.degrees(d.tilt_max_rad) == pytest.approx(np.full((4, 6), 3.637), abs=0.001)


@pytest.mark.parametrize("field,limit,refused", [
    ("max_rotor_speed_rad_s", 487.0, None),  # the case study peaks at 486.4 rad/s (4645 RPM)
    ("max_rotor_speed_rad_s", 485.0, r"drone 1 needs a rotor at 4645 RPM, past the motor limit \(4631 RPM\) from t = "),
    ("servo_limit_rad", np.radians(91.5), None),  # its drones tilt up to 90.2 and 91.2 deg
    ("servo_limit_rad", np.radians(90.5), r"drone 2 needs a rotor tilted 91.2 deg, past the servo range \(\+-90.5 deg\)"),
])
def test_check_refuses_a_formation_past_the_motor_limit_or_the_servo_range(paper_spec, field, limit, refused):
    plan = plan_from_dict(spec_with(paper_spec, ("airframe", field), float(limit)), "my.toml")
    if refused is None:
        plan.check_formation(horizon_s=20)  # (the margins plan check keeps for the feedback: test_air_margin)
    else:
        with pytest.raises(PlanError, match="my.toml: formation cannot be flown: " + refused):
            plan.check(horizon_s=20)


def test_check_refuses_a_formation_pitched_past_the_controllers_limit(paper_spec):
    """The RFL's M(x) is singular at pitch 90 deg (errata); the controller stops at 1.4 rad."""
    spec = copy.deepcopy(paper_spec)
    spec["formation"]["attitude_rad"] = [[0.0, 0.3, 0.0]] * 5 + [[0.0, -1.45, 0.0]]
    with pytest.raises(PlanError, match=r"my.toml: formation cannot be flown: drone 6 needs a pitch of 83.1 deg, "
                                        r"past the controller's limit \(80.2 deg\) from t = 0 s"):
        plan_from_dict(spec, "my.toml").check(horizon_s=10)


def test_keyframe_plan(paper_spec):
    spec = copy.deepcopy(paper_spec)
    spec["formation"] = {"type": "keyframes", "keyframes": [
        {"t_s": 0.0, "position_m": [[i * 3.0, 0.0, 10.0] for i in range(6)]},
        {"t_s": 20.0, "position_m": [[0.0, i * 3.0, 12.0] for i in range(6)], "attitude_rad": [0.0, 0.0, 0.5]},
    ]}
    plan = plan_from_dict(spec, "k.toml")
    plan.check(horizon_s=30)
    assert np.allclose(plan.formation.offsets(25.0)[0][:, 9:12], [[0.0, i * 3.0, 12.0] for i in range(6)])


@pytest.mark.parametrize("n", [7, 50, 200, 1000])
def test_resized_polygon_keeps_its_neighbours_apart_at_the_same_speed(paper_plan, n):
    """--drones N: neighbours 1.5 minimum separations (2.76 m) apart, the tangential speed of the
    case study (10 m/s), a blend long enough to keep its peak acceleration, the ring trees."""
    p = paper_plan.with_agents(n)
    ref, _ = p.reference(30.0)
    pos = ref[:, 9:12]
    gaps = np.linalg.norm(pos - np.roll(pos, -1, axis=0), axis=1)
    spacing = 1.5 * 8 * paper_plan.airframe.arm_length_m
    assert gaps == pytest.approx(np.full(n, max(spacing, 2 * 10.0 * np.sin(np.pi / n))))
    assert np.linalg.norm(ref[:, 0:3], axis=1) == pytest.approx(np.full(n, 10.0))  # |velocity| = R w
    R = p.formation.radius_m
    assert p.entry.blend_s == pytest.approx(12.0 * np.sqrt(max(R, 10.0) / 10.0), abs=0.1)
    assert [t.name for t in p.schedule.topologies] == ["ring-tree", "ring-tree-left", "ring-tree-right"]
    assert p.duration_s >= p.settled_from_s + 20.0 and p.duration_s == int(p.duration_s)
    if n <= 200:
        p.check()


def test_resizing_keeps_the_families_a_plan_names(paper_spec):
    spec = copy.deepcopy(paper_spec)
    spec["topology"]["families"] = ["two-chain", "triangles", "reverse-two-chain"]
    p = plan_from_dict(spec, "named.toml").with_agents(50)
    assert [t.name for t in p.schedule.topologies] == ["two-chain", "triangles", "reverse-two-chain"]
    with pytest.raises(PlanError, match=r"^named.toml: topology schedule cannot be certified: switching every 5 s "
                                        r"between two-chain, triangles, reverse-two-chain lets the bound on the "
                                        r"formation error grow [0-9.e+]+x per cycle; "):
        p.check()


def test_drones_too_close_along_the_reference_are_refused(paper_spec):
    """A hexagon's side is its radius: 1.5 m, under the 1.84 m default (8 arm lengths)."""
    spec = spec_with(paper_spec, ("formation", "radius_m"), 1.5)
    with pytest.raises(PlanError, match=r"^tight.toml: drones 1 and [26] come within 1.50 m of each other at t = 0 s along "
                                        r"the reference, closer than the minimum separation 1.84 m \(check.min_separation_m\)$"):
        plan_from_dict(spec, "tight.toml").check()
    spec["check"] = {"min_separation_m": 1.4}
    plan_from_dict(spec, "tight.toml").check()


def test_plan_length_and_settled_window(paper_spec):
    plan = plan_from_dict(paper_spec, "p.toml")
    assert plan.duration_s == 60.0 and plan.settled_from_s == 25.0  # the paper's [25 s, 50 s] and on
    with pytest.raises(PlanError, match=r"duration_s \(20 s\) must be longer than the entry and its settling "
                                        r"\(entry.climb_s \+ entry.blend_s \+ check.settle_s = 25 s\)"):
        plan_from_dict(spec_with(paper_spec, ("duration_s",), 20.0), "p.toml")
    longer = plan_from_dict(spec_with(paper_spec, ("entry", "blend_s"), 40.0), "p.toml")
    assert longer.settled_from_s == 53.0 and longer.duration_s == 73.0


def test_the_controllers_know_the_air_the_plan_is_flown_in(paper_spec):
    """No air (no [wind], none given): no drag term, the paper's law. In air (the plan's [wind], or a
    simulation's): ISA sea level, or the plan's [controller] air_density_kg_m3 wherever it flies."""
    plain = plan_from_dict(paper_spec)
    assert plain.controller_air_density_kg_m3(None) == 0.0
    assert plain.controller_air_density_kg_m3(Wind()) == 1.225
    windy = plan_from_dict(spec_with(paper_spec, ("wind", "speed_m_s"), 3.0))
    assert windy.controller_air_density_kg_m3(windy.wind) == 1.225
    high = plan_from_dict(spec_with(paper_spec, ("controller", "air_density_kg_m3"), 1.0))
    assert high.controller_air_density_kg_m3(None) == high.controller_air_density_kg_m3(Wind()) == 1.0
    off = plan_from_dict(spec_with(paper_spec, ("controller", "air_density_kg_m3"), 0))
    assert off.controller_air_density_kg_m3(Wind(speed_m_s=5.0)) == 0.0


def test_in_flight_a_plan_may_not_say_otherwise_about_the_air(paper_spec):
    windy = spec_with(paper_spec, ("wind", "speed_m_s"), 3.0)
    assert in_flight_change_problem(windy, spec_with(paper_spec, ("wind", "speed_m_s"), 6.0)) is None
    assert "may not add or remove [wind]" in in_flight_change_problem(paper_spec, windy)
    assert "may not add or remove [wind]" in in_flight_change_problem(windy, paper_spec)
    fixed = spec_with(paper_spec, ("controller", "air_density_kg_m3"), 1.225)
    assert in_flight_change_problem(fixed, spec_with(fixed, ("wind", "speed_m_s"), 3.0)) is None


def test_one_verdict_judges_each_plan_over_its_own_settled_window(paper_spec):
    """sim, plot and demo judge with ``metrics.judge``: over the plan's settled window (its entry's
    end plus check.settle_s), the second half of a flight too short for it. A drone 0.2 m off its
    place only before a plan's window is within the bounds; the same drone judged from 25 s with a
    longer entry's plan (window from 53 s) is off."""
    from triswarm.protocol import metrics

    longer = plan_from_dict(spec_with(paper_spec, ("entry", "blend_s"), 40.0), "p.toml")
    t_s = np.arange(0.0, longer.duration_s + 1e-9, 0.5)
    ref = np.stack([longer.reference(float(t))[0] for t in t_s])
    position_m, euler_rad = ref[:, :, 9:12].copy(), ref[:, :, 6:9].copy()
    position_m[t_s < 50.0, 2, 0] += 0.2  # drone 3, before the window only
    perf, rows = metrics.judge(longer, t_s, position_m, euler_rad)
    assert perf.window_start_s == 53.0 and perf.within_bounds and all(r["within_bounds"] for r in rows)
    assert rows[2]["worst_position_error_m"] == pytest.approx(0.0, abs=1e-9)
    perf, rows = metrics.judge(longer, t_s, position_m, euler_rad, window_start_s=25.0)
    assert not perf.within_bounds and [r["drone"] for r in rows if not r["within_bounds"]] == [3]
    assert rows[2]["worst_position_error_m"] == pytest.approx(0.2)
    assert metrics.settled_window_start_s(longer, 40.0) == 20.0  # (too short: its second half)
