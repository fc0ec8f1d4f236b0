"""A certificate that the formation error of the switched swarm decays, and how much it can grow first.

With the RFL exact, each drone is x_r' = A_r x_r + B_r v, and under the protocol (72) with exact
states the formation error delta = xi - 1 (x) x0 obeys

    delta' = (I (x) A_r - c M_sigma (x) B_r K) delta,      M_sigma = L_sigma + G_sigma,

with K = R^-1 B_r^T P from the Riccati equation A_r^T P + P A_r - P B_r R^-1 B_r^T P + Q = 0.
Eigenvalues of M_sigma say whether each topology alone converges; they do not bound the transient,
and switching between topologies can make a schedule diverge although every topology converges.

Candidate Lyapunov functions V_sigma = delta^T (Theta_sigma (x) P) delta, Theta_sigma > 0 (N x N):

* Flow. If Theta M + M^T Theta >= 2 mu Theta (mu is the smallest generalized eigenvalue of
  (sym(Theta M), Theta)), then with S = P B_r R^-1 B_r^T P and the Riccati equation,
  V' <= -delta^T (Theta (x) (Q + (2 c mu - 1) S)) delta <= -beta V, with beta the smallest
  generalized eigenvalue of (Q + (2 c mu - 1) S, P). beta may be negative (V may grow).
* Switch sigma -> sigma': V_sigma' <= rho V_sigma, rho the largest generalized eigenvalue of
  (Theta_sigma', Theta_sigma).
* A periodic schedule (each topology for T seconds, in turn) therefore multiplies V by at most
  G = prod_k rho_k exp(-beta_k T) per cycle: the schedule is certified when G < 1. With one Theta
  for every topology, rho = 1 and all beta_k > 0 certify any switching whatsoever.

Any positive Theta gives a sound bound; the choice only changes how conservative it is, so a few
families of candidates are tried and the best kept (``certify``). Pure math: arrays in, arrays out.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg

MAX_THETA_CONDITION = 1e10
"""Candidates Theta with a larger condition number are numerically meaningless and are dropped."""
LYAPUNOV_SHARES = (0.3, 0.5, 0.7, 0.8, 0.9, 0.95)
"""Candidate family (a): Theta_k solves Theta (M_k - mu I) + (M_k - mu I)^T Theta = I with
mu = share * lambda_R(M_k)."""
DIAGONAL_RATIOS = (0.5, 0.25, 0.125, 0.0625)
"""Candidate family (b): diagonal Theta with theta_i = ratio ** depth_i (depth from the leader); a
ratio too small for a deep graph is raised to the smallest that keeps Theta usable."""
LYAPUNOV_MAX_AGENTS = 400
"""Family (a) costs O(N^3) per topology and share; above this size, and once a common diagonal
Theta certifies any switching, it is not tried."""


@dataclass(frozen=True)
class LoopMatrices:
    """The nominal single-drone loop: x' = A x + B v, LQR weights Q, R, Riccati solution P."""

    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    P: np.ndarray

    @property
    def K(self) -> np.ndarray:
        return np.linalg.solve(self.R, self.B.T @ self.P)

    @property
    def S(self) -> np.ndarray:
        S = self.P @ self.B @ np.linalg.solve(self.R, self.B.T @ self.P)
        return 0.5 * (S + S.T)

    def decay_rate(self, m: float) -> float:
        """beta(m): the smallest generalized eigenvalue of (Q + (m - 1) S, P): V = x^T P x decays at
        least at rate beta under x' = (A - m B K) x when m = 2 c mu."""
        return float(scipy.linalg.eigh(self.Q + (m - 1.0) * self.S, self.P, eigvals_only=True)[0])


@dataclass(frozen=True)
class Bound:
    """What one choice of Theta_k proves about the schedule (each topology ``period_s``, in turn)."""

    candidate: str
    """Which Theta: its family and parameter."""
    period_s: float
    mu: np.ndarray
    """(m,): Theta_k M_k + M_k^T Theta_k >= 2 mu_k Theta_k."""
    beta_1_s: np.ndarray
    """(m,): V decays at least at this rate [1/s] while topology k is in force (negative: grows)."""
    rho: np.ndarray
    """(m,): V may jump by this factor at the switch from topology k to k+1 (cyclically)."""
    theta_max: np.ndarray
    """(m,): largest eigenvalue of Theta_k."""
    theta_min: np.ndarray
    """(m,): smallest eigenvalue of Theta_k."""
    cond_P: float

    @property
    def log_growth_per_cycle(self) -> float:
        """ln G: V is multiplied by at most G over each cycle of the schedule."""
        return float(np.sum(np.log(self.rho)) - np.sum(self.beta_1_s) * self.period_s)

    @property
    def certified(self) -> bool:
        return self.log_growth_per_cycle < -1e-9

    @property
    def any_switching(self) -> bool:
        """One Lyapunov function for every topology, decreasing in each: any switching signal."""
        return bool(np.all(self.rho <= 1.0) and np.all(self.beta_1_s > 0))

    @property
    def min_dwell_s(self) -> float:
        """The shortest period for which this Theta certifies the schedule (inf: none)."""
        total = float(np.sum(self.beta_1_s))
        if total <= 0:
            return math.inf
        return max(0.0, float(np.sum(np.log(self.rho))) / total)

    def envelope(self, t_s) -> np.ndarray:
        """Bound on ||delta(t)|| / ||delta(0)|| for a start at t = 0 at the start of the first
        topology (how a plan runs its schedule), t >= 0."""
        return np.exp(self.log_envelope(t_s))

    def log_envelope(self, t_s) -> np.ndarray:
        """ln of ``envelope`` (which overflows where an uncertified bound grows)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        m, T = len(self.rho), self.period_s
        k = np.floor(t / T).astype(int)
        steps = np.log(self.rho) - self.beta_1_s * T  # interval j, then the switch j -> j+1
        starts = np.concatenate([[0.0], np.cumsum(steps[np.arange(int(k.max(initial=0))) % m])])
        log_v = starts[k] - self.beta_1_s[k % m] * (t - k * T)
        return 0.5 * (np.log(self.cond_P * self.theta_max[0] / self.theta_min[k % m]) + log_v)

    @property
    def transient_bound(self) -> float:
        """sup over t, and over a start at any phase of the schedule, of ||delta(t)|| / ||delta(0)||;
        inf when this Theta does not certify the schedule."""
        if not self.certified:
            return math.inf
        m, T = len(self.rho), self.period_s
        worst = 0.0
        for s in range(m):
            log_v = max(0.0, -self.beta_1_s[s] * T)  # however long the start's topology still runs
            for j in range(m + 1):  # j = m: the start's topology again, after a whole cycle
                k = (s + j) % m
                here = log_v
                if j:
                    log_v += math.log(self.rho[(k - 1) % m])
                    here = log_v + max(0.0, -self.beta_1_s[k] * T)
                    log_v -= self.beta_1_s[k] * T
                worst = max(worst, here + math.log(self.theta_max[s] / self.theta_min[k]))
        return math.sqrt(self.cond_P * math.exp(worst))


@dataclass(frozen=True)
class Certificate:
    """Every candidate's bound for one schedule. Each is a valid bound on its own, so the best of
    each figure holds: the fastest decay, the smallest transient, the shortest dwell time."""

    topology_names: tuple[str, ...]
    period_s: float
    c: float
    bounds: tuple[Bound, ...]

    @property
    def best(self) -> Bound | None:
        """The bound with the fastest decay per cycle (None: no candidate was usable)."""
        return min(self.bounds, key=lambda b: b.log_growth_per_cycle, default=None)

    @property
    def log_growth_per_cycle(self) -> float:
        return math.inf if self.best is None else self.best.log_growth_per_cycle

    @property
    def certified(self) -> bool:
        return self.best is not None and self.best.certified

    @property
    def any_switching(self) -> bool:
        return any(b.any_switching for b in self.bounds)

    @property
    def cycle_s(self) -> float:
        return self.period_s * len(self.topology_names)

    @property
    def decay_rate_1_s(self) -> float:
        """Average exponential decay rate of ||delta|| the bound certifies (negative: growth)."""
        return -0.5 * self.log_growth_per_cycle / self.cycle_s

    @property
    def transient_bound(self) -> float:
        return min((b.transient_bound for b in self.bounds), default=math.inf)

    @property
    def min_dwell_s(self) -> float:
        return min((b.min_dwell_s for b in self.bounds), default=math.inf)

    def envelope(self, t_s) -> np.ndarray:
        """The smallest of the bounds' envelopes (each holds)."""
        log_env = np.min([b.log_envelope(t_s) for b in self.bounds] or [np.full(np.size(t_s), np.inf)], axis=0)
        return np.exp(np.minimum(log_env, 700.0))

    def summary(self) -> dict:
        best = self.best
        out = {
            "certified": self.certified,
            "any_switching": self.any_switching,
            "switch_period_s": self.period_s,
            "c": self.c,
            "growth_per_cycle": math.exp(min(self.log_growth_per_cycle, 700.0)),
            "log_growth_per_cycle": self.log_growth_per_cycle,
            "decay_rate_1_s": self.decay_rate_1_s,
            "transient_bound": self.transient_bound,
            "min_dwell_s": self.min_dwell_s,
        }
        if best is not None:
            out.update({"best_candidate": best.candidate,
                        "mu": dict(zip(self.topology_names, best.mu.tolist())),
                        "beta_1_s": dict(zip(self.topology_names, best.beta_1_s.tolist())),
                        "rho": dict(zip(self.topology_names, best.rho.tolist()))})
        return out


def _heard(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(heard[i, j]: i hears j, pinned[i]) from M = L + G."""
    n = M.shape[0]
    heard = (M != 0) & ~np.eye(n, dtype=bool)
    pinned = np.diag(M) - np.where(heard, -M, 0.0).sum(axis=1) > 1e-12
    return heard, pinned


def depths(M: np.ndarray) -> np.ndarray:
    """Fewest hops from the leader to each agent along the graph of M = L + G (pinned agents at
    depth 0; unreachable agents at depth N)."""
    heard, pinned = _heard(M)
    n = M.shape[0]
    depth = np.full(n, n)
    depth[pinned] = 0
    frontier = pinned.copy()
    d = 0
    while frontier.any():
        d += 1
        new = heard[:, frontier].any(axis=1) & (depth == n)
        depth[new] = d
        frontier = new
    return depth


def levels(M: np.ndarray) -> np.ndarray | None:
    """Most hops from the leader to each agent (the longest path, so every edge goes from a lower
    to a higher level), or None if the graph has a directed cycle or an unreachable agent."""
    heard, pinned = _heard(M)
    n = M.shape[0]
    level = np.zeros(n, dtype=int)
    remaining = heard.sum(axis=1)
    ready = list(np.flatnonzero(remaining == 0))
    if not np.all(pinned[ready]):
        return None
    done = 0
    while ready:
        j = ready.pop()
        done += 1
        for i in np.flatnonzero(heard[:, j]):
            level[i] = max(level[i], level[j] + 1)
            remaining[i] -= 1
            if remaining[i] == 0:
                ready.append(i)
    return level if done == n else None


def _lyapunov_theta(M: np.ndarray, mu: float) -> np.ndarray | None:
    n = M.shape[0]
    try:
        theta = scipy.linalg.solve_continuous_lyapunov((M - mu * np.eye(n)).T, np.eye(n))
    except (np.linalg.LinAlgError, ValueError):
        return None
    return 0.5 * (theta + theta.T)


def _usable(theta: np.ndarray) -> tuple[float, float] | None:
    """(smallest, largest) eigenvalue of a candidate Theta, or None if it is not clearly positive
    definite or too ill-conditioned to mean anything."""
    if not np.all(np.isfinite(theta)):
        return None
    lam = np.sort(np.diag(theta)) if _is_diagonal(theta) else np.linalg.eigvalsh(theta)
    if lam[0] <= 0 or lam[-1] / lam[0] > MAX_THETA_CONDITION:
        return None
    return float(lam[0]), float(lam[-1])


def _mu(theta: np.ndarray, M: np.ndarray) -> float:
    """The largest mu with Theta M + M^T Theta >= 2 mu Theta."""
    if _is_diagonal(theta):  # Theta^-1/2 sym(Theta M) Theta^-1/2, in O(N^2) before the eigenvalues
        t = np.diag(theta)
        TM = t[:, None] * M
        d = 1.0 / np.sqrt(t)
        return float(np.linalg.eigvalsh(0.5 * (TM + TM.T) * np.outer(d, d))[0])
    return float(scipy.linalg.eigh(0.5 * (theta @ M + M.T @ theta), theta, eigvals_only=True)[0])


def _is_diagonal(theta: np.ndarray) -> bool:
    return not np.any(theta - np.diag(np.diag(theta)))


def _rho(theta_to: np.ndarray, theta_from: np.ndarray) -> float:
    """Largest generalized eigenvalue of (Theta_to, Theta_from): V_to <= rho V_from."""
    if theta_to is theta_from:
        return 1.0
    if _is_diagonal(theta_to) and _is_diagonal(theta_from):
        return float(np.max(np.diag(theta_to) / np.diag(theta_from)))
    return float(scipy.linalg.eigh(theta_to, theta_from, eigvals_only=True)[-1])


def _diagonal_candidates(Ms: Sequence[np.ndarray]):
    """(name, [Theta_k]) with Theta_k = diag(ratio ** depth) (family (b)), per topology and common."""
    union = sum(Ms)  # L + G of the union graph (weights add)
    lv = [levels(M) for M in Ms]
    if all(x is not None for x in lv):  # acyclic: every edge climbs a level
        orders = [("level", lv, levels(union))]
    else:
        orders = [("depth", [depths(M) for M in Ms], depths(union))]
    for what, per_topology, common in orders:
        same = all(np.array_equal(d, per_topology[0]) for d in per_topology)
        deepest = max(int(d.max()) for d in [*per_topology, common] if d is not None)
        # the smallest ratio a graph this deep allows (condition number MAX_THETA_CONDITION)
        floor = MAX_THETA_CONDITION ** (-1.0 / deepest) * (1 + 1e-9) if deepest else 0.0
        for r in sorted({max(r, floor) for r in DIAGONAL_RATIOS}):
            if same:  # one object for all: rho = 1 exactly
                yield f"common diagonal {r:g}^{what}", [np.diag(r ** per_topology[0].astype(float))] * len(Ms)
                continue
            yield f"diagonal {r:g}^{what} per topology", [np.diag(r ** d.astype(float)) for d in per_topology]
            if common is not None:
                yield f"common diagonal {r:g}^{what}", [np.diag(r ** common.astype(float))] * len(Ms)


def _lyapunov_candidates(Ms: Sequence[np.ndarray], wanted):
    """(name, [Theta_k]) from the Lyapunov equation of each M_k shifted by a share of its lambda_R
    (family (a)), while ``wanted()``."""
    if not wanted():
        return
    lam_R = [float(np.linalg.eigvals(M).real.min()) for M in Ms]
    for share in LYAPUNOV_SHARES:
        thetas = [_lyapunov_theta(M, share * lam) for M, lam in zip(Ms, lam_R)]
        if all(t is not None for t in thetas):
            yield f"Lyapunov (M - {share:g} lambda_R I)", thetas


def certify(loop: LoopMatrices, c: float, Ms: Sequence[np.ndarray], period_s: float,
            names: Sequence[str] | None = None) -> Certificate:
    """Bounds for topologies ``Ms`` (L + G each, N x N), each held ``period_s`` in turn, with
    coupling gain ``c``, from every usable candidate Theta."""
    if not Ms:
        raise ValueError("a schedule needs at least one topology")
    names = tuple(names) if names is not None else tuple(f"topology-{k + 1}" for k in range(len(Ms)))
    Ms = [np.asarray(M, dtype=float) for M in Ms]
    m, n = len(Ms), Ms[0].shape[0]
    cond_P = float(np.linalg.cond(loop.P))
    beta_of: dict[float, float] = {}

    def beta(mu: float) -> float:
        if mu not in beta_of:
            beta_of[mu] = loop.decay_rate(2.0 * c * mu)
        return beta_of[mu]

    bounds: list[Bound] = []

    def lyapunov_wanted() -> bool:  # family (a) costs O(N^3) per topology; it cannot beat a bound for any switching
        return n <= LYAPUNOV_MAX_AGENTS and not any(b.any_switching for b in bounds)

    for name, thetas in itertools.chain(_diagonal_candidates(Ms), _lyapunov_candidates(Ms, lyapunov_wanted)):
        eig = [_usable(t) for t in thetas]
        if any(e is None for e in eig):
            continue
        mu = np.array([_mu(t, M) for t, M in zip(thetas, Ms)])
        rho = np.array([_rho(thetas[(k + 1) % m], thetas[k]) for k in range(m)])
        bounds.append(Bound(name, float(period_s), mu, np.array([beta(x) for x in mu]), rho,
                            np.array([e[1] for e in eig]), np.array([e[0] for e in eig]), cond_P))
    return Certificate(names, float(period_s), float(c), tuple(bounds))
