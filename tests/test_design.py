"""Algorithm 1: the Riccati equations, (91), (77) for every topology, B_tilde/B_bar, gamma and the
feasibility test (76)."""

import numpy as np
import pytest

from triswarm.protocol.design import FormationError, check_feasibility
from triswarm.protocol.formation import RawOffsets, RotatingPolygon


def test_lqr_riccati_equation_holds(paper_plan):
    d = paper_plan.design
    A, B, Q, R, P = d.A_r, d.B_r, d.weights.Q, d.weights.R, d.P
    residual = A.T @ P + P @ A + Q - P @ B @ np.linalg.solve(R, B.T) @ P           # (89)
    assert np.abs(residual).max() < 1e-7 * np.abs(Q).max()
    assert np.allclose(d.K, np.linalg.solve(R, B.T @ P))                             # (90)
    assert np.all(np.linalg.eigvalsh(P) > 0)


def test_kalman_riccati_equation_holds(paper_plan):
    d = paper_plan.design
    A, C, Qb, Rb, Pb = d.A_r, d.C_r, d.weights.Q_bar, d.weights.R_bar, d.P_bar
    residual = A @ Pb + Pb @ A.T - Pb @ C.T @ np.linalg.solve(Rb, C @ Pb) + Qb       # (99)
    assert np.abs(residual).max() < 1e-7 * np.abs(Qb).max()
    assert np.allclose(d.F, Pb @ C.T @ np.linalg.inv(Rb))                            # (98)


def test_scalar_lqr_closed_form():
    """python-control's LQR as the design uses it, on a scalar integrator: S = sqrt(Q R), K = S / R."""
    import control

    K, S, _ = control.lqr(np.array([[0.0]]), np.array([[1.0]]), np.array([[4.0]]), np.array([[9.0]]))
    assert S[0, 0] == pytest.approx(6.0) and K[0, 0] == pytest.approx(6.0 / 9.0)


def test_coupling_gain_satisfies_91(paper_plan):
    d = paper_plan.design
    lam_R = min(e.real.min() for e in d.eigenvalues)
    assert d.lambda_R == pytest.approx(lam_R)
    assert d.c >= 1.0 / (2.0 * lam_R) - 1e-12
    assert d.c == pytest.approx(d.weights.coupling_margin / (2.0 * lam_R))


def test_theorem_1_matrices_are_hurwitz_for_every_topology(paper_plan):
    d = paper_plan.design
    mats = d.closed_loop_matrices()
    assert {name for name, _, _ in mats} == {"two-chain", "triangles", "reverse-two-chain"}
    assert len(mats) == 18
    for name, lam, M in mats:
        assert np.linalg.eigvals(M).real.max() < 0, (name, lam)
    assert np.linalg.eigvals(d.observer_matrix()).real.max() < 0
    assert np.linalg.eigvals(d.augmented_observer_matrix()).real.max() < 0


@pytest.mark.parametrize("rate_hz, settles", [(200.0, True), (100.0, True), (50.0, False)])
def test_the_sampled_loop_is_the_continuous_one_with_its_input_held(paper_plan, rate_hz, settles):
    """Design.sampled_loop: (77)'s worst loop as the controllers run it, v held over each period.
    Against the reference model integrated (solve_ivp) with v = -c lambda K x held from each
    period's start, from the worst pole's eigenvector: the state grows by |z| each period; and the
    same |z| from scipy.signal's discretisation. The case study's gains settle at 100 and 200 Hz
    (the firmware stacks' rate and the plan's) and not at 50 Hz (flown: 27 m off by 20 s)."""
    from scipy.integrate import solve_ivp
    from scipy.signal import cont2discrete

    d = paper_plan.design
    s = d.sampled_loop(rate_hz)
    assert (s.radius < 1.0) == settles and (s.problem() is None) == settles
    T, gain = 1.0 / rate_hz, d.c * s.eigenvalue * d.K
    Phi, Gamma = cont2discrete((d.A_r, d.B_r, np.eye(12), np.zeros((12, 6))), T, method="zoh")[:2]
    z, vectors = np.linalg.eig(Phi - Gamma @ gain)
    assert np.abs(z).max() == pytest.approx(s.radius, rel=1e-9)
    x0 = vectors[:, np.argmax(np.abs(z))]
    x = x0
    for _ in range(10):
        v = -gain @ x
        x = solve_ivp(lambda t, y: d.A_r @ y + d.B_r @ v, (0.0, T), x, rtol=1e-11, atol=1e-13).y[:, -1]
    assert np.linalg.norm(x) / np.linalg.norm(x0) == pytest.approx(s.radius ** 10, rel=1e-6)


def test_lyapunov_argument_of_theorem_2(paper_plan):
    """V = d* P d decreases along A_r - c lambda B_r K for every lambda with Re >= lambda_R (95)."""
    d = paper_plan.design
    for lams in d.eigenvalues:
        for lam in lams:
            M = d.A_r - d.c * lam * d.B_r @ d.K
            Vdot = M.conj().T @ d.P + d.P @ M
            assert np.linalg.eigvalsh((Vdot + Vdot.conj().T) / 2).max() < 0


def test_gamma_makes_the_formation_an_exact_trajectory(paper_plan, rng):
    """(84): A_r h_i - h_dot_i + B_r gamma_i = 0 when (76) holds."""
    d = paper_plan.design
    for t in rng.uniform(0, 60, 10):
        h, h_dot = paper_plan.formation.offsets(t)
        gamma = d.gamma(h, h_dot)
        assert np.abs(h @ d.A_r.T - h_dot + gamma @ d.B_r.T).max() < 1e-9


def paper_printed_offsets(t, n=6):
    """h_i exactly as printed in Section 5 (rows 1-6 are the derivatives of rows 7-12)."""
    i = np.arange(1, n + 1)
    ph = t + (i - 1) * np.pi / 3
    s = (-1.0) ** i
    z = np.zeros(n)
    return np.stack([10 * np.cos(ph), -10 * np.sin(ph), z, z, z, z, -0.5 * s, -0.5 * s, 0.5 * s,
                     10 * np.sin(ph), 10 * np.cos(ph), np.full(n, 20.0)], axis=1)


def paper_printed_offsets_dot(t, n=6):
    i = np.arange(1, n + 1)
    ph = t + (i - 1) * np.pi / 3
    z = np.zeros(n)
    return np.stack([-10 * np.sin(ph), -10 * np.cos(ph), z, z, z, z, z, z, z,
                     10 * np.cos(ph), -10 * np.sin(ph), z], axis=1)


def test_76_accepts_the_papers_offsets(paper_plan):
    d = paper_plan.design
    raw = RawOffsets(6, paper_printed_offsets, paper_printed_offsets_dot)
    check_feasibility(d.A_r, d.B_bar, raw, np.linspace(0, 20, 201))
    # and the rotating polygon is the printed h_i
    for t in (0.0, 1.7, 13.2):
        assert np.allclose(RotatingPolygon.paper(6).offsets(t)[0], paper_printed_offsets(t), atol=1e-12)


def test_76_refuses_velocity_rows_that_are_not_the_derivative(paper_plan):
    d = paper_plan.design

    def wrong(t):  # drone 3's velocity rows doubled
        h = paper_printed_offsets(t)
        h[2, 0:3] *= 2.0
        return h

    raw = RawOffsets(6, wrong, paper_printed_offsets_dot)
    with pytest.raises(FormationError, match=r"drone 3 position rows 10-12 do not change at the rate its velocity rows 1-3 give") as exc:
        check_feasibility(d.A_r, d.B_bar, raw, np.linspace(0, 10, 101), source="test plan")
    assert "drone 1" not in str(exc.value) and str(exc.value).startswith("test plan fails the feasibility condition (76)")
