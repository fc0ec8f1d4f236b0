"""Graphs: Laplacian and pinning, Assumption 1, the topology families, switching."""

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
    two_chain, tri, rev = (f(6) for f in graph.FAMILIES.values())
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
    ts = tuple(f(6) for f in graph.FAMILIES.values())
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
