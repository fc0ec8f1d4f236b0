"""Communication graphs of the swarm: adjacency, Laplacian, pinning, Assumption 1, switching.

Convention: ``adjacency[i, j] > 0`` means agent i receives agent j's estimate (j is an in-neighbour
of i), which is how a_ij enters the protocol (72). Agents are indexed from 0 here and numbered from
1 for people. ``pinning[i] = g_i > 0`` means agent i receives the leader's state.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .errors import GraphError


def _agents(indices) -> str:
    return ", ".join(str(i + 1) for i in indices)


@dataclass(frozen=True)
class Topology:
    name: str
    adjacency: np.ndarray
    pinning: np.ndarray

    def __post_init__(self) -> None:
        A = np.array(self.adjacency, dtype=float)
        g = np.array(self.pinning, dtype=float)
        if A.ndim != 2 or A.shape[0] != A.shape[1]:
            raise GraphError(f"topology {self.name}: adjacency must be a square matrix, got shape {A.shape}")
        if g.shape != (A.shape[0],):
            raise GraphError(f"topology {self.name}: pinning must have one entry per agent ({A.shape[0]})")
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(g))):
            raise GraphError(f"topology {self.name}: weights must be finite")
        if np.any(A < 0) or np.any(g < 0):
            raise GraphError(f"topology {self.name}: weights must be non-negative")
        if np.any(np.diag(A) != 0):
            raise GraphError(f"topology {self.name}: an agent cannot be its own neighbour (self loop)")
        A.setflags(write=False)
        g.setflags(write=False)
        object.__setattr__(self, "adjacency", A)
        object.__setattr__(self, "pinning", g)

    @classmethod
    def from_edges(cls, name: str, n_agents: int, edges: Sequence[tuple[int, int]], pinned: Sequence[int],
                   weight: float = 1.0) -> "Topology":
        """Edges (j, i) with agents numbered from 1: information flows from j to i. Agent 0 is the leader."""
        A = np.zeros((n_agents, n_agents))
        g = np.zeros(n_agents)
        for j, i in edges:
            if not (1 <= i <= n_agents) or not (0 <= j <= n_agents):
                raise GraphError(f"topology {name}: edge ({j}, {i}) names an agent outside 0..{n_agents}")
            if j == 0:
                g[i - 1] = weight
            else:
                A[i - 1, j - 1] = weight
        for i in pinned:
            if not (1 <= i <= n_agents):
                raise GraphError(f"topology {name}: pinned agent {i} is outside 1..{n_agents}")
            g[i - 1] = weight
        return cls(name, A, g)

    @property
    def n_agents(self) -> int:
        return self.adjacency.shape[0]

    @cached_property
    def in_degree(self) -> np.ndarray:
        d = self.adjacency.sum(axis=1)
        d.setflags(write=False)
        return d

    @property
    def laplacian(self) -> np.ndarray:
        """L = D - A with D the in-degree matrix."""
        return np.diag(self.in_degree) - self.adjacency

    @property
    def L_plus_G(self) -> np.ndarray:
        return self.laplacian + np.diag(self.pinning)

    def eigenvalues(self) -> np.ndarray:
        """Eigenvalues of L + G, sorted by real part."""
        lam = np.linalg.eigvals(self.L_plus_G)
        return lam[np.argsort(lam.real, kind="stable")]

    def in_neighbours(self, i: int) -> np.ndarray:
        """Indices j (from 0) that agent i (from 0) listens to."""
        return np.flatnonzero(self.adjacency[i] > 0)

    def reachable_from_leader(self, present: np.ndarray | None = None) -> np.ndarray:
        """Boolean mask of agents with a directed path from the leader; with ``present`` (a boolean
        mask), through present agents only (absent agents neither relay nor count)."""
        if present is None:
            return _closure(self.adjacency, self.pinning > 0)
        present = np.asarray(present, dtype=bool)
        return _closure(self.adjacency * present[None, :] * present[:, None], (self.pinning > 0) & present)

    def has_spanning_tree(self) -> bool:
        """True if some agent reaches every agent along directed edges (ignoring the leader)."""
        n = self.n_agents
        return any(_closure(self.adjacency, np.arange(n) == root).all() for root in range(n))

    def check_assumption_1(self) -> None:
        """Assumption 1: a spanning tree whose root hears the leader; equivalently every agent has a
        directed path from the leader, which makes every eigenvalue of L + G lie in Re > 0."""
        missing = np.flatnonzero(~self.reachable_from_leader())
        if missing.size:
            raise GraphError(
                f"topology {self.name} violates Assumption 1: no directed path from the leader to "
                f"agent{'s' if missing.size > 1 else ''} {_agents(missing)}"
            )


@dataclass(frozen=True)
class Schedule:
    """Topologies used in turn, each for ``period_s`` seconds, starting at t = 0 and cycling."""

    topologies: tuple[Topology, ...]
    period_s: float

    def __post_init__(self) -> None:
        if not self.topologies:
            raise GraphError("a switching schedule needs at least one topology")
        n = {t.n_agents for t in self.topologies}
        if len(n) != 1:
            raise GraphError(f"all topologies of a schedule must have the same number of agents, got {sorted(n)}")
        if not (np.isfinite(self.period_s) and self.period_s > 0):
            raise GraphError(f"switching period must be a positive number of seconds, got {self.period_s!r}")

    @property
    def n_agents(self) -> int:
        return self.topologies[0].n_agents

    def index_at(self, t_s: float) -> int:
        if t_s < 0:
            return 0
        return int(t_s // self.period_s) % len(self.topologies)

    def at(self, t_s: float) -> Topology:
        return self.topologies[self.index_at(t_s)]

    def check(self) -> None:
        for topo in self.topologies:
            topo.check_assumption_1()


def _pins(n: int, *agents: int) -> list[int]:
    return sorted({a for a in agents if 1 <= a <= n})


def two_chain(n: int) -> Topology:
    """Agents 1 and 2 hear the leader; agent i >= 3 hears i-1 and i-2; agent 2 also hears 1.
    Acyclic, so L + G is triangular with eigenvalues 1 and 2."""
    edges = [(1, 2)] if n >= 2 else []
    edges += [(j, i) for i in range(3, n + 1) for j in (i - 1, i - 2)]
    return Topology.from_edges("two-chain", n, edges, _pins(n, 1, 2))


def reverse_two_chain(n: int) -> Topology:
    """The two-chain run backwards: agents N and N-1 hear the leader, agent i hears i+1 and i+2."""
    edges = [(n, n - 1)] if n >= 2 else []
    edges += [(j, i) for i in range(1, n - 1) for j in (i + 1, i + 2)]
    return Topology.from_edges("reverse-two-chain", n, edges, _pins(n, n, n - 1))


def triangles(n: int) -> Topology:
    """Agents in groups of three (1-2-3, 4-5-6, ...), each group a directed cycle a->b->c->a; agent
    i >= 4 also hears agent i-3; agents 1 and 2 hear the leader. Cyclic: L + G has complex
    eigenvalues, and their spread does not grow with N."""
    edges = []
    for start in range(1, n + 1, 3):
        group = list(range(start, min(start + 3, n + 1)))
        if len(group) == 3:
            edges += [(group[0], group[1]), (group[1], group[2]), (group[2], group[0])]
        elif len(group) == 2:
            edges += [(group[0], group[1])]
    edges += [(i - 3, i) for i in range(4, n + 1)]
    return Topology.from_edges("triangles", n, edges, _pins(n, 1, 2))


PAPER_FAMILIES = {"two-chain": two_chain, "triangles": triangles, "reverse-two-chain": reverse_two_chain}
"""The case study's three families, defined for any N: every agent hears two others (or the leader)
when N >= 3, so removing any one agent leaves Assumption 1 intact in the two chains. Their depth
from the leader grows like N/2, and switching between the two chains (opposite root ends) makes
transients grow with N: use them for small swarms only (``default_families``)."""

RING_ROOTS = 3
"""Agents pinned to the leader in the ring trees: spread evenly around the ring."""


def ring_levels(n: int, roots: int = RING_ROOTS) -> tuple[np.ndarray, np.ndarray]:
    """The levels of the ring trees: ``roots`` agents spread evenly by index (for a rotating
    polygon, index order is ring order) are level 0; then, recursively, the agent halfway along
    each gap between two placed agents joins the next level. Returns (level (N,), bounds (N, 2)):
    bounds[i] are the agents (from 0) that bound the gap agent i halves, -1 for the roots. Depth is
    about log2(N / roots) + 1."""
    r = min(roots, n)
    root_idx = [(k * n) // r for k in range(r)]
    level = np.full(n, -1)
    bounds = np.full((n, 2), -1)
    level[root_idx] = 0
    gaps = [(root_idx[k], root_idx[(k + 1) % r] + (n if k + 1 == r else 0)) for k in range(r)]
    while gaps:
        nxt = []
        for a, b in gaps:  # agents strictly between a and b (indices mod n) are not placed yet
            if b - a < 2:
                continue
            mid = (a + b) // 2
            level[mid % n] = 1 + max(level[a % n], level[b % n])
            bounds[mid % n] = (a % n, b % n)
            nxt += [(a, mid), (mid, b)]
        gaps = nxt
    return level, bounds


def _ring_tree(name: str, n: int, side: str) -> Topology:
    """A ring tree: the roots hear the leader; every other agent hears two agents of lower levels,
    with weight 1/2 each, so every agent averages what it hears and every eigenvalue of L + G is 1.
    ``side`` picks them: "both" the two agents bounding its gap (its nearest lower-level agents on
    each side of the ring); "left"/"right" the nearest two lower-level agents on that side. All
    three share the levels, are acyclic along them, and every non-root agent hears two distinct
    agents of lower levels, so losing any one agent leaves every other agent a path from the leader."""
    level, bounds = ring_levels(n)
    A = np.zeros((n, n))
    g = (level == 0).astype(float)
    for i in np.flatnonzero(level > 0):
        lower = np.flatnonzero(level < level[i])
        if side == "both":
            heard = list(bounds[i])
        else:
            step = -1 if side == "left" else 1
            ring = [(i + step * k) % n for k in range(1, n)]
            heard = [j for j in ring if level[j] < level[i]][:2]
        heard = sorted(set(heard))
        if not heard or not set(heard) <= set(lower):
            raise AssertionError(f"ring tree {name}: agent {i + 1} would hear {heard}, not lower-level agents")
        A[i, heard] = 1.0 / len(heard)
    return Topology(name, A, g)


def ring_tree(n: int) -> Topology:
    """Each non-root agent hears the two agents bounding the gap it halves (see ``_ring_tree``)."""
    return _ring_tree("ring-tree", n, "both")


def ring_tree_left(n: int) -> Topology:
    """Each non-root agent hears the nearest two lower-level agents before it on the ring."""
    return _ring_tree("ring-tree-left", n, "left")


def ring_tree_right(n: int) -> Topology:
    """Each non-root agent hears the nearest two lower-level agents after it on the ring."""
    return _ring_tree("ring-tree-right", n, "right")


RING_FAMILIES = {"ring-tree": ring_tree, "ring-tree-left": ring_tree_left, "ring-tree-right": ring_tree_right}
"""Families whose depth grows like log2 N, with three pinned agents and two in-neighbours each.
They share their levels, so one diagonal Lyapunov function serves all three and any switching
between them is certified (``certificate``)."""

FAMILIES = {**PAPER_FAMILIES, **RING_FAMILIES}
"""Every topology family defined for any number of agents, by name."""

PAPER_FAMILIES_MAX_AGENTS = 6
"""``default_families``: up to this many drones, the paper's three families; above, the ring trees."""


def default_families(n: int) -> list[str]:
    """The families a plan that names none switches between: the paper's three for the case study's
    size (N <= PAPER_FAMILIES_MAX_AGENTS), the ring trees above, where the chains' depth N/2 makes
    their transients grow too large to certify (with the default coupling margin the certificate
    vouches for the paper's three up to 8 drones)."""
    return list(PAPER_FAMILIES if n <= PAPER_FAMILIES_MAX_AGENTS else RING_FAMILIES)


def _closure(adjacency: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """The agents reached from ``seed`` (a boolean mask) along edges j -> i with adjacency[i, j] > 0."""
    reached = seed.copy()
    frontier = reached.copy()
    while frontier.any():
        new = (adjacency[:, frontier] > 0).any(axis=1) & ~reached
        reached |= new
        frontier = new
    return reached
