"""The per-agent step of the distributed protocol (72)-(73) in discrete time.

Written over a leading agent axis: a companion calls it with N = 1 (its own row), the in-process
simulation with all N agents at once. The only thing that differs is how the caller forms the
neighbour sum  sum_j a_ij xi_j  (a companion from the estimates it received over Zenoh, the
simulation as ``adjacency @ xi``).

Continuous protocol, with xi_i = xhat_i - h_i:
    v_i      = c K ( sum_j a_ij (xi_j - xi_i) + g_i (x0 - xi_i) ) + gamma_i          (72)
    xhat_i'  = A_r xhat_i + B_r v_i + c F (y_i - C_r xhat_i)                            (73)
The observer (73), discretised exactly, and the RFL run in ``controller.FormationController``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels
from .design import Design


@dataclass(frozen=True)
class Reference:
    """What one tick needs from the plan: the time its estimates refer to, the offsets h there,
    the leader x0 there, and gamma (78) at the middle of the interval the command is held for
    (with the leader's own feedforward, zero for a leader that obeys (70))."""

    t_p: float
    h: np.ndarray
    x0: np.ndarray
    gamma: np.ndarray


def reference_at(design: Design, offsets, leader, t: float, lead_s: float, dt_s: float,
                 rows: slice | np.ndarray = slice(None)) -> Reference:
    """``offsets(t)`` and ``leader(t)`` give (h, h_dot) (N, 12) and (x0, x0_dot) (12,)."""
    t_p = t + lead_s
    h, _ = offsets(t_p)
    x0, _ = leader(t_p)
    h_mid, h_mid_dot = offsets(t_p + 0.5 * dt_s)
    x0_mid, x0_mid_dot = leader(t_p + 0.5 * dt_s)
    return Reference(t_p, h[rows], x0, design.gamma(h_mid[rows] + x0_mid, h_mid_dot[rows] + x0_mid_dot))


def consensus_error(xi: np.ndarray, neighbour_sum: np.ndarray, in_degree: np.ndarray, pinning: np.ndarray,
                    x0: np.ndarray) -> np.ndarray:
    """sum_j a_ij (xi_j - xi_i) + g_i (x0 - xi_i), shape (N, 12)."""
    return neighbour_sum - (in_degree + pinning)[:, None] * xi + pinning[:, None] * x0


def protocol_input(d: Design, xi: np.ndarray, neighbour_sum: np.ndarray, in_degree: np.ndarray,
                   pinning: np.ndarray, x0: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """(72): v (N, 6) for agents with estimates-minus-offsets xi (N, 12): c K times
    ``consensus_error``, plus gamma. The other arguments broadcast to N rows (``protocol_rows``)."""
    xi = np.asarray(xi, dtype=float)
    n, m = xi.shape[0], d.K.shape[0]
    return protocol_rows(d, xi, np.broadcast_to(neighbour_sum, xi.shape), np.broadcast_to(in_degree, (n,)),
                         np.broadcast_to(pinning, (n,)), np.broadcast_to(x0, xi.shape), np.broadcast_to(gamma, (n, m)))


def protocol_rows(d: Design, xi: np.ndarray, neighbour_sum: np.ndarray, in_degree: np.ndarray,
                  pinning: np.ndarray, x0: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """(72) with every argument given per row: xi, neighbour_sum, x0 (N, 12), in_degree and pinning
    (N,), gamma (N, 6). Compiled row by row: an agent's v is the same bits whether it is computed
    alone or with others."""
    def c(a):  # (contiguous and writable, as every caller's: a read-only view, a broadcast one, would be
        # another type to the compiled kernel, compiled anew the first time a hold or a landing came)
        return np.require(a, dtype=float, requirements=("C", "W"))

    out = np.empty((xi.shape[0], d.K.shape[0]))
    kernels.protocol_rows(d.cK, c(xi), c(neighbour_sum), c(in_degree), c(pinning), c(x0), c(gamma), out)
    return out


_ORIGIN = np.zeros(12)
_ORIGIN.setflags(write=False)


def no_leader(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The leader of absolute references (a flight controller's own, a companion's hold): at the
    local origin, at rest. Use as ``reference_at(..., leader=no_leader, ...)``."""
    return _ORIGIN, _ORIGIN


def pinned_input(d: Design, xi: np.ndarray, x0: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """(72) for agents that hear nobody and are pinned to the leader x0 alone: v (N, 6)."""
    n = xi.shape[0]
    return protocol_input(d, xi, np.zeros_like(xi), np.zeros(n), np.ones(n), x0, gamma)
