"""The tri-rotor model (24)-(27), the actuator map (29) and hover trim, against the errata's numbers
and against geometry."""

import numpy as np
import pytest

from triswarm.protocol import model
from triswarm.protocol.airframe import RPM_TO_RAD_S, Airframe, ParameterError

from .conftest import random_states


def test_hover_trim_matches_errata(airframe):
    omega, alpha = model.hover_trim(airframe)
    assert omega == pytest.approx([288.38] * 3, abs=0.01)
    assert np.degrees(alpha) == pytest.approx([3.637] * 3, abs=0.001)
    u = model.hover_input(airframe)
    assert u[:3] == pytest.approx([5275.3] * 3, abs=0.1)
    assert u[3:] == pytest.approx([82994.9] * 3, abs=0.1)
    # and it really is an equilibrium of (24)-(27) at any position and heading
    x = np.zeros(12)
    x[8], x[9:12] = 1.3, [4.0, -2.0, 7.0]
    x_level = x.copy()
    x_level[8] = 0.0
    assert np.abs(model.state_derivative(x_level, u, airframe)).max() < 1e-12
    assert np.abs(model.state_derivative(x, u, airframe)).max() < 1e-12
    # the same rotor speeds and angles through (29), not the solved rho
    omega, alpha = model.hover_trim(airframe)
    assert np.abs(model.state_derivative(x, model.actuator_map(omega, alpha), airframe)).max() < 1e-9


def test_derivative_at_a_yawed_pitched_state_by_hand(airframe):
    """Pitch 30 deg, yaw 90 deg, flying 2 m/s along body x, yawing at 0.5 rad/s, rotor 1 alone at
    300 rad/s untilted. By hand: gravity in the body frame g (sin 30, 0, -cos 30); the Coriolis term
    w x v = (0, 1, 0); rotor 1 pushes kf w^2 along body z from the arm l e_x, so its torque is
    -l kf w^2 e_y, and its drag torque -kd w^2 e_z; (26) with roll 0 gives (r tan 30, 0, r / cos 30);
    body x points north-tilted-down turned to the west: R e_x = (0, cos 30, -sin 30)."""
    af = airframe
    g, m, l, kf, kd = af.gravity_m_s2, af.mass_kg, af.arm_length_m, af.k_f_N_s2, af.k_d_N_m_s2
    Ixx, Iyy, Izz, Iyz = af.Ixx_kg_m2, af.Iyy_kg_m2, af.Izz_kg_m2, af.Iyz_kg_m2
    th, r, w2 = np.radians(30.0), 0.5, 300.0**2
    x = np.zeros(12)
    x[0], x[5], x[7], x[8], x[9:12] = 2.0, r, th, np.pi / 2, [1.0, 2.0, 3.0]
    u = np.array([0.0, 0.0, 0.0, w2, 0.0, 0.0])
    f = model.state_derivative(x, u, af)
    assert f[0:3] == pytest.approx([g * 0.5, -1.0, -g * np.cos(th) + kf * w2 / m], abs=1e-12)
    # (25): I w_dot = tau - w x I w with I w = (0, -Iyz r, Izz r), w x I w = (Iyz r^2, 0, 0)
    tau = np.array([-Iyz * r**2, -l * kf * w2, -kd * w2])
    det = Iyy * Izz - Iyz**2
    assert f[3:6] == pytest.approx([tau[0] / Ixx, (Izz * tau[1] + Iyz * tau[2]) / det,
                                    (Iyz * tau[1] + Iyy * tau[2]) / det], rel=1e-12)
    assert f[6:9] == pytest.approx([r * np.tan(th), 0.0, r / np.cos(th)], abs=1e-12)
    assert f[9:12] == pytest.approx([0.0, 2.0 * np.cos(th), -2.0 * np.sin(th)], abs=1e-12)


def test_drag_by_hand(airframe):
    """At rest in a 6 m/s wind from the north (towards -x), level and yawed 90 deg (body x to the
    west, body y to the south): the drag 1/2 rho C_d A 36 N pushes along earth -x, body +y."""
    x = np.zeros(12)
    x[8] = np.pi / 2
    u = model.hover_input(airframe)
    rho_air = 1.2
    f = model.state_derivative(x, u, airframe, wind_e_m_s=[-6.0, 0.0, 0.0], air_density_kg_m3=rho_air)
    drag_N = 0.5 * rho_air * airframe.drag_coefficient * airframe.frontal_area_m2 * 36.0
    assert f[0:3] == pytest.approx([0.0, drag_N / airframe.mass_kg, 0.0], abs=1e-12)
    assert np.abs(f[3:12]).max() < 1e-12
    # no wind: no drag at any velocity (the paper's model); still air: the drag of the motion
    x[0:3] = [3.0, -1.0, 2.0]
    still = model.state_derivative(x, u, airframe, wind_e_m_s=np.zeros(3), air_density_kg_m3=rho_air)
    none = model.state_derivative(x, u, airframe)
    v_e = model.rotation_body_to_earth(x[6:9]) @ x[0:3]
    k = 0.5 * rho_air * airframe.drag_coefficient * airframe.frontal_area_m2
    drag_b = model.rotation_body_to_earth(x[6:9]).T @ (-k * np.linalg.norm(v_e) * v_e)
    assert still[0:3] - none[0:3] == pytest.approx(drag_b / airframe.mass_kg, abs=1e-12)
    assert np.array_equal(still[3:], none[3:])


def test_power_balance_along_the_flow(airframe, rng):
    """The mechanical energy 1/2 m |v|^2 + 1/2 w.I w + m g z changes along the model's flow (its
    directional derivative, by central differences) at the power of the rotors' force and torque
    and of the drag: gravity, the Coriolis and the gyroscopic terms do no work."""
    I = model.inertia_matrix(airframe)
    m, g = airframe.mass_kg, airframe.gravity_m_s2

    def energy(x):
        return 0.5 * m * x[0:3] @ x[0:3] + 0.5 * x[3:6] @ I @ x[3:6] + m * g * x[11]

    wind = np.array([4.0, -3.0, 1.0])
    k = 0.5 * 1.225 * airframe.drag_coefficient * airframe.frontal_area_m2
    for x in random_states(rng, 20):
        u = rng.uniform(-2e5, 2e5, 6)
        f = model.state_derivative(x, u, airframe, wind_e_m_s=wind)
        h = 1e-6
        dE = (energy(x + h * f) - energy(x - h * f)) / (2 * h)
        v_e = model.rotation_body_to_earth(x[6:9]) @ x[0:3]
        rel = v_e - wind
        power = (airframe.k_f_N_s2 * model.H_f @ u) @ x[0:3] + (model.torque_matrix(airframe) @ u) @ x[3:6] \
            - k * np.linalg.norm(rel) * rel @ v_e
        assert dE == pytest.approx(power, rel=1e-6, abs=1e-6)


def test_motor_limit_numbers(airframe):
    assert airframe.max_rotor_speed_rad_s == pytest.approx(1256.64, abs=0.01)
    assert airframe.max_omega_sq == pytest.approx(1.579e6, rel=1e-3)
    assert 12000 * RPM_TO_RAD_S == pytest.approx(1256.637, abs=1e-3)


def test_actuator_map_round_trips(rng):
    omega = rng.uniform(0.0, 1256.0, (200, 3))
    alpha = rng.uniform(-np.pi + 1e-6, np.pi - 1e-6, (200, 3))
    u = model.actuator_map(omega, alpha)
    omega2, alpha2 = model.actuator_inverse(u)
    assert np.allclose(omega2, omega, rtol=1e-12, atol=1e-9)
    assert np.allclose(alpha2, alpha, atol=1e-9)
    # and the other way round, from arbitrary rho
    rho = rng.normal(0, 1e5, (200, 6))
    assert np.allclose(model.actuator_map(*model.actuator_inverse(rho)), rho, rtol=1e-9, atol=1e-6)


def test_rotation_is_rz_ry_rx_of_equation_6(rng):
    def Rx(a):
        return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])

    def Ry(a):
        return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])

    def Rz(a):  # errata: the second row is [sin, cos, 0]
        return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])

    for eta in rng.uniform(-1.5, 1.5, (20, 3)):
        R = model.rotation_body_to_earth(eta)
        assert np.allclose(R, Rz(eta[2]) @ Ry(eta[1]) @ Rx(eta[0]), atol=1e-14)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-14)
        assert np.linalg.det(R) == pytest.approx(1.0)


def test_euler_rate_matrix_is_consistent_with_the_rotation(rng):
    """R^T dR/dt = S(omega) when eta_dot = Psi(eta) omega (finite differences)."""
    for _ in range(20):
        eta = rng.uniform(-1.2, 1.2, 3)
        omega = rng.normal(size=3)
        eta_dot = model.euler_rate_matrix(eta) @ omega
        h = 1e-6
        R_dot = (model.rotation_body_to_earth(eta + h * eta_dot) - model.rotation_body_to_earth(eta - h * eta_dot)) / (2 * h)
        S = model.rotation_body_to_earth(eta).T @ R_dot
        assert np.allclose(S, [[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]], atol=1e-7)
        assert np.allclose(model.body_rate_matrix(eta) @ model.euler_rate_matrix(eta), np.eye(3), atol=1e-12)


def test_forces_and_torques_follow_the_arm_geometry(airframe, rng):
    """(3), (11), (13) against the sum over rotors of R_li^b F_i and l_i x F_i built from (1)-(2), (12).

    The arm of rotor i lies along its local x axis (Section 3.1: "X_li is extended outside the i-th arm
    along the same line as the arm"), l_i = l R_li e_x; the l_2, l_3 printed in (10) contradict this and
    H_t (a typo), while this geometry reproduces H_t exactly."""
    c, s = -0.5, np.sqrt(3) / 2
    R_l = [np.eye(3), np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])]
    arms = airframe.arm_length_m * np.array([R @ [1.0, 0.0, 0.0] for R in R_l])
    for _ in range(10):
        omega = rng.uniform(0, 800, 3)
        alpha = rng.uniform(-2, 2, 3)
        force = np.zeros(3)
        torque = np.zeros(3)
        for i in range(3):
            F_local = airframe.k_f_N_s2 * omega[i] ** 2 * np.array([0, np.sin(alpha[i]), np.cos(alpha[i])])
            D_local = -airframe.k_d_N_m_s2 * omega[i] ** 2 * np.array([0, np.sin(alpha[i]), np.cos(alpha[i])])
            force += R_l[i] @ F_local
            torque += np.cross(arms[i], R_l[i] @ F_local) + R_l[i] @ D_local
        rho = model.actuator_map(omega, alpha)
        assert np.allclose(airframe.k_f_N_s2 * model.H_f @ rho, force, rtol=1e-12, atol=1e-12)
        assert np.allclose(model.torque_matrix(airframe) @ rho, torque, rtol=1e-12, atol=1e-12)


def test_free_body_derivative_is_gravity_and_kinematics(airframe, rng):
    x = random_states(rng, 50)
    f = model.state_derivative(x, np.zeros((50, 6)), airframe)
    R = model.rotation_body_to_earth(x[:, 6:9])
    # earth-frame acceleration of a free body is -g e_z: d/dt(R v) = R (v_dot + w x v)
    acc_e = (R @ (f[:, 0:3] + np.cross(x[:, 3:6], x[:, 0:3]))[:, :, None])[:, :, 0]
    assert np.allclose(acc_e, [0, 0, -airframe.gravity_m_s2], atol=1e-12)
    assert np.allclose(f[:, 9:12], (R @ x[:, 0:3, None])[:, :, 0])


@pytest.mark.parametrize("field,value", [("mass_kg", -0.5), ("mass_kg", float("nan")), ("k_f_N_s2", 0.0),
                                         ("Iyz_kg_m2", 0.1), ("servo_limit_rad", 4.0)])
def test_airframe_refuses_bad_parameters(field, value):
    with pytest.raises(ParameterError, match=field.split("_")[0]):
        Airframe(**{field: value})
