"""The certificate of the switched formation-error system against independent truth: the scalar
closed form, exact trajectories of the switched linear system (matrix exponentials), and schedules
whose exact growth per cycle (the monodromy matrix) is known."""

import math

import numpy as np
import pytest
import scipy.linalg

from triswarm.protocol import graph
from triswarm.protocol.certificate import LoopMatrices, certify
from triswarm.protocol.graph import Topology
from triswarm.protocol.plan import DEFAULT_COUPLING_MARGIN


def scalar_loop(a=0.5, q=2.0, r=0.5):
    """x' = a x + v, cost q x^2 + r v^2: P = r (a + sqrt(a^2 + q / r)), K = P / r (python-control's
    scalar LQR check)."""
    P = r * (a + math.sqrt(a * a + q / r))
    return LoopMatrices(np.array([[a]]), np.array([[1.0]]), np.array([[q]]), np.array([[r]]), np.array([[P]]))


@pytest.fixture(scope="module")
def loop(paper_plan):
    d = paper_plan.design
    return LoopMatrices(d.A_r, d.B_r, paper_plan.weights.Q, paper_plan.weights.R, d.P)


def exact_flow(loop, c, M, t):
    """exp(t (I (x) A - c M (x) B K)): the nominal error system under one topology."""
    n = M.shape[0]
    return scipy.linalg.expm(t * (np.kron(np.eye(n), loop.A) - c * np.kron(M, loop.B @ loop.K)))


def monodromy_radius(loop, c, Ms, T):
    Phi = np.eye(Ms[0].shape[0] * loop.A.shape[0])
    for M in Ms:
        Phi = exact_flow(loop, c, M, T) @ Phi
    return float(np.abs(np.linalg.eigvals(Phi)).max())


def test_scalar_case_is_exact():
    """One agent pinned with weight g: delta' = (a - c g K) delta, so V = theta P delta^2 decays at
    exactly 2 (c g K - a), and the envelope is |delta(t)| / |delta(0)| itself."""
    loop = scalar_loop()
    a, K = loop.A[0, 0], loop.K[0, 0]
    c, g1, g2, T = 0.8, 1.0, 3.0, 0.7
    cert = certify(loop, c, [np.array([[g1]]), np.array([[g2]])], T)
    assert cert.certified and cert.any_switching and cert.min_dwell_s == 0.0
    assert cert.best.mu == pytest.approx([g1, g2])
    assert cert.best.beta_1_s == pytest.approx([2 * (c * g1 * K - a), 2 * (c * g2 * K - a)], rel=1e-9)
    t = np.linspace(0.0, 5.0, 101)
    k = np.floor(t / T).astype(int)
    # exact: time spent in each topology by t
    in_1 = T * ((k + 1) // 2) + np.where(k % 2 == 0, t - k * T, 0.0)
    in_2 = t - in_1
    exact = np.exp(-(c * g1 * K - a) * in_1 - (c * g2 * K - a) * in_2)
    assert cert.envelope(t) == pytest.approx(exact, rel=1e-9)
    assert cert.log_growth_per_cycle == pytest.approx(-2 * T * (c * (g1 + g2) * K - 2 * a), rel=1e-9)


def test_a_gain_too_small_is_not_certified():
    loop = scalar_loop()
    K, a = loop.K[0, 0], loop.A[0, 0]
    c = 0.9 * a / K  # c g K < a: the single loop itself diverges
    cert = certify(loop, c, [np.array([[1.0]])], 1.0)
    assert not cert.certified and math.isinf(cert.transient_bound)


def test_one_topology_is_certified(loop):
    """Each family alone, as a schedule of one, with the paper's margin of 3."""
    for make in (graph.two_chain, graph.triangles, graph.ring_tree_left):
        t = make(12)
        c = 3.0 / (2 * t.eigenvalues().real.min())
        cert = certify(loop, c, [t.L_plus_G], 5.0, [t.name])
        assert cert.certified and cert.any_switching and cert.decay_rate_1_s > 0, t.name


def test_the_bound_holds_along_exact_trajectories(loop):
    """The paper's three families at N = 4, switched every 2 s: ||delta(t)|| never exceeds the
    certified envelope, from random initial errors, over three cycles sampled every 0.05 s."""
    topologies = [f(4) for f in graph.PAPER_FAMILIES.values()]
    Ms = [t.L_plus_G for t in topologies]
    c = 3.0 / (2 * min(t.eigenvalues().real.min() for t in topologies))
    T, dt = 2.0, 0.05
    cert = certify(loop, c, Ms, T)
    assert cert.certified
    steps = [exact_flow(loop, c, M, dt) for M in Ms]
    rng = np.random.default_rng(3)
    t = np.arange(0, int(round(3 * len(Ms) * T / dt)) + 1) * dt
    envelope = cert.envelope(t)
    worst_ratio = 0.0
    for _ in range(20):
        delta = rng.normal(size=4 * 12) * rng.choice([1e-3, 1.0, 1e3], size=4 * 12)
        norm0 = np.linalg.norm(delta)
        for k, tk in enumerate(t):
            ratio = np.linalg.norm(delta) / norm0
            assert ratio <= envelope[k] * (1 + 1e-9), (tk, ratio, envelope[k])
            worst_ratio = max(worst_ratio, ratio / envelope[k])
            delta = steps[int((tk + 1e-9) // T) % len(Ms)] @ delta
        assert np.linalg.norm(delta) / norm0 <= cert.transient_bound
    assert envelope[-1] < envelope[0]  # and the envelope itself decays: the bound says something


def test_refuses_a_schedule_that_diverges(loop):
    """The paper's families at N = 24 with c on the boundary (91): the exact growth per cycle of the
    switched system is above 1 (it diverges), and the certificate refuses it."""
    topologies = [f(24) for f in graph.PAPER_FAMILIES.values()]
    Ms = [t.L_plus_G for t in topologies]
    c = 1.0 / (2 * min(t.eigenvalues().real.min() for t in topologies))
    assert monodromy_radius(loop, c, Ms, 5.0) > 1.0
    cert = certify(loop, c, Ms, 5.0)
    assert not cert.certified and math.isinf(cert.transient_bound)


def test_certified_schedules_are_stable(loop):
    """Soundness on random schedules of small random digraphs: whenever the certificate vouches for
    a schedule, its exact monodromy matrix has spectral radius below 1."""
    rng = np.random.default_rng(11)
    certified = 0
    for _ in range(25):
        n = int(rng.integers(2, 4))
        Ms = []
        while len(Ms) < 2:
            A = (rng.uniform(size=(n, n)) < 0.5) * rng.uniform(0.2, 3.0, size=(n, n))
            np.fill_diagonal(A, 0.0)
            g = (rng.uniform(size=n) < 0.5) * rng.uniform(0.2, 2.0, size=n)
            t = Topology("random", A, g)
            if t.reachable_from_leader().all():
                Ms.append(t.L_plus_G)
        c = rng.uniform(1.0, 6.0) / (2 * min(np.linalg.eigvals(M).real.min() for M in Ms))
        T = rng.uniform(0.2, 3.0)
        if certify(loop, c, Ms, T).certified:
            certified += 1
            assert monodromy_radius(loop, c, Ms, T) < 1.0
    assert certified >= 5  # the property was exercised


def test_min_dwell_time_is_where_certification_starts(loop):
    """Below the dwell time the bound needs, no candidate certifies; just above, one does."""
    topologies = [f(6) for f in graph.PAPER_FAMILIES.values()]
    Ms = [t.L_plus_G for t in topologies]
    c = 3.0 / (2 * min(t.eigenvalues().real.min() for t in topologies))
    dwell = certify(loop, c, Ms, 5.0).min_dwell_s
    assert 0 < dwell < 5.0
    assert certify(loop, c, Ms, 1.01 * dwell).certified
    assert not certify(loop, c, Ms, 0.99 * dwell).certified


def test_ring_trees_are_certified_for_any_switching_at_any_size(loop):
    """With the shipped coupling margin (every eigenvalue of L + G is 1, so c = margin / 2)."""
    for n in (2, 5, 13, 40, 97, 200):
        topologies = [f(n) for f in graph.RING_FAMILIES.values()]
        cert = certify(loop, DEFAULT_COUPLING_MARGIN / 2, [t.L_plus_G for t in topologies], 5.0)
        assert cert.certified and cert.any_switching and cert.min_dwell_s == 0.0, n
        assert cert.decay_rate_1_s > 0.15, n


def test_the_case_studys_schedule_is_certified_and_margin_1_is_not(loop):
    """The paper's families at N = 6, switched every 5 s: certified with the shipped margin (it
    needs fewer than 5 s between switches), not on the boundary of (91), where the triangles graph
    alone cannot be shown to decay."""
    topologies = [f(6) for f in graph.PAPER_FAMILIES.values()]
    Ms = [t.L_plus_G for t in topologies]
    lambda_R = min(t.eigenvalues().real.min() for t in topologies)
    cert = certify(loop, DEFAULT_COUPLING_MARGIN / (2 * lambda_R), Ms, 5.0)
    assert cert.certified and cert.min_dwell_s < 5.0
    assert not certify(loop, 1.0 / (2 * lambda_R), Ms, 5.0).certified


def test_switches_that_destabilize_are_refused():
    """Three agents on a scalar loop: each topology alone decays, but switching between them every
    0.27 s diverges (exact growth per cycle 1.07); the jumps at the switches make the certificate
    refuse it."""
    loop = scalar_loop()
    a, K = loop.A[0, 0], loop.K[0, 0]
    M1 = np.array([[0.94, 0, 0], [0, 2.15, -2.15], [-9.19, 0, 9.19]])
    M2 = np.array([[4.06, -4.06, 0], [0, 2.86, -2.86], [0, -4.09, 5.84]])
    c, T = 0.43, 0.27
    for M in (M1, M2):
        assert np.linalg.eigvals(a * np.eye(3) - c * K * M).real.max() < 0
        assert certify(loop, c, [M], T).certified
    assert monodromy_radius(loop, c, [M1, M2], T) > 1.05
    assert not certify(loop, c, [M1, M2], T).certified
