"""The per-drone controller: observer discretisation, delay predictor, the compiled tick against a
numpy reference, one code path for N = 1 and N."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from triswarm.protocol import model
from triswarm.protocol.agent import protocol_input
from triswarm.protocol.controller import FormationController, _zoh_foh
from triswarm.protocol.design import zoh
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


@pytest.mark.parametrize("latency_ticks", [0, 3])
def test_predictor_gives_the_state_one_servo_delay_and_the_latency_ahead(paper_plan, rng, latency_ticks):
    """Drive the real plant (servo delay 10 ms) with arbitrary v, each command reaching it
    ``latency_ticks`` periods after the measurement it answers; the controller, told that latency,
    predicts x_r at t + 10 ms + the latency, and that must be what the plant then does. (With the
    motors held back by the whole lead, not the servo delay alone, a row is 10 % off.)"""
    d = paper_plan.design
    af = paper_plan.airframe
    plant = hovering_plant(af, 1, af.servo_delay_s)
    ctrl = FormationController(d, 1, 200.0, latency_s=latency_ticks * 0.005)
    ctrl.reset(plant.observe().paper_state())
    assert ctrl.lead_ticks == 2 + latency_ticks and ctrl.lead_s == pytest.approx(0.01 + latency_ticks * 0.005)
    freqs, phases = rng.uniform(2.0, 6.0, 6), rng.uniform(0, 2 * np.pi, 6)  # ~0.2 rad of attitude swing
    predicted, actual, sent = {}, {}, []
    for k in range(600):
        obs = plant.observe()
        actual[k] = paper_plan.rfl.phi_r(obs.paper_state())[0]
        predicted[k + ctrl.lead_ticks] = ctrl.observe(np.concatenate([obs.euler_rad, obs.position_m], axis=1))[0]
        v = 500.0 * np.sin(freqs * k * 0.005 + phases)
        sent.append(ctrl.actuate(v[None, :]))
        if k >= latency_ticks:
            plant.command(sent[k - latency_ticks].omega_rad_s, sent[k - latency_ticks].alpha_rad)
        plant.advance(5)
    err = np.array([predicted[k] - actual[k] for k in range(100, 600)])
    scale = np.abs(np.array([actual[k] for k in range(100, 600)])).max(axis=0) + 1e-3
    rel = np.abs(err).max(axis=0) / scale
    assert np.all(rel < 5e-4), rel  # measured: below 6e-5 on every row
    assert np.abs(err[:, 9:12]).max() < 1e-4  # position predicted within 0.1 mm


def within_range(omega, alpha, G, limit, torque_priority=100.0):
    """kernels.allocate_within_range's rule, from its docstring: rotors beyond the servo range held at
    its nearest edge, pushing along it, the others free; the angular rows of w = G rho weighted
    ``torque_priority`` times in the least squares; again while the solution puts another rotor
    beyond. Returns the rotor speeds, the servo angles and which rotors are held."""
    w = G @ model.actuator_map(omega, alpha)
    held = np.zeros(3, dtype=bool)
    weight = np.r_[np.ones(3), np.full(3, torque_priority)]
    while True:
        grew = ~held & (np.abs(alpha) > limit)
        if not grew.any():
            return omega, alpha, held
        held |= grew
        edge = np.sign(alpha) * limit
        columns = []
        for j in range(3):
            if held[j]:
                columns.append(G[:, j] * np.sin(edge[j]) + G[:, j + 3] * np.cos(edge[j]))
            else:
                columns += [G[:, j], G[:, j + 3]]
        p = np.linalg.lstsq(weight[:, None] * np.array(columns).T, weight * w, rcond=None)[0]
        k = 0
        for j in range(3):
            if held[j]:
                omega[j], alpha[j] = np.sqrt(max(p[k], 0.0)), edge[j]
                k += 1
            else:
                omega[j], alpha[j] = np.sqrt(np.hypot(p[k], p[k + 1])), np.arctan2(p[k], p[k + 1])
                k += 2


class NumpyController:
    """One tick of the controller in plain numpy, from the design and protocol/controller.py's
    docstring, not from its kernels: the observer (73) with the disturbance state, discretised
    (ZOH on v, FOH on y), the prediction over the servo delay, the disturbance cancelled, half a
    period on, (49) by linear solve (``RFL.control``) in the estimated wind, the thrust adaptation,
    the wind estimate's step (kernels.update_wind_estimate's docstring), the actuator inverse of
    Remark 1 within the servo range, and the v a drone at the range's edge commits (what its
    rotors deliver)."""

    def __init__(self, design, n, rate_hz, adaptation_rate_1_s, air_density_kg_m3=0.0, wind_estimate_rate_1_s=0.0):
        A, B, C, F = design.observer_model()
        T = 1.0 / rate_hz
        self.Phi, self.Gv, self.Gy0, self.Gy1 = _zoh_foh(A - design.c * F @ C, B, design.c * F, T)
        Phi1, G1 = zoh(A, B, T)
        self.lead = int(round(design.rfl.airframe.servo_delay_s / T))
        self.pred_Phi = np.linalg.matrix_power(Phi1, self.lead)
        self.pred_G = [np.linalg.matrix_power(Phi1, self.lead - 1 - j) @ G1 for j in range(self.lead)]
        self.half_Phi, self.half_G = zoh(A, B, 0.5 * T)
        self.E_inv = np.linalg.inv(design.B_r[0:6])
        self.rfl, self.n, self.adapt_k = design.rfl, n, adaptation_rate_1_s * T
        self.air = air_density_kg_m3
        af = design.rfl.airframe
        self.k_m = 0.5 * air_density_kg_m3 * af.drag_coefficient * af.frontal_area_m2 / af.mass_kg
        self.wind_gain = wind_estimate_rate_1_s * T
        self.G = model.input_matrix(af)

    def reset(self, x):
        self.z = np.hstack([self.rfl.phi_r(x), np.zeros((self.n, 6))])
        self.y_prev, self.fresh, self.kappa = x[:, 6:12].copy(), True, np.ones(self.n)
        self.v_pipe = [np.zeros((self.n, 6))] * self.lead
        self.motor_pipe = [model.actuator_inverse(self.rfl.control(x, np.zeros((self.n, 6)), self.air))[0]] * self.lead
        self.v_applied = np.zeros((self.n, 6))
        self.wind = np.zeros((self.n, 3))

    def observe(self, y):
        if not self.fresh:
            self.z = self.z @ self.Phi.T + self.v_applied @ self.Gv.T + self.y_prev @ self.Gy0.T + y @ self.Gy1.T
        self.fresh, self.y_prev = False, y.copy()
        self.z_pred = self.z @ self.pred_Phi.T + sum(v @ G.T for v, G in zip(self.v_pipe, self.pred_G))
        return self.z_pred[:, :12]

    def actuate(self, v):
        v = v - self.z_pred[:, 12:18] @ self.E_inv.T
        zm = self.z_pred @ self.half_Phi.T + v @ self.half_G.T
        u = self.rfl.control(self.rfl.phi_r_inverse(zm[:, :12]), v, self.air, self.wind)
        thrust = zm[:, :12] @ self.rfl.L[3:6].T + v @ self.rfl.M0[3:6].T + [0.0, 0.0, self.rfl.airframe.gravity_m_s2]
        air_v = zm[:, 0:3] - self.wind
        thrust += self.k_m * np.linalg.norm(air_v, axis=1, keepdims=True) * air_v  # (the drag's share)
        thrust += self.z[:, 12:15]  # (asked before the disturbance estimate is cancelled)
        n2 = (thrust**2).sum(axis=1)
        step = np.where(n2 > 1.0, self.adapt_k * (self.z[:, 12:15] * thrust).sum(axis=1) / n2, 0.0)
        self.kappa = np.clip(self.kappa * (1.0 + step), 0.3, 3.0)
        omega, alpha = model.actuator_inverse(u / self.kappa[:, None])
        beyond = np.zeros((self.n, 3), dtype=bool)
        for i in range(self.n):
            omega[i], alpha[i], beyond[i] = within_range(omega[i], alpha[i], self.G, self.rfl.airframe.servo_limit_rad)
        # a drone with a rotor at the edge commits the v that gives what its rotors deliver: u is
        # affine in v with slope beta(x) (51), so v + beta^-1 (u delivered - u)
        x = self.rfl.phi_r_inverse(zm[:, :12])
        shortfall = self.kappa[:, None] * model.actuator_map(omega, alpha) - u
        dv = np.linalg.solve(self.rfl.beta(x), shortfall[..., None])[..., 0]
        v = np.where(beyond.any(axis=1, keepdims=True), v + dv, v)
        if self.wind_gain and self.k_m:  # (not for a drone with a rotor at the servo range's edge)
            speed = np.maximum(np.linalg.norm(air_v, axis=1), 1.0)[:, None]
            d = self.z[:, 12:15]
            J_inv_d = (d - air_v * (air_v * d).sum(axis=1, keepdims=True) / (2 * speed**2)) / speed
            step = (self.wind_gain / self.k_m * J_inv_d)[:, 0:2]
            self.wind[:, 0:2] += np.where(beyond.any(axis=1, keepdims=True), 0.0, step)
        self.v_applied, self.v_pipe = self.v_pipe[0], self.v_pipe[1:] + [v]
        omega_now, self.motor_pipe = self.motor_pipe[0], self.motor_pipe[1:] + [omega]
        return omega_now, alpha


@pytest.mark.parametrize("air_density_kg_m3, wind_estimate_rate_1_s", [(0.0, 0.0), (1.225, 0.0), (1.225, 2.0)],
                         ids=["no-air", "sea-level-air", "sea-level-air-wind-estimated"])
def test_compiled_controller_equals_a_numpy_reference_and_agents_are_independent(paper_plan, rng, air_density_kg_m3,
                                                                                  wind_estimate_rate_1_s):
    """Six agents at once (compiled kernels) against the numpy reference above, over ticks with noisy
    measurements and arbitrary protocol inputs (some drive rotors past the servo range); and six
    single-agent controllers, one per agent, give the six-agent controller's commands, agent by agent. In no air and in air (the drag cancelled, drones moving at up to
    14 m/s), with and without the wind estimate."""
    d = paper_plan.design
    n = 6
    x = np.zeros((n, 12))
    x[:, 9:12] = rng.uniform(-3, 3, (n, 3))
    x[:, 6:9] = rng.uniform(-0.3, 0.3, (n, 3))
    if air_density_kg_m3:
        x[:, 0:3] = rng.uniform(-8, 8, (n, 3))
    air = {"air_density_kg_m3": air_density_kg_m3, "wind_estimate_rate_1_s": wind_estimate_rate_1_s}
    batch, ref = FormationController(d, n, **air), NumpyController(d, n, 200.0, 3.0, **air)
    singles = [FormationController(d, 1, **air) for _ in range(n)]  # (one per drone, as the companions run it)
    for c in (batch, ref):
        c.reset(x)
    for i, single in enumerate(singles):
        single.reset(x[i:i + 1])
    topo = paper_plan.schedule.topologies[1]
    beyond_range = False
    for _ in range(40):
        y = x[:, 6:12] + rng.normal(0, 0.01, (n, 6))
        xi = batch.observe(y)
        assert np.allclose(xi, ref.observe(y), rtol=1e-9, atol=1e-9)
        for i, single in enumerate(singles):
            assert np.allclose(single.observe(y[i:i + 1]), xi[i:i + 1], rtol=1e-12, atol=1e-12), i
        gamma = rng.normal(0, 100, (n, 6))
        v = protocol_input(d, xi, topo.adjacency @ xi, topo.in_degree, topo.pinning, np.zeros(12), gamma)
        act = batch.actuate(v)
        omega, alpha = ref.actuate(v)
        assert np.allclose(act.omega_rad_s, omega, rtol=1e-9, atol=1e-6)
        assert np.allclose(act.alpha_rad, alpha, rtol=1e-9, atol=1e-9)
        assert np.allclose(batch.thrust_scale, ref.kappa, rtol=1e-12)
        assert np.allclose(batch.wind_estimate_e_m_s, ref.wind, rtol=1e-9, atol=1e-12)
        beyond_range |= np.abs(alpha).max() >= d.rfl.airframe.servo_limit_rad
        for i, single in enumerate(singles):
            one = single.actuate(v[i:i + 1])
            assert np.allclose(one.omega_rad_s, act.omega_rad_s[i:i + 1], rtol=1e-12), i
            assert np.allclose(one.alpha_rad, act.alpha_rad[i:i + 1], rtol=1e-12, atol=1e-12), i
            assert np.allclose(single.thrust_scale, batch.thrust_scale[i:i + 1], rtol=1e-12), i
            assert np.allclose(single.wind_estimate_e_m_s, batch.wind_estimate_e_m_s[i:i + 1], rtol=1e-12, atol=1e-12), i
    assert np.abs(batch.thrust_scale - 1.0).max() > 1e-6  # (the adaptation did move)
    assert beyond_range  # (the servo range was met)
    if wind_estimate_rate_1_s:
        assert np.abs(batch.wind_estimate_e_m_s).max() > 1e-3 and not batch.wind_estimate_e_m_s[:, 2].any()


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


def _ticks(ctrl, ys, rates, vs):
    out = []
    for y, w, v in zip(ys, rates, vs):
        out.append(ctrl.observe(y, None, w).copy())
        act = ctrl.actuate(v)
        out.append(np.concatenate([act.omega_rad_s, act.alpha_rad], axis=1))
    return out


def test_without_measured_rates_the_controller_is_the_observer_alone_bit_for_bit(paper_plan, rng):
    """Rates that did not come (NaN rows, or none at all) leave every number as the observer alone
    makes it, in a row of their own while the other rows take rates; the default ignores rates."""
    d = paper_plan.design
    n = 3
    x = np.zeros((n, 12))
    x[:, 6:12] = rng.uniform(-0.3, 0.3, (n, 6))
    ys = [x[:, 6:12] + rng.normal(0, 0.01, (n, 6)) for _ in range(30)]
    vs = [rng.normal(0, 50, (n, 6)) for _ in range(30)]
    rates = [rng.normal(0, 0.5, (n, 3)) for _ in range(30)]
    for w in rates:
        w[1] = np.nan  # agent 2 has no gyro
    plain, measured, ignored = FormationController(d, n), FormationController(d, n, measured_rates=True), FormationController(d, n)
    for c in (plain, measured, ignored):
        c.reset(x)
    ref = _ticks(plain, ys, [None] * 30, vs)
    got = _ticks(measured, ys, rates, vs)
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(ref, got))
    assert not np.allclose(ref[-2][0], got[-2][0])  # (the others did take their rates)
    assert all(np.array_equal(a, b) for a, b in zip(ref, _ticks(ignored, ys, rates, vs)))


def test_measured_rates_on_a_trajectory_of_the_model_keep_the_estimate_exact(paper_plan, rng):
    """x_r(t) = e^(A_r t) x_r(0) with v = 0, measured exactly: eta and lambda, and body rates
    omega = Psi(eta)^-1 eta_dot (tilted, turning: Psi is far from I). The observer with the rates
    as three more outputs starts at x_r(0) and must stay on it, and predict x_r(t + lead) from it."""
    import scipy.linalg

    d = paper_plan.design
    ctrl = FormationController(d, 1, measured_rates=True)
    xr0 = np.r_[0.4, -0.3, 0.2, 0.6, -0.5, 0.8, 0.35, -0.3, 1.0, 2.0, -1.0, 20.0]
    ctrl.reset(d.rfl.phi_r_inverse(xr0)[None, :])
    for k in range(60):
        t = k * ctrl.dt_s
        xr = scipy.linalg.expm(d.A_r * t) @ xr0
        omega = np.linalg.solve(model.euler_rate_matrix(xr[6:9]), xr[3:6])
        pred = ctrl.observe(xr[None, 6:12], None, omega[None, :])
        ahead = scipy.linalg.expm(d.A_r * (t + ctrl.lead_s)) @ xr0
        # Euler rates and angles (which the rates enter) to 1e-7 rad(/s); the rest within the first-order
        # hold's error on the position (a cubic in t here)
        assert np.allclose(ctrl.estimate[0, 3:9], xr[3:9], rtol=0, atol=1e-7), (k, ctrl.estimate[0] - xr)
        assert np.allclose(pred[0, 3:9], ahead[3:9], rtol=0, atol=1e-7)
        assert np.allclose(ctrl.estimate[0], xr, rtol=0, atol=1e-4) and np.allclose(pred[0], ahead, rtol=0, atol=1e-4)
    # a wrong rate is seen: the same run with the rates of a level attitude (Psi = I) strays
    wrong = FormationController(d, 1, measured_rates=True)
    wrong.reset(d.rfl.phi_r_inverse(xr0)[None, :])
    for k in range(60):
        xr = scipy.linalg.expm(d.A_r * k * wrong.dt_s) @ xr0
        wrong.observe(xr[None, 6:12], None, xr[None, 3:6])
    assert np.abs(wrong.estimate[0, 3:6] - xr[3:6]).max() > 1e-3


def test_a_hold_and_a_formation_share_one_compiled_protocol():
    """The protocol a hold or a landing runs (``pinned_input``: broadcast, read-only views of its
    arguments) is the specialization the formation's rows run: no compilation waits for the first
    hold or landing of a flight. (It did: numba took the read-only views for another type, and the
    first landing of a fresh install stopped the companion's commands for a second, long enough for
    PX4 to end the flight.)"""
    from triswarm.gcs.scenarios import load_plan
    from triswarm.protocol import kernels
    from triswarm.protocol.agent import pinned_input, protocol_rows

    d = load_plan("paper-hexagon").design
    rows = protocol_rows(d, np.ones((2, 12)), np.zeros((2, 12)), np.zeros(2), np.ones(2), np.zeros((2, 12)),
                         np.zeros((2, 6)))
    compiled = set(kernels.protocol_rows.signatures)
    held = pinned_input(d, np.ones((1, 12)), np.zeros(12), np.zeros((1, 6)))
    assert set(kernels.protocol_rows.signatures) == compiled
    assert np.array_equal(held[0], rows[0])  # (pinned alone to a leader at the origin: the same v)
