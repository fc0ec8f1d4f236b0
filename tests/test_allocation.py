"""Where the servo range leaves a drone short (``kernels.allocate_within_range``): rotors beyond the
range are held at its edge, and the three give the angular accelerations asked first and of the
specific force what is left. Checked against an independent solver (scipy's SLSQP, the angular
accelerations as constraints, over the same rotors held) and against the rule it replaced (each
rotor's force projected on the range's edge, the others as asked)."""

import numpy as np
import pytest
from scipy.optimize import minimize

from triswarm.protocol import kernels, model

SCALE = 1e5
"""rho's order of magnitude [rad^2/s^2] (rotors at 300 rad/s), for the reference solver's variables."""


@pytest.fixture
def airframe(paper_plan):
    af = paper_plan.airframe
    return model.input_matrix(af), af.servo_limit_rad


def allocated(rho, G, limit):
    out, edge = rho.copy(), np.zeros(3)
    held = kernels.allocate_within_range(out, limit, G, edge)
    return out, edge, held


def reference(w, G, edge):
    """The least force error with the angular accelerations of w exactly, each rotor held at
    ``edge[j]`` (non-zero) pushing along it (non-negative push), the others free: SLSQP."""
    held = edge != 0
    n_free = 2 * int((~held).sum())

    def rho_of(p):
        rho, k, f = np.zeros(6), n_free, 0
        for j in range(3):
            if held[j]:
                rho[j], rho[j + 3] = p[k] * np.sin(edge[j]), p[k] * np.cos(edge[j])
                k += 1
            else:
                rho[j], rho[j + 3] = p[f], p[f + 1]
                f += 2
        return rho * SCALE

    def force_error(p):
        return float(np.sum((G[:3] @ rho_of(p) - w[:3]) ** 2))

    n = n_free + int(held.sum())
    bounds = [(None, None)] * n_free + [(0.0, None)] * int(held.sum())
    p0 = np.full(n, 1.0)
    torque_scale = np.linalg.norm(w[3:]) + 1.0
    res = minimize(force_error, p0, method="SLSQP", bounds=bounds,
                   constraints=[{"type": "eq", "fun": lambda p: (G[3:] @ rho_of(p) - w[3:]) / torque_scale}],
                   options={"ftol": 1e-12, "maxiter": 1000})
    assert res.success, res.message
    return rho_of(res.x)


def test_within_the_range_nothing_changes(airframe, rng):
    G, limit = airframe
    for _ in range(300):
        rho = model.actuator_map(rng.uniform(100, 700, 3), rng.uniform(-limit, limit, 3))
        out, edge, held = allocated(rho, G, limit)
        assert not held and not edge.any()
        assert np.array_equal(out, rho)  # (to the bit)


def test_a_rotor_beyond_the_range_is_held_at_its_edge_and_the_attitude_is_kept(airframe, rng):
    """One rotor asked past the range (up to pointing straight down), the others well within: the
    rotor ends at the nearest edge, every rotor within the range, the angular accelerations as
    asked, and no smaller force error is possible with them kept (SLSQP over the same rotors held).
    The projection on the edge it replaced left angular accelerations short by up to hundreds of
    rad/s^2."""
    G, limit = airframe
    worst_projection_torque = 0.0
    for trial in range(60):
        omega = rng.uniform(250.0, 600.0, 3)
        alpha = rng.uniform(-1.3, 1.3, 3)
        j = trial % 3
        alpha[j] = rng.choice([-1.0, 1.0]) * rng.uniform(limit + 0.02, np.pi)
        rho = model.actuator_map(omega, alpha)
        w = G @ rho
        out, edge, held = allocated(rho, G, limit)
        assert held and edge[j] == np.sign(alpha[j]) * limit
        push, angle = np.hypot(out[:3], out[3:]), np.arctan2(out[:3], out[3:])
        assert np.all((np.abs(angle) <= limit + 1e-12) | (push < 1e-6 * SCALE)), np.degrees(angle)
        assert np.allclose(angle[edge != 0], edge[edge != 0]) or np.all(push[edge != 0] < 1e-6 * SCALE)
        delivered = G @ out
        torque_error = np.linalg.norm(delivered[3:] - w[3:])
        assert torque_error <= 1e-3 * np.linalg.norm(w[3:]) + 1e-6, (trial, torque_error)
        best = reference(w, G, edge)
        force_error, best_force_error = (np.linalg.norm(r[:3] - w[:3]) for r in (delivered, G @ best))
        assert force_error <= best_force_error * 1.001 + 1e-6, (trial, force_error, best_force_error)
        projected = rho.copy()  # (the rule before: the force projected on the edge, the others as asked)
        along = max(np.sin(edge[j]) * rho[j] + np.cos(edge[j]) * rho[j + 3], 0.0)
        projected[j], projected[j + 3] = along * np.sin(edge[j]), along * np.cos(edge[j])
        worst_projection_torque = max(worst_projection_torque, np.linalg.norm(G[3:] @ projected - w[3:]))
    assert worst_projection_torque > 100.0  # rad/s^2: what the attitude lost before


def test_every_rotor_beyond_the_range_still_gives_a_command_within_it(airframe, rng):
    """All three asked past the range (a drone thrown upside down): all three held, none beyond,
    and the rotor speeds finite."""
    G, limit = airframe
    for _ in range(50):
        alpha = rng.choice([-1.0, 1.0], 3) * rng.uniform(limit + 0.01, np.pi, 3)
        out, edge, held = allocated(model.actuator_map(rng.uniform(100, 700, 3), alpha), G, limit)
        assert held and np.all(edge != 0)
        push, angle = np.hypot(out[:3], out[3:]), np.arctan2(out[:3], out[3:])
        assert np.all(np.isfinite(out)) and np.all((np.abs(angle) <= limit + 1e-12) | (push == 0.0))


def test_inputs_that_are_not_finite_are_left_as_they_are(airframe):
    """A drone whose state is already lost (NaN) gets its NaN back, for the simulation to call it
    diverged; the kernel does not raise."""
    G, limit = airframe
    rho = np.array([np.nan, 1e5, -1e5, -1e5, 1e5, 1e5])
    out, edge, held = allocated(rho, G, limit)
    assert not held and np.isnan(out[0]) and np.array_equal(out[1:], rho[1:])
