"""Formation offsets: the derivatives are exact (finite differences), and shapes are what they say."""

import numpy as np
import pytest

from triswarm.protocol.airframe import ParameterError
from triswarm.protocol.formation import (Blend, ConstantFormation, EntryBlend, KeyframeFormation, QuinticTransfer,
                                         RelativeTo, Rejoin, RotatingPolygon, Row, Shifted, quintic_blend,
                                         rejoin_duration)
from triswarm.protocol.plan import plan_from_dict


def assert_exact_derivative(formation, times, h=1e-5, tol=1e-6):
    for t in times:
        hp, _ = formation.offsets(t + h)
        hm, _ = formation.offsets(t - h)
        _, hd = formation.offsets(t)
        assert np.allclose((hp - hm) / (2 * h), hd, atol=tol), t


def keyframes():
    shapes = np.array([
        [[0, 0, 10], [4, 0, 10], [8, 0, 10]],
        [[0, 0, 10], [2, 3, 12], [4, 0, 14]],
        [[-5, 0, 5], [0, 5, 5], [5, 0, 5]],
    ], dtype=float)
    att = np.zeros_like(shapes)
    att[1, :, 2] = 0.8
    return KeyframeFormation(np.array([2.0, 8.0, 15.0]), shapes, att)


@pytest.mark.parametrize("make", [
    lambda: RotatingPolygon.paper(6),
    lambda: RotatingPolygon(7, 4.0, 12.0, -0.6, np.tile([0.1, -0.2, 0.3], (7, 1)), 0.4),
    keyframes,
    lambda: EntryBlend(RotatingPolygon.paper(6), np.tile([1.0, -2.0, 0.0], (6, 1)), np.zeros(3), 1.0, 9.0),
    lambda: ConstantFormation(np.ones((4, 3)), np.zeros((4, 3))),
    lambda: QuinticTransfer([[1, 2, 3]], [[10, -4, 1]], [[6, 0, 0]], [[0.5, -0.5, 1]], [[0, 0.3, 0]], [[0, 0, 1]], 2.0, 4.0),
    lambda: Rejoin(braking_from_polygon(3.0), RotatingPolygon.paper(6), 4.0, 6.0),
])
def test_offsets_have_exact_derivatives(make):
    assert_exact_derivative(make(), np.linspace(0.3, 19.7, 60))


def test_rotating_polygon_geometry():
    f = RotatingPolygon(5, 3.0, 7.0, 0.5, np.zeros((5, 3)))
    for t in (0.0, 2.0):
        p = f.kinematics(t).p
        assert np.allclose(np.linalg.norm(p[:, :2], axis=1), 3.0)
        assert np.allclose(p[:, 2], 7.0)
        ang = np.arctan2(p[:, 0], p[:, 1])  # phase measured as in [R sin, R cos]
        assert np.allclose(np.mod(np.diff(ang), 2 * np.pi), 2 * np.pi / 5)
        assert ang[0] == pytest.approx(0.5 * t)


def test_keyframes_pass_through_the_shapes_and_hold_outside():
    f = keyframes()
    for k, t in enumerate(f.times_s):
        kin = f.kinematics(t)
        assert np.allclose(kin.p, f.positions_m[k]) and np.allclose(kin.eta, f.attitudes_rad[k])
    for t in (0.0, 1.0, 20.0):
        kin = f.kinematics(t)
        assert np.allclose(kin.p_dot, 0) and np.allclose(kin.p_ddot, 0)
    assert np.allclose(f.kinematics(0.0).p, f.positions_m[0])
    assert np.allclose(f.kinematics(30.0).p, f.positions_m[-1])


def test_entry_blend_starts_at_the_start_and_ends_on_the_target():
    target = RotatingPolygon.paper(6)
    start = np.random.default_rng(0).uniform(-3, 3, (6, 3))
    f = EntryBlend(target, start, np.zeros(3), 2.0, 10.0)
    h0, hd0 = f.offsets(2.0)
    assert np.allclose(h0[:, 9:12], start) and np.allclose(h0[:, 6:9], 0) and np.allclose(hd0, 0)
    for t in (12.0, 20.0):
        assert np.allclose(f.offsets(t)[0], target.offsets(t)[0])
        assert np.allclose(f.offsets(t)[1], target.offsets(t)[1])


def test_quintic_blend_is_rest_to_rest():
    assert quintic_blend(0.0) == (0.0, 0.0, 0.0) and quintic_blend(1.0) == (1.0, 0.0, 0.0)
    s, ds, dds = quintic_blend(0.5)
    assert s == pytest.approx(0.5) and ds == pytest.approx(1.875) and dds == pytest.approx(0.0)


@pytest.mark.parametrize("kwargs,msg", [
    (dict(radius_m=float("nan")), "radius_m must be a finite"),
    (dict(radius_m=-1.0), "must not be negative"),
    (dict(attitude_rad=np.zeros((2, 3))), "one triple per agent"),
])
def test_bad_formation_parameters_are_refused(kwargs, msg):
    base = dict(n_agents=3, radius_m=1.0, altitude_m=5.0, rate_rad_s=1.0, attitude_rad=np.zeros((3, 3)))
    base.update(kwargs)
    with pytest.raises(ParameterError, match=msg):
        RotatingPolygon(**base)


def test_quintic_transfer_matches_its_boundary_conditions():
    f = QuinticTransfer([[1, 2, 3]], [[10, -4, 1]], [[6, 0, 0]], [[0.5, -0.5, 1]], [[0, 0.3, 0]], [[0, 0, 1]], 2.0, 4.0)
    k0, k1 = f.kinematics(2.0), f.kinematics(6.0)
    assert np.allclose(k0.p, [[1, 2, 3]]) and np.allclose(k0.p_dot, [[10, -4, 1]]) and np.allclose(k0.p_ddot, 0)
    assert np.allclose(k0.eta_dot, [[0, 0.3, 0]])
    assert np.allclose(k1.p, [[6, 0, 0]]) and np.allclose(k1.p_dot, 0) and np.allclose(k1.p_ddot, 0, atol=1e-12)
    assert np.allclose(f.kinematics(9.0).p, [[6, 0, 0]]) and np.allclose(f.kinematics(9.0).eta, [[0, 0, 1]])


def braking_from_polygon(t0: float, n: int = 6) -> QuinticTransfer:
    """Every agent of the paper's polygon braking to a stop from t0 (10 m/s tangential), as offsets."""
    k = RotatingPolygon.paper(n).kinematics(t0)
    stop = k.p + k.p_dot * 2.5
    return QuinticTransfer(k.p, k.p_dot, stop, k.eta, k.eta_dot, k.eta, t0, 5.0)


def test_rejoin_continues_the_source_and_ends_on_the_target():
    target = RotatingPolygon.paper(6)
    source = braking_from_polygon(3.0)
    f = Rejoin(source, target, 4.0, 6.0)
    a, b = f.kinematics(4.0), source.kinematics(4.0)
    for name in ("p", "p_dot", "p_ddot", "eta", "eta_dot", "eta_ddot"):  # (no step even in acceleration)
        assert np.allclose(getattr(a, name), getattr(b, name), atol=1e-9), name
    assert np.abs(source.kinematics(4.0).p_ddot - target.kinematics(4.0).p_ddot).max() > 1.0  # (there was one to avoid)
    for name in ("p", "p_dot", "p_ddot", "eta", "eta_dot", "eta_ddot"):
        assert np.allclose(getattr(f.kinematics(10.0), name), getattr(target.kinematics(10.0), name), atol=1e-9), name
    assert np.allclose(f.kinematics(3.5).p, source.kinematics(3.5).p)  # the source before t0
    assert np.allclose(f.kinematics(12.0).p, target.kinematics(12.0).p)


def test_a_short_hold_costs_a_short_excursion():
    """Braking for 0.1 s from 10 m/s on a 10 m circle, then back: 1 m/s off the formation's velocity
    and the formation's 10 m/s^2 turn away in acceleration, so the way back strays at most
    dp + 0.198 dv T + 0.0173 da T^2 over T = 1 s (the quintic's peaks for each initial error alone,
    in closed form: under half a metre), where a blend that follows the source (which goes on
    braking) strays metres away."""
    target = RotatingPolygon.paper(6)
    source = braking_from_polygon(3.0)
    t = np.linspace(3.1, 9.1, 601)
    rejoin = Rejoin(source, target, 3.1, 1.0)
    dp, dv = (np.linalg.norm(e, axis=1).max() for e in rejoin.initial_error)
    da = np.linalg.norm(source.kinematics(3.1).p_ddot - target.kinematics(3.1).p_ddot, axis=1).max()
    assert dp < 0.06 and 0.9 < dv < 1.1 and 5.0 < da < 15.0
    away = lambda f: max(np.linalg.norm(f.kinematics(x).p - target.kinematics(x).p, axis=1).max() for x in t)  # noqa: E731
    assert away(rejoin) <= dp + 0.198 * dv + 0.0173 * da + 1e-6 < 0.5
    assert away(Blend(source, target, 3.1, 6.0)) > 3.0


@pytest.mark.parametrize("dp, dv", [(0.0, 1.0), (1.0, 0.0), (15.0, 10.0), (0.01, 0.01)])
def test_rejoin_duration_bounds_the_peak_acceleration(dp, dv):
    T = rejoin_duration(dp, dv, accel_m_s2=4.0, min_s=1.0)
    rejoin = Rejoin(QuinticTransfer([[dp, 0, 0]], [[dv, 0, 0]], [[dp, 0, 0]], [[0, 0, 0]], [[0, 0, 0]], [[0, 0, 0]], 0, 1e-3),
                    ConstantFormation(np.zeros((1, 3)), np.zeros((1, 3))), 0.0, T)
    peak = max(abs(rejoin.kinematics(x).p_ddot[0, 0]) for x in np.linspace(0, T, 2001))
    assert T >= 1.0 and peak <= 4.0 * 1.6  # each error alone within the limit; together within 60 % of it
    if max(dp, dv) > 0.5:
        assert peak >= 4.0 * 0.9  # and no slower than needed


def test_rejoin_relative_to_a_moving_leader():
    """An absolute hold written relative to a leader, then rejoined: still continuous."""
    leader = QuinticTransfer([[5, -5, 0]], [[1, 0, 0]], [[9, -5, 0]], [[0, 0, 0]], [[0, 0, 0]], [[0, 0, 0]], 0.0, 8.0)
    hold = QuinticTransfer(np.tile([[10, 0, 20]], (6, 1)), np.tile([[0, 3, 0]], (6, 1)), np.tile([[10, 3, 20]], (6, 1)),
                           np.zeros((6, 3)), np.zeros((6, 3)), np.zeros((6, 3)), 1.0, 2.0)
    f = Rejoin(RelativeTo(hold, leader), RotatingPolygon.paper(6), 2.0, 5.0)
    assert_exact_derivative(f, np.linspace(1.53, 7.53, 25))
    assert np.allclose(f.kinematics(2.0).p, hold.kinematics(2.0).p - leader.kinematics(2.0).p)


def test_offsets_fast_paths_equal_the_kinematics(paper_plan):
    """The rotating polygon and the blends write h, h_dot directly in the control loop; they must be
    exactly what the kinematics give."""
    from triswarm.protocol.formation import Formation

    start = np.array([[1.0, 2.0, 0.0]] * 6) + np.arange(6)[:, None]
    entry = paper_plan.entry_formation(start, 0.0)
    for t in (0.0, 1.3, 3.0, 7.7, 14.9, 15.0, 40.2):
        for f in (paper_plan.formation, entry):
            h, h_dot = f.offsets(t)
            k_h, k_h_dot = Formation.offsets(f, t)  # the base class: kinematics(t).offsets()
            assert np.allclose(h, k_h, rtol=0, atol=1e-12) and np.allclose(h_dot, k_h_dot, rtol=0, atol=1e-12), t


@pytest.mark.parametrize("n", [6, 24])
def test_one_agents_row_flies_the_same_reference_as_the_whole_swarm(paper_spec, n):
    """A companion builds its entry and rejoin on its own Row of the formation: every agent's
    reference is its row of the references built for the whole swarm, through the climb, the blend
    and a rejoin from a braking start."""
    plan = plan_from_dict(paper_spec).with_agents(n) if n != 6 else plan_from_dict(paper_spec)
    rng = np.random.default_rng(1)
    start = np.column_stack([rng.uniform(-20, 20, (n, 2)), np.zeros(n)])
    t0 = 3.0
    whole = plan.entry_formation(start, t0)
    times = np.linspace(t0 - 1.0, t0 + plan.entry.climb_s + plan.entry.blend_s + 2.0, 37)
    brake_whole = QuinticTransfer(start + 1.0, np.ones((n, 3)), start + 3.0, np.zeros((n, 3)), np.zeros((n, 3)),
                                  np.zeros((n, 3)), t0, 4.0)
    rejoin_whole = Rejoin(brake_whole, plan.formation, t0, 6.0)
    for i in (0, n // 2, n - 1):
        mine = plan.entry_formation(start[i:i + 1], t0, Row(plan.formation, i))
        brake_mine = QuinticTransfer(*(a[i:i + 1] for a in (brake_whole.p0, brake_whole.p_dot0, brake_whole.p1,
                                                             brake_whole.eta0, brake_whole.eta_dot0, brake_whole.eta1)),
                                     t0, 4.0)
        rejoin_mine = Rejoin(brake_mine, Row(plan.formation, i), t0, 6.0)
        assert mine.n_agents == rejoin_mine.n_agents == 1
        for t in times:
            for one, all_ in ((mine, whole), (rejoin_mine, rejoin_whole)):
                h, h_dot = one.offsets(t)
                H, H_dot = all_.offsets(t)
                np.testing.assert_allclose(h, H[i:i + 1], rtol=0, atol=1e-12)
                np.testing.assert_allclose(h_dot, H_dot[i:i + 1], rtol=0, atol=1e-12)
            k, K = Row(plan.formation, i).kinematics(t), plan.formation.kinematics(t)
            np.testing.assert_allclose(k.p, K.p[i:i + 1], rtol=0, atol=0)


def test_keyframe_offsets_are_kept_for_the_agents_of_a_process():
    """The agents of one companion process fly rows of one formation at the same instants: the
    offsets of an instant are computed once, read-only, and each row is that row."""
    formation = keyframes()
    for t in (1.0, 5.0, 9.5, 16.0):
        h, h_dot = formation.offsets(t)
        assert formation.offsets(t)[0] is h and not h.flags.writeable and not h_dot.flags.writeable
        np.testing.assert_array_equal(h, formation.kinematics(t).offsets()[0])
        assert Shifted(formation, 2.5).offsets(t + 2.5)[0] is h  # (a plan put in force in flight)
        for i in range(formation.n_agents):
            np.testing.assert_array_equal(Row(formation, i).offsets(t)[1], h_dot[i:i + 1])
