"""The simulated plant: same physics as the paper's model, RK4 against closed forms, actuator delay
and limits, ground contact, bad commands. (Its wind: test_wind.py.)"""

import numpy as np
import pytest

from triswarm.protocol import model
from triswarm.sitl import physics as ph

from .conftest import random_states


@pytest.mark.parametrize("windy", [False, True])
def test_plant_derivative_equals_the_paper_model(airframe, rng, windy):
    """The plant (quaternion attitude) and the model (Euler angles) share (24), (25), (27) and the drag
    (``protocol.dynamics``): what differs, the attitude, must agree too. (This also fails when numba's
    cache of the plant holds an older protocol/dynamics.py: delete the *.nbi and *.nbc files.)"""
    P = ph.airframe_vector(airframe, 1.225 if windy else 0.0)
    for x in random_states(rng, 30, max_pitch=1.4):
        u = rng.uniform(-1e5, 1e5, 6)
        wind = rng.uniform(-10, 10, (1, 3)) if windy else None
        f = model.state_derivative(x, u, airframe, None if wind is None else wind[0])
        s = np.zeros(13)
        s[ph.POS], s[ph.VEL_B], s[ph.QUAT], s[ph.RATE_B] = x[9:12], x[0:3], ph.quaternion_from_euler(x[6:9]), x[3:6]
        out = np.zeros(13)
        ph._derivative(s, u, P, wind, 0, out)
        assert np.allclose(out[ph.VEL_B], f[0:3], rtol=1e-12, atol=1e-9)
        assert np.allclose(out[ph.RATE_B], f[3:6], rtol=1e-12, atol=1e-9)
        assert np.allclose(out[ph.POS], f[9:12], rtol=1e-12, atol=1e-9)
        # quaternion rate maps to the Euler rates of (26)
        h = 1e-7
        eta_dot = (ph.euler_from_quaternion(s[ph.QUAT] + h * out[ph.QUAT]) - ph.euler_from_quaternion(s[ph.QUAT] - h * out[ph.QUAT])) / (2 * h)
        assert np.allclose(eta_dot, f[6:9], atol=1e-5)


def test_euler_quaternion_round_trip(rng):
    eta = rng.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi], (100, 3))
    assert np.allclose(ph.euler_from_quaternion(ph.quaternion_from_euler(eta)), eta, atol=1e-10)
    R = ph.rotation_from_quaternion(ph.quaternion_from_euler(eta))
    assert np.allclose(R, model.rotation_body_to_earth(eta), atol=1e-12)


def test_free_fall_follows_the_closed_form(airframe):
    plant = ph.Plant(airframe, 1, dt_s=1e-3)
    plant.reset([[0.0, 0.0, 50.0]], euler_rad=[[0.3, -0.2, 1.0]], velocity_b_m_s=[[0.0, 0.0, 0.0]])
    plant.landed[:] = False
    plant.advance(2000)
    z = plant.observe().position_m[0, 2]
    assert z == pytest.approx(50.0 - 0.5 * airframe.gravity_m_s2 * 2.0**2, abs=1e-9)


def test_torque_free_body_conserves_energy_and_angular_momentum(airframe):
    """Motors off, in free fall: |I w| and w.I w are constants of the motion (Euler's equations)."""
    plant = ph.Plant(airframe, 1, dt_s=1e-3)
    plant.reset([[0.0, 0.0, 1e4]], rate_b_rad_s=[[3.0, -2.0, 5.0]], velocity_b_m_s=[[0.0, 0.0, 0.0]])
    plant.landed[:] = False
    I = model.inertia_matrix(airframe)
    w0 = plant.observe().rate_b_rad_s[0]
    R0 = ph.rotation_from_quaternion(plant.state[0, ph.QUAT])
    H0, E0 = R0 @ I @ w0, w0 @ I @ w0
    plant.advance(5000)
    w = plant.observe().rate_b_rad_s[0]
    R = ph.rotation_from_quaternion(plant.state[0, ph.QUAT])
    assert np.allclose(R @ I @ w, H0, rtol=1e-7)  # angular momentum fixed in the earth frame
    assert w @ I @ w == pytest.approx(E0, rel=1e-7)


def test_hover_input_holds_the_drone(airframe):
    omega, alpha = model.hover_trim(airframe)
    plant = ph.Plant(airframe, 3, dt_s=1e-3)
    plant.reset(np.array([[0, 0, 5.0], [1, 1, 5.0], [2, 0, 10.0]]), servo_rad=alpha)
    plant.landed[:] = False
    plant.command(np.tile(omega, (3, 1)), np.tile(alpha, (3, 1)))
    plant.advance(3000)
    obs = plant.observe()
    assert np.abs(obs.position_m - [[0, 0, 5.0], [1, 1, 5.0], [2, 0, 10.0]]).max() < 1e-9
    assert np.abs(obs.euler_rad).max() < 1e-9


def test_servo_delay_is_a_transport_delay(airframe):
    plant = ph.Plant(airframe, 1, dt_s=1e-3, servo_delay_s=0.01)
    plant.reset([[0, 0, 100.0]], servo_rad=[0.0, 0.0, 0.0])
    plant.landed[:] = False
    plant.command([[300.0, 300.0, 300.0]], [[0.5, -0.3, 0.2]])
    seen = []
    for _ in range(15):
        plant.advance(1)
        seen.append(np.arctan2(plant.rho[0, 0:3], plant.rho[0, 3:6]).copy())
    seen = np.array(seen)
    assert np.allclose(seen[:10], 0.0)            # steps 0..9: still the old angle
    assert np.allclose(seen[10:], [0.5, -0.3, 0.2])  # from step 10 = 0.01 s on: the new one


def test_a_servo_of_finite_speed_turns_at_its_rate_after_the_delay(airframe):
    """With servo_rate_rad_s, a servo turns towards its delayed command at that rate: from the old
    angle a0 to the new a1 it follows a0 + rate (t - delay) sign(a1 - a0) and stops at a1; the
    longer way round (-100 deg to +100 deg) goes through the middle of the range, never across its
    ends. A command that changes while the servo turns turns it towards the new one."""
    rate_rad_s, delay_s, dt_s = 10.0, 0.01, 1e-3
    af = airframe.replace(servo_rate_rad_s=rate_rad_s, servo_delay_s=delay_s)
    plant = ph.Plant(af, 1, dt_s=dt_s)
    start = np.radians([0.0, -100.0, 30.0])
    plant.reset([[0, 0, 100.0]], servo_rad=start)
    plant.landed[:] = False
    target = np.radians([60.0, 100.0, 30.0])
    plant.command([[300.0, 300.0, 300.0]], [target])
    seen = []
    for _ in range(500):
        plant.advance(1)
        seen.append(np.arctan2(plant.rho[0, 0:3], plant.rho[0, 3:6]).copy())
    t_s = dt_s * np.arange(1, 501)  # (the angle applied through step k ends at (k + 1) dt)
    turned = np.clip(rate_rad_s * (t_s - delay_s), 0.0, None)[:, None]
    expected = start + np.sign(target - start) * np.minimum(turned, np.abs(target - start))
    # (arctan2 wraps: compare on the circle; the middle of the range is what the path crosses)
    assert np.allclose(np.angle(np.exp(1j * (np.array(seen) - expected))), 0.0, atol=1e-9)
    assert np.abs(np.array(seen)[:, 1]).max() <= np.radians(100.0) + 1e-9 and np.array(seen)[200, 1] > 0
    plant.command([[300.0, 300.0, 300.0]], [start])  # back, from where each servo is
    at = plant.servo_rad.copy()
    plant.advance(int(delay_s / dt_s) + 20)
    assert plant.servo_rad == pytest.approx(at + np.sign(start - at) * np.minimum(20 * dt_s * rate_rad_s,
                                                                                 np.abs(start - at)))


def test_motor_and_servo_limits_are_applied(airframe):
    plant = ph.Plant(airframe, 1, dt_s=1e-3, servo_delay_s=0.0)
    plant.reset([[0, 0, 100.0]])
    plant.landed[:] = False
    plant.command([[5000.0, 400.0, -10.0]], [[3.0, -3.0, 0.1]])
    plant.advance(1)
    omega = np.sqrt(np.hypot(plant.rho[0, 0:3], plant.rho[0, 3:6]))
    alpha = np.arctan2(plant.rho[0, 0:3], plant.rho[0, 3:6])
    assert omega == pytest.approx([airframe.max_rotor_speed_rad_s, 400.0, 0.0])
    assert alpha[0] == pytest.approx(airframe.servo_limit_rad)
    assert alpha[1] == pytest.approx(-airframe.servo_limit_rad)


def test_non_finite_commands_are_not_applied(airframe):
    """A NaN or infinite command is a motor stopped or a servo centred, exactly."""
    bad, zeroed = (ph.Plant(airframe, 1, dt_s=1e-3) for _ in range(2))
    for plant in (bad, zeroed):
        plant.reset([[0, 0, 100.0]])
        plant.landed[:] = False
    bad.command([[np.nan, np.inf, 300.0]], [[np.nan, 0.0, -np.inf]])
    zeroed.command([[0.0, 0.0, 300.0]], [[0.0, 0.0, 0.0]])
    bad.advance(100)
    zeroed.advance(100)
    assert np.all(np.isfinite(bad.state))
    assert np.array_equal(bad.state, zeroed.state) and np.array_equal(bad.rho, zeroed.rho)
    assert np.abs(bad.state[0, ph.RATE_B]).max() > 1.0  # (one rotor alone does turn the drone)


def test_held_thrust_and_attitude_give_constant_acceleration(airframe):
    """The hover input scaled by 1.1 at a tilted attitude: no torque, so the attitude holds, and
    the body force 1.1 m g along body z gives the earth acceleration R (0, 0, 1.1 g) - (0, 0, g),
    constant: p(t) = p0 + a t^2 / 2, which RK4 integrates exactly."""
    omega, alpha = model.hover_trim(airframe)
    eta = np.array([0.3, -0.2, 1.1])
    plant = ph.Plant(airframe, 1, dt_s=1e-3, servo_delay_s=0.0)
    plant.reset([[1.0, 2.0, 50.0]], euler_rad=[eta], servo_rad=alpha)
    plant.landed[:] = False
    plant.command([omega * np.sqrt(1.1)], [alpha])
    plant.advance(2000)
    g = airframe.gravity_m_s2
    a = model.rotation_body_to_earth(eta) @ [0.0, 0.0, 1.1 * g] - [0.0, 0.0, g]
    obs = plant.observe()
    assert obs.position_m[0] == pytest.approx([1.0, 2.0, 50.0] + 0.5 * a * 2.0**2, abs=1e-8)
    assert obs.velocity_e_m_s[0] == pytest.approx(a * 2.0, abs=1e-8)
    assert obs.euler_rad[0] == pytest.approx(eta, abs=1e-10)


def test_ground_contact(airframe):
    omega, alpha = model.hover_trim(airframe)
    plant = ph.Plant(airframe, 3, dt_s=1e-3, servo_delay_s=0.0)
    plant.reset(np.array([[0, 0, 0.0], [3, 0, 0.0], [6, 0, 2.0]]), servo_rad=alpha)
    assert list(plant.landed) == [True, True, False]
    # drone 1: motors off; drone 2: 90 % of hover thrust; drone 3: falls from 2 m, motors off
    plant.command(np.array([[0, 0, 0], omega * np.sqrt(0.9), [0, 0, 0]]), np.tile(alpha, (3, 1)))
    for _ in range(200):
        plant.advance(10)
        assert plant.state[:, 2].min() >= 0.0
    obs = plant.observe()
    assert np.allclose(obs.position_m[:2], [[0, 0, 0], [3, 0, 0]], atol=1e-12)
    assert obs.position_m[2, 2] == 0.0 and obs.landed.all()
    assert np.abs(obs.velocity_e_m_s).max() == 0.0 and np.abs(obs.euler_rad[:, :2]).max() == 0.0
    # 110 % of hover thrust: lifts off and climbs with a = 0.1 g
    plant.command(np.tile(omega * np.sqrt(1.1), (3, 1)), np.tile(alpha, (3, 1)))
    plant.advance(1000)
    obs = plant.observe()
    assert not obs.landed.any()
    assert obs.position_m[:, 2] == pytest.approx(0.5 * 0.1 * airframe.gravity_m_s2 * 1.0**2, rel=0.01)
