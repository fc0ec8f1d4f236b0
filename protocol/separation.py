"""How close drones come to each other along a reference: the closest pair over a time span.

Sampled every ``step``, with no pair missed between samples. At every sample a k-d tree gives each
drone's nearest neighbour, and every pair closer than ``within_m + speed_bound * step`` is followed
over the half steps on either side of the sample, moving at its sampled relative velocity (the
closest point of a straight line). Two drones slower than ``speed_bound`` close in by at most
speed_bound * step over a half step, so a pair that dips below ``within_m`` anywhere is followed
from its nearest sample; the straight line is off by at most (a1 + a2) (step / 2)^2 / 2 for
accelerations a1, a2 (2.5 cm at 10 m/s^2 and a 0.1 s step). Pure math, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class Approach:
    """The closest two drones came: the distance [m], the pair (numbered from 0), the time [s]."""

    distance_m: float
    pair: tuple[int, int]
    t_s: float


def closest_approach(motion: Callable[[float], tuple[np.ndarray, np.ndarray]], times_s: np.ndarray,
                     speed_bound_m_s: float, within_m: float) -> Approach | None:
    """The closest approach of any two drones over ``times_s`` (evenly spaced; the earliest of
    ties), given their positions [m] and velocities [m/s] (N, 3) each at a time, and a bound on
    every drone's speed.
    Below ``within_m`` it is found to within the straight-line error above; farther pairs are only
    sampled. None for fewer than two drones."""
    times = np.asarray(times_s, dtype=float)
    half = 0.5 * float(times[1] - times[0]) if times.size > 1 else 0.0
    reach = within_m + 2.0 * speed_bound_m_s * half
    best = Approach(math.inf, (-1, -1), math.nan)
    for t in times:
        p, v = (np.asarray(x, dtype=float) for x in motion(float(t)))
        if p.shape[0] < 2:
            return None
        tree = cKDTree(p)
        d, j = tree.query(p, k=2)
        i = int(np.flatnonzero(d[:, 1] <= d[:, 1].min() + TIE_M)[0])  # the lowest-numbered of ties
        best = _closer(best, float(d[i, 1]), i, int(j[i, 1]), float(t))
        pairs = tree.query_pairs(reach, output_type="ndarray")
        if not pairs.size or half == 0.0:
            continue
        r = p[pairs[:, 1]] - p[pairs[:, 0]]
        u = v[pairs[:, 1]] - v[pairs[:, 0]]
        uu = np.einsum("ij,ij->i", u, u)
        tau = np.clip(-np.einsum("ij,ij->i", r, u) / np.where(uu > 0, uu, 1.0), -half, half)
        tau = np.where(uu > 0, tau, 0.0)
        dist = np.linalg.norm(r + u * tau[:, None], axis=1)
        m = int(np.argmin(dist))
        best = _closer(best, float(dist[m]), int(pairs[m, 0]), int(pairs[m, 1]), float(t + tau[m]))
    return best


TIE_M = 1e-6
"""Distances within this of the closest so far count as ties, and the earliest of them is kept (in a
rigid formation every sample ties)."""


def _closer(best: Approach, d: float, i: int, j: int, t: float) -> Approach:
    if d < best.distance_m - TIE_M or (d < best.distance_m + TIE_M and t < best.t_s):
        return Approach(d, (min(i, j), max(i, j)), t)
    return best
