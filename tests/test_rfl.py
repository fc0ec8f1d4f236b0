"""Robust feedback linearization (49)-(56): exactness by finite differences, and the linear model it
produces equals the Jacobian linearization at hover."""

import numpy as np
import pytest

from triswarm.protocol import model
from triswarm.protocol.design import left_inverse_pair
from triswarm.protocol.rfl import decoupling_matrix

from .conftest import random_states


def jacobian(f, x0, h=1e-6):
    return np.stack([(f(x0 + h * e) - f(x0 - h * e)) / (2 * h) for e in np.eye(x0.size)], axis=-1)


def test_rfl_is_exact_along_the_true_dynamics(rfl, airframe, rng):
    """d/dt phi_r(x) along f(x, u(x, v)) = A_r phi_r(x) + B_r v at random states with |theta| < 1.2."""
    x = random_states(rng, 40, max_pitch=1.2)
    v = rng.normal(0, 2e4, (40, 6))
    u = rfl.control(x, v)
    xdot = model.state_derivative(x, u, airframe)
    h = 1e-6
    lhs = (rfl.phi_r(x + h * xdot) - rfl.phi_r(x - h * xdot)) / (2 * h)
    rhs = rfl.phi_r(x) @ rfl.A_r.T + v @ rfl.B_r.T
    scale = np.abs(rhs).max(axis=1, keepdims=True) + 1.0
    assert np.abs(lhs - rhs).max() / scale.max() < 1e-6
    assert np.all(np.abs(lhs - rhs) <= 1e-6 * scale)


def test_linear_model_is_the_jacobian_at_hover(rfl, airframe):
    u0 = model.hover_input(airframe)
    A = jacobian(lambda x: model.state_derivative(x, u0, airframe), np.zeros(12))
    B = jacobian(lambda u: model.state_derivative(np.zeros(12), u, airframe), u0, h=1.0)
    # at the origin x_r = x to first order, so the Jacobian in x is the Jacobian in x_r
    assert np.allclose(rfl.A_r, A, atol=1e-8)
    assert np.allclose(rfl.B_r, B, rtol=1e-9, atol=1e-12)


def test_structure_matches_errata(rfl, airframe):
    g = airframe.gravity_m_s2
    A = np.zeros((12, 12))
    A[0, 7], A[1, 6] = g, -g
    A[6:9, 3:6] = np.eye(3)
    A[9:12, 0:3] = np.eye(3)
    assert np.allclose(rfl.A_r, A, atol=1e-12)
    assert np.all(rfl.B_r[6:] == 0)
    assert np.allclose(rfl.C_r, np.hstack([np.zeros((6, 6)), np.eye(6)]))
    # the errata's row 1 of pinv(B_r) (the printed B_tilde has another input scaling)
    B_tilde, B_bar = left_inverse_pair(rfl.B_r)
    assert B_tilde[0, :6] == pytest.approx([0, 16920.5, 537.75, 0, -22.8, 125.06], abs=0.1)
    assert np.allclose(B_tilde @ rfl.B_r, np.eye(6), atol=1e-9)
    assert np.allclose(B_bar @ rfl.B_r, 0)


def test_law_at_hover_is_the_trim_and_beta_is_identity(rfl, airframe):
    x = np.zeros(12)
    assert np.allclose(rfl.alpha(x), model.hover_input(airframe), rtol=1e-12)
    assert np.allclose(rfl.beta(x), np.eye(6), atol=1e-12)


def test_decoupling_matrix_condition_is_bounded_below_90_degrees_pitch_and_grows_towards_it(airframe):
    """M(x) (57) = blockdiag(Psi(eta), R(eta)) G, G the constant input matrix. W = Psi^-1 has
    W^T W = [[1, 0, -s], [0, 1, 0], [-s, 0, 1]] (s = sin theta), singular values 1 and sqrt(1 +- s), so
    cond(Psi) = sqrt((1 + |s|) / (1 - |s|)) whatever the roll and yaw, and
        cond(G) / cond(Psi) <= cond(M) <= cond(G) cond(Psi):
    bounded for |theta| < pi/2 (below 1200 up to the controller's 1.4 rad), cond(G) at level, and
    growing like 1/cos(theta) towards +-pi/2, where M is singular."""
    cond_G = np.linalg.cond(model.input_matrix(airframe))
    angles = np.linspace(-np.pi, np.pi, 13)

    def conds(theta):
        x = np.zeros((angles.size, angles.size, 12))
        x[..., 6], x[..., 8] = np.meshgrid(angles, angles)
        x[..., 7] = theta
        return np.linalg.cond(decoupling_matrix(x.reshape(-1, 12), airframe))

    for theta in np.linspace(-1.4, 1.4, 29):
        c = conds(theta)
        s = abs(np.sin(theta))
        cond_psi = np.sqrt((1 + s) / (1 - s))
        assert np.all(c <= cond_G * cond_psi * (1 + 1e-9)) and np.all(c >= cond_G / cond_psi * (1 - 1e-9))
        assert c.max() < 1200.0
    assert conds(0.0) == pytest.approx(cond_G, rel=1e-9)
    for eps in (1e-2, 1e-4, 1e-6):  # cond(Psi) ~ 2 / eps at theta = +-(pi/2 - eps)
        for theta in (np.pi / 2 - eps, -np.pi / 2 + eps):
            c = conds(theta)
            assert c.min() > 10.0 / eps and c.max() < 2.0 * cond_G / eps


def test_phi_r_inverse_and_solve_free_law(rfl, rng):
    x = random_states(rng, 50, max_pitch=1.2)
    assert np.allclose(rfl.phi_r_inverse(rfl.phi_r(x)), x, atol=1e-10)
    v = rng.normal(0, 1e4, (50, 6))
    u_xr, y_ddot = rfl.control_xr(rfl.phi_r(x), v)
    assert np.allclose(u_xr, rfl.control(x, v), rtol=1e-10, atol=1e-6)
    assert np.allclose(y_ddot, rfl.phi_r(x) @ rfl.L.T + v @ rfl.M0.T)


SEA_LEVEL = 1.225


def earth_acceleration(x, xdot):
    """lambda_ddot = d/dt (R v_b) = R (v_b_dot + omega x v_b), from a state and its derivative (28)."""
    R = model.rotation_body_to_earth(x[:, 6:9])
    return (R @ (xdot[:, 0:3] + np.cross(x[:, 3:6], x[:, 0:3]))[..., None])[..., 0]


def test_rfl_in_still_air_cancels_the_plants_drag_exactly(rfl, airframe, rng):
    """The same state and input through the plant's model in still air: its acceleration is the one
    the law commands, y_ddot = L x_r + M(0) v, in closed form (lambda_ddot = R (v_b_dot + omega x v_b))
    and, for eta too, by finite differences along the true dynamics. Without the drag term the same
    flight is off by exactly the drag, -(k/m) |lambda_dot| lambda_dot (k = 1/2 rho C_d A)."""
    x = random_states(rng, 40, max_pitch=1.2)
    x[:, 0:3] = rng.uniform(-15, 15, (40, 3))  # up to 26 m/s through the air
    v = rng.normal(0, 2e4, (40, 6))
    still = np.zeros(3)
    u, y_ddot = rfl.control_xr(rfl.phi_r(x), v, air_density_kg_m3=SEA_LEVEL)
    xdot = model.state_derivative(x, u, airframe, wind_e_m_s=still, air_density_kg_m3=SEA_LEVEL)
    scale = np.abs(y_ddot).max() + 1.0
    assert np.abs(earth_acceleration(x, xdot) - y_ddot[:, 3:6]).max() < 1e-12 * scale
    h = 1e-6
    lhs = (rfl.phi_r(x + h * xdot) - rfl.phi_r(x - h * xdot)) / (2 * h)
    rhs = rfl.phi_r(x) @ rfl.A_r.T + v @ rfl.B_r.T
    assert np.all(np.abs(lhs - rhs) <= 1e-6 * (np.abs(rhs).max(axis=1, keepdims=True) + 1.0))
    # the drag term switched off: the plant's acceleration misses the commanded one by the drag
    u_paper, _ = rfl.control_xr(rfl.phi_r(x), v)
    xdot_paper = model.state_derivative(x, u_paper, airframe, wind_e_m_s=still, air_density_kg_m3=SEA_LEVEL)
    vel_e = rfl.phi_r(x)[:, 0:3]
    k_m = 0.5 * SEA_LEVEL * airframe.drag_coefficient * airframe.frontal_area_m2 / airframe.mass_kg
    drag = -k_m * np.linalg.norm(vel_e, axis=1, keepdims=True) * vel_e
    assert np.abs(drag).max() > 5.0  # [m/s^2] (it is not small)
    assert np.allclose(earth_acceleration(x, xdot_paper) - y_ddot[:, 3:6], drag, rtol=1e-10, atol=1e-10 * scale)


def test_law_in_air_by_linear_solve_equals_the_compiled_one_and_no_air_is_the_papers(rfl, rng):
    x = random_states(rng, 50, max_pitch=1.2)
    v = rng.normal(0, 1e4, (50, 6))
    u_xr, _ = rfl.control_xr(rfl.phi_r(x), v, air_density_kg_m3=SEA_LEVEL)
    assert np.allclose(u_xr, rfl.control(x, v, air_density_kg_m3=SEA_LEVEL), rtol=1e-10, atol=1e-6)
    assert not np.allclose(u_xr, rfl.control(x, v), rtol=1e-6)
    assert np.array_equal(rfl.control_xr(rfl.phi_r(x), v, air_density_kg_m3=0.0)[0], rfl.control_xr(rfl.phi_r(x), v)[0])


def test_still_air_leaves_the_linearization_at_hover_as_it_is(rfl, airframe):
    """The drag's Jacobian, -(k/m) (|v| I + v v^T / |v|), vanishes at v = 0: the Jacobian of the
    model in still air at hover is A_r, and the law at hover is the trim, so A_r and L stay the
    paper's. Away from hover it does not vanish (the aerodynamic damping the law cancels)."""
    u0 = model.hover_input(airframe)
    still = np.zeros(3)
    A = jacobian(lambda x: model.state_derivative(x, u0, airframe, wind_e_m_s=still, air_density_kg_m3=SEA_LEVEL),
                 np.zeros(12))
    assert np.allclose(rfl.A_r, A, atol=1e-7)  # (central differences of |v| v leave h k/m = 2e-8)
    assert np.allclose(rfl.control(np.zeros(12), np.zeros(6), air_density_kg_m3=SEA_LEVEL), model.hover_input(airframe),
                       rtol=1e-12)
    x10 = np.zeros(12)
    x10[0] = 10.0
    A10 = jacobian(lambda x: model.state_derivative(x, u0, airframe, wind_e_m_s=still, air_density_kg_m3=SEA_LEVEL), x10)
    k_m = 0.5 * SEA_LEVEL * airframe.drag_coefficient * airframe.frontal_area_m2 / airframe.mass_kg
    assert A10[0, 0] == pytest.approx(-2 * k_m * 10.0, rel=1e-6) and A10[1, 1] == pytest.approx(-k_m * 10.0, rel=1e-6)
