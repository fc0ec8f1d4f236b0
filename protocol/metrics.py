"""How well a swarm flew its plan: formation errors against x0 + h_i(t), from any telemetry."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .plan import Plan

PAPER_POSITION_BOUND_M = 0.10
PAPER_ATTITUDE_BOUND_RAD = 0.02


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles to (-pi, pi]."""
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


def formation_errors(plan: Plan, t_s: np.ndarray, position_m: np.ndarray, euler_rad: np.ndarray):
    """Position error norm [m] (T, N) and absolute attitude errors [rad] (T, N, 3) of every drone
    against the plan's reference x0(t) + h_i(t) (the formation, not the entry manoeuvre)."""
    ref = np.stack([plan.reference(float(t))[0] for t in t_s])  # (T, N, 12)
    pos_err = np.linalg.norm(position_m - ref[:, :, 9:12], axis=2)
    att_err = np.abs(wrap_angle(euler_rad - ref[:, :, 6:9]))
    return pos_err, att_err


@dataclass(frozen=True)
class Performance:
    window_start_s: float
    worst_position_m: float
    worst_attitude_rad: float
    worst_position_drone: int
    worst_attitude_drone: int
    convergence_time_s: float | None
    position_bound_m: float
    attitude_bound_rad: float
    worst_position_t_s: float = float("nan")
    """When the worst position error was seen (NaN for an empty window)."""
    worst_attitude_t_s: float = float("nan")

    @property
    def within_bounds(self) -> bool:
        return self.worst_position_m <= self.position_bound_m and self.worst_attitude_rad <= self.attitude_bound_rad

    def as_dict(self) -> dict:
        return {
            "window_start_s": self.window_start_s,
            "worst_position_error_m": self.worst_position_m,
            "worst_position_error_drone": self.worst_position_drone,
            "worst_attitude_error_rad": self.worst_attitude_rad,
            "worst_attitude_error_drone": self.worst_attitude_drone,
            "worst_position_error_t_s": self.worst_position_t_s,
            "worst_attitude_error_t_s": self.worst_attitude_t_s,
            "convergence_time_s": self.convergence_time_s,
            "position_bound_m": self.position_bound_m,
            "attitude_bound_rad": self.attitude_bound_rad,
            "within_bounds": self.within_bounds,
        }


def assess(t_s: np.ndarray, pos_err: np.ndarray, att_err: np.ndarray, window_start_s: float = 25.0,
           position_bound_m: float = PAPER_POSITION_BOUND_M,
           attitude_bound_rad: float = PAPER_ATTITUDE_BOUND_RAD) -> Performance:
    """Worst errors over [window_start_s, end] and the convergence time: the earliest t after which
    every drone stays within both bounds to the end (None if it never does). An empty window (a
    run that ended early) counts as infinitely bad."""
    att_max = att_err.max(axis=2)
    w = t_s >= window_start_s
    t_p = t_a = float("nan")
    if w.any():
        wp, wa, tw = pos_err[w], att_max[w], t_s[w]
        worst_p, worst_a = float(wp.max()), float(wa.max())
        k_p, drone_p = np.unravel_index(np.argmax(wp), wp.shape)
        k_a, drone_a = np.unravel_index(np.argmax(wa), wa.shape)
        drone_p, drone_a, t_p, t_a = int(drone_p) + 1, int(drone_a) + 1, float(tw[k_p]), float(tw[k_a])
    else:
        worst_p = worst_a = float("inf")
        drone_p = drone_a = 0
    ok = (pos_err.max(axis=1) <= position_bound_m) & (att_max.max(axis=1) <= attitude_bound_rad)
    conv = None
    if ok.size and ok[-1]:
        bad = np.flatnonzero(~ok)
        conv = float(t_s[bad[-1] + 1]) if bad.size else float(t_s[0])
    return Performance(window_start_s, worst_p, worst_a, drone_p, drone_a, conv, position_bound_m, attitude_bound_rad,
                       t_p, t_a)


def settled_window_start_s(plan: Plan, end_s: float) -> float:
    """Where a flight of ``plan`` that ends at plan time ``end_s`` is judged from: the plan's settled
    window (the entry's end plus ``check.settle_s``), or the second half of a flight too short to
    reach it."""
    return plan.settled_from_s if plan.settled_from_s < end_s else 0.5 * end_s


def judge(plan: Plan, t_s: np.ndarray, position_m: np.ndarray, euler_rad: np.ndarray,
          window_start_s: float | None = None, position_bound_m: float = PAPER_POSITION_BOUND_M,
          attitude_bound_rad: float = PAPER_ATTITUDE_BOUND_RAD) -> tuple[Performance, list[dict]]:
    """The verdict on a flight of ``plan`` (paper frame, plan time ``t_s``), over [window_start_s,
    end] (by default the plan's settled window: ``settled_window_start_s``), and every drone's
    worst errors there (None where the window is empty) with whether they are within the bounds:
    one verdict for ``sim``, ``plot`` and ``demo``."""
    pos_err, att_err = formation_errors(plan, t_s, position_m, euler_rad)
    start = settled_window_start_s(plan, float(t_s[-1])) if window_start_s is None else float(window_start_s)
    perf = assess(t_s, pos_err, att_err, start, position_bound_m, attitude_bound_rad)
    w = t_s >= start
    rows = []
    for i in range(pos_err.shape[1]):
        worst_p = float(pos_err[w, i].max()) if w.any() else None
        worst_a = float(att_err[w, i].max()) if w.any() else None
        rows.append({"drone": i + 1, "worst_position_error_m": worst_p, "worst_attitude_error_rad": worst_a,
                     "within_bounds": worst_p is not None and worst_p <= position_bound_m
                     and worst_a <= attitude_bound_rad})
    return perf, rows
