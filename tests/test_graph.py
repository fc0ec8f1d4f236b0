"""Graphs: Laplacian and pinning, Assumption 1, the topology families, switching."""

import math

import numpy as np
import pytest

from triswarm.protocol import graph
from triswarm.protocol.graph import GraphError, Schedule, Topology


def test_laplacian_of_a_small_directed_graph():
    # 1 -> 2, 1 -> 3, 2 -> 3; leader -> 1
    t = Topology.from_edges("t", 3, [(1, 2), (1, 3), (2, 3)], pinned=[1])
    assert np.array_equal(t.adjacency, [[0, 0, 0], [1, 0, 0], [1, 1, 0]])
    assert np.array_equal(t.laplacian, [[0, 0, 0], [-1, 1, 0], [-1, -1, 2]])
    assert np.allclose(t.laplacian @ np.ones(3), 0)  # Lemma 1: 1_N is a right null vector
    assert np.allclose(np.sort(t.eigenvalues().real), [1, 1, 2])  # triangular: the diagonal
    assert list(t.in_neighbours(2)) == [0, 1]


def test_graph_without_spanning_tree_is_refused():
    # agents 3 and 4 form a separate component
    t = Topology.from_edges("split", 4, [(1, 2), (3, 4)], pinned=[1])
    assert not t.has_spanning_tree()
    with pytest.raises(GraphError, match=r"split violates Assumption 1: no directed path from the leader to agents 3, 4"):
        t.check_assumption_1()


def test_spanning_tree_whose_root_is_not_pinned_is_refused():
    t = Topology.from_edges("unpinned-root", 3, [(1, 2), (2, 3)], pinned=[2])
    assert t.has_spanning_tree()
    with pytest.raises(GraphError, match="agent 1$"):
        t.check_assumption_1()


def test_assumption_1_is_equivalent_to_stable_L_plus_G(rng):
    """Random digraphs: every agent reachable from the leader <=> all eigenvalues of L + G in Re > 0."""
    for _ in range(300):
        n = int(rng.integers(2, 8))
        A = (rng.uniform(size=(n, n)) < 0.3).astype(float)
        np.fill_diagonal(A, 0)
        g = (rng.uniform(size=n) < 0.3).astype(float)
        t = Topology("r", A, g)
        ok = t.reachable_from_leader().all()
        assert ok == (t.eigenvalues().real.min() > 1e-9)


@pytest.mark.parametrize("n", range(1, 21))
def test_families_satisfy_assumption_1_for_any_size(n):
    for make in graph.FAMILIES.values():
        t = make(n)
        t.check_assumption_1()
        assert t.eigenvalues().real.min() >= 0.5


def test_the_paper_scenario_graphs():
    two_chain, tri, rev = (f(6) for f in graph.PAPER_FAMILIES.values())
    assert np.allclose(np.sort(two_chain.eigenvalues().real), [1, 2, 2, 2, 2, 2])
    assert np.iscomplexobj(tri.eigenvalues()) and np.abs(tri.eigenvalues().imag).max() > 0.5
    assert tri.eigenvalues().real.min() == pytest.approx(0.534, abs=1e-3)
    assert list(np.flatnonzero(rev.pinning)) == [4, 5]
    # losing any one agent leaves the two chains connected to the leader
    for t in (two_chain, rev):
        for k in range(6):
            keep = [i for i in range(6) if i != k]
            Topology("minus", t.adjacency[np.ix_(keep, keep)], t.pinning[keep]).check_assumption_1()


def test_switching_schedule_cycles_every_period():
    ts = tuple(f(6) for f in graph.PAPER_FAMILIES.values())
    s = Schedule(ts, 5.0)
    assert [s.index_at(t) for t in (0, 4.99, 5.0, 9.99, 10.0, 15.0, 31.0)] == [0, 0, 1, 1, 2, 0, 0]
    with pytest.raises(GraphError):
        Schedule(ts, float("nan"))
    with pytest.raises(GraphError, match="same number of agents"):
        Schedule((graph.two_chain(3), graph.two_chain(4)), 5.0)


@pytest.mark.parametrize("A,g,msg", [
    (np.ones((2, 2)), np.ones(2), "self loop"),
    (np.array([[0, -1.0], [1, 0]]), np.ones(2), "non-negative"),
    (np.zeros((2, 3)), np.ones(2), "square"),
    (np.zeros((2, 2)), np.ones(3), "one entry per agent"),
    (np.array([[0, np.nan], [1, 0]]), np.ones(2), "finite"),
])
def test_malformed_topologies_are_refused(A, g, msg):
    with pytest.raises(GraphError, match=msg):
        Topology("bad", A, g)


def test_reachable_through_present_agents_only():
    """The paper's triangles on six drones without agent 2: agent 3 hears only 2, so it alone is
    cut off; in the two-chain every other agent still has a path."""
    from triswarm.protocol.graph import triangles, two_chain

    present = np.array([True, False, True, True, True, True])
    assert triangles(6).reachable_from_leader(present).tolist() == [True, False, False, True, True, True]
    assert two_chain(6).reachable_from_leader(present).tolist() == [True, False, True, True, True, True]
    assert triangles(6).reachable_from_leader().all()


RING_SIZES = list(range(1, 130)) + [200, 333, 1000]


def ring_distance(i, j, n):
    return min((i - j) % n, (j - i) % n)


@pytest.mark.parametrize("n", RING_SIZES)
def test_ring_trees_scale(n):
    """Three pinned agents, every other agent hears two, depth at most log2(N / 3) + 2, the same
    levels in every variant and every edge climbing a level (acyclic, so every eigenvalue of L + G
    is 1: each agent averages what it hears), and the loss of any one agent leaves every other
    agent a path from the leader."""
    level, _ = graph.ring_levels(n)
    assert level.max() <= (math.log2(n / 3) + 2 if n > 3 else 0)
    for make in graph.RING_FAMILIES.values():
        t = make(n)
        assert t.pinning.sum() == min(3, n) and set(np.flatnonzero(t.pinning)) == set(np.flatnonzero(level == 0))
        heard = t.adjacency > 0
        if n >= 3:
            assert np.all(heard.sum(axis=1)[level > 0] == 2)
        assert np.allclose(t.adjacency.sum(axis=1)[level > 0], 1.0)  # weights 1/in-degree
        rows, cols = np.nonzero(heard)
        assert np.all(level[cols] < level[rows])  # every edge climbs a level
        assert np.allclose(np.diag(t.L_plus_G), 1.0)
        t.check_assumption_1()
        for lost in range(n if n <= 333 else 0):  # (1000 agents: 16 s of closures; the proof is by levels)
            present = np.arange(n) != lost
            assert t.reachable_from_leader(present)[present].all(), (t.name, lost)


@pytest.mark.parametrize("n", [7, 50, 200])
def test_ring_tree_agents_hear_their_nearest_lower_level_agents_on_the_ring(n):
    """Locality on the ring (index order is ring order on a rotating polygon): in ring-tree each
    agent hears the nearest lower-level agent on each side; in the one-sided variants, the nearest
    two on that side."""
    level, _ = graph.ring_levels(n)
    for name, side in (("ring-tree", "both"), ("ring-tree-left", -1), ("ring-tree-right", 1)):
        t = graph.FAMILIES[name](n)
        for i in np.flatnonzero(level > 0):
            heard = set(t.in_neighbours(i))
            lower = [j for j in range(n) if level[j] < level[i]]
            if side == "both":
                left = min(lower, key=lambda j: (i - j) % n)
                right = min(lower, key=lambda j: (j - i) % n)
                assert heard == {left, right}
            else:
                by_side = sorted(lower, key=lambda j: (side * (j - i)) % n)
                assert heard == set(by_side[:2])
        gap = n / 3
        assert max(ring_distance(i, j, n) for i in range(n) for j in t.in_neighbours(i)) <= 2 * gap


def test_default_families_by_size():
    assert graph.default_families(6) == list(graph.PAPER_FAMILIES)
    assert graph.default_families(graph.PAPER_FAMILIES_MAX_AGENTS) == list(graph.PAPER_FAMILIES)
    assert graph.default_families(graph.PAPER_FAMILIES_MAX_AGENTS + 1) == list(graph.RING_FAMILIES)
