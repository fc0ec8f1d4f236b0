"""The per-drone controller: observer discretisation, delay predictor, one code path for N = 1 and N."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from triswarm.protocol import model
from triswarm.protocol.agent import protocol_input
from triswarm.protocol.controller import FormationController, _zoh_foh
from triswarm.sitl.physics import Plant


def test_first_order_hold_discretisation_matches_the_ode(paper_plan, rng):
    d = paper_plan.design
    A, B, C, F = d.observer_model()
    T = 0.005
    Ao, By = A - d.c * F @ C, d.c * F
    Phi, Gv, Gy0, Gy1 = _zoh_foh(Ao, B, By, T)
    z0, v = rng.normal(size=A.shape[0]), rng.normal(size=6)
    y0, y1 = rng.normal(size=6), rng.normal(size=6)
    sol = solve_ivp(lambda t, z: Ao @ z + B @ v + By @ (y0 + (y1 - y0) * t / T), (0, T), z0, rtol=1e-12, atol=1e-12)
    assert np.allclose(sol.y[:, -1], Phi @ z0 + Gv @ v + Gy0 @ y0 + Gy1 @ y1, rtol=1e-8, atol=1e-8)


def hovering_plant(af, n, delay):
    omega, alpha = model.hover_trim(af)
    plant = Plant(af, n, dt_s=1e-3, servo_delay_s=delay)
    plant.reset(np.tile([0.0, 0.0, 20.0], (n, 1)), servo_rad=alpha)
    plant.landed[:] = False
    plant.command(np.tile(omega, (n, 1)), np.tile(alpha, (n, 1)))
    return plant


def test_predictor_gives_the_state_one_servo_delay_ahead(paper_plan, rng):
    """Drive the real plant (servo delay 10 ms) with arbitrary v; the controller's prediction of x_r at
    t + 10 ms must be what the plant then does."""
    d = paper_plan.design
    af = paper_plan.airframe
    plant = hovering_plant(af, 1, af.servo_delay_s)
    ctrl = FormationController(d, 1, 200.0)
    ctrl.reset(plant.observe().paper_state())
    assert ctrl.lead_ticks == 2 and ctrl.lead_s == pytest.approx(0.01)
    freqs, phases = rng.uniform(2.0, 6.0, 6), rng.uniform(0, 2 * np.pi, 6)  # ~0.2 rad of attitude swing
    predicted, actual = {}, {}
    for k in range(600):
        obs = plant.observe()
        actual[k] = paper_plan.rfl.phi_r(obs.paper_state())[0]
        predicted[k + ctrl.lead_ticks] = ctrl.observe(np.concatenate([obs.euler_rad, obs.position_m], axis=1))[0]
        v = 500.0 * np.sin(freqs * k * 0.005 + phases)
        act = ctrl.actuate(v[None, :])
        plant.command(act.omega_rad_s, act.alpha_rad)
        plant.advance(5)
    err = np.array([predicted[k] - actual[k] for k in range(100, 600)])
    scale = np.abs(np.array([actual[k] for k in range(100, 600)])).max(axis=0) + 1e-3
    rel = np.abs(err).max(axis=0) / scale
    assert np.all(rel < 5e-4), rel  # measured: below 6e-5 on every row
    assert np.abs(err[:, 9:12]).max() < 1e-4  # position predicted within 0.1 mm


def test_batch_and_single_agent_controllers_agree(paper_plan, rng):
    """One code path: N agents at once give the same commands as N controllers with N = 1."""
    d = paper_plan.design
    n = 6
    x = np.zeros((n, 12))
    x[:, 9:12] = rng.uniform(-3, 3, (n, 3))
    batch = FormationController(d, n)
    singles = [FormationController(d, 1) for _ in range(n)]
    batch.reset(x)
    for i, s in enumerate(singles):
        s.reset(x[i:i + 1])
    topo = paper_plan.schedule.topologies[1]
    x0 = np.zeros(12)
    for _ in range(20):
        y = x[:, 6:12] + rng.normal(0, 0.01, (n, 6))
        xi_b = batch.observe(y)
        xi_s = np.vstack([s.observe(y[i:i + 1]) for i, s in enumerate(singles)])
        assert np.allclose(xi_b, xi_s, atol=1e-9)
        gamma = rng.normal(0, 100, (n, 6))
        v_b = protocol_input(d, xi_b, topo.adjacency @ xi_b, topo.in_degree, topo.pinning, x0, gamma)
        v_s = np.vstack([protocol_input(d, xi_s[i:i + 1], (topo.adjacency[i] @ xi_s)[None, :], topo.in_degree[i:i + 1],
                                        topo.pinning[i:i + 1], x0, gamma[i:i + 1]) for i in range(n)])
        assert np.allclose(v_b, v_s)
        a_b = batch.actuate(v_b)
        a_s = [s.actuate(v_s[i:i + 1]) for i, s in enumerate(singles)]
        assert np.allclose(a_b.omega_rad_s, np.vstack([a.omega_rad_s for a in a_s]))
        assert np.allclose(a_b.alpha_rad, np.vstack([a.alpha_rad for a in a_s]))


def test_missing_measurements_do_not_poison_the_estimate(paper_plan):
    d = paper_plan.design
    ctrl = FormationController(d, 2)
    x = np.zeros((2, 12))
    x[:, 11] = 10.0
    ctrl.reset(x)
    y = x[:, 6:12].copy()
    for k in range(10):
        yk = y.copy()
        if k in (3, 4):
            yk[1] = np.nan
        est = ctrl.observe(yk)
        assert np.all(np.isfinite(est))
        act = ctrl.actuate(np.zeros((2, 6)))
        assert np.all(np.isfinite(act.omega_rad_s)) and np.all(np.isfinite(act.alpha_rad))
    assert np.abs(est[:, 9:12] - x[:, 9:12]).max() < 1e-3
