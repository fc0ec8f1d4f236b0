"""Wind at the drones: a steady wind, Dryden turbulence and 1-cosine gusts, in the paper's earth frame
(x north, y west, z up). Pure math: the plant (``sitl/physics.py``) carries the turbulence's state
and draws its noise from a Generator it is given; the drag this wind causes is ``dynamics``'.

Directions are meteorological: ``from_deg`` is where the wind blows from, clockwise from north
(0 from the north, 90 from the east, 270 from the west): a wind from 270 deg blows towards the east,
-y in the paper's frame. ``wind_vector_e`` is the one place that turns a direction into a vector.

Turbulence: the Dryden model of MIL-F-8785C (1980), section 3.7.2, low-altitude form (below
1000 ft), as MIL-HDBK-1797 (1997) repeats it. At height h [ft]:
    sigma_w = 0.1 W20,  sigma_u = sigma_v = sigma_w / (0.177 + 0.000823 h)^0.4      [intensities]
    L_w = h,            L_u = L_v = h / (0.177 + 0.000823 h)^1.2                      [length scales]
where W20 is the wind speed at 20 ft: 15 kt for light, 30 kt for moderate, 45 kt for severe
turbulence. u lies along the mean wind, v across it (horizontal), w vertical. Spectra (8785C):
    u: sigma_u^2 2 L_u / (pi V) / (1 + (L_u w / V)^2)                 (correlation e^(-x/L))
    v, w: sigma^2 L / (pi V) (1 + 3 (L w / V)^2) / (1 + (L w / V)^2)^2  (e^(-x/L) (1 - x / 2L))
with V the speed at which the frozen turbulence passes the drone: the mean wind for a drone that
holds its place (Taylor's hypothesis), at least ``MIN_ADVECTION_M_S``. Each drone gets a
realisation of its own (independent: the conservative choice for a formation, whose drones 10 m
apart would in the air feel partly the same eddies).

Gusts: the discrete 1-cosine gust (as in CS-25.341 / FAR 25.341, in time instead of distance),
    speed(t) = A/2 (1 - cos(2 pi (t - t0) / T))  for t0 <= t <= t0 + T, 0 otherwise,
horizontal, felt by every drone at the same instant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from .airframe import ParameterError, finite_number
from .jit import njit

SEA_LEVEL_AIR_DENSITY_KG_M3 = 1.225
"""ISA sea-level air density."""
KNOT_M_S = 1852.0 / 3600.0
FOOT_M = 0.3048
TURBULENCE_SIGMA_W_M_S = {"none": 0.0, "light": 0.1 * 15 * KNOT_M_S, "moderate": 0.1 * 30 * KNOT_M_S,
                          "severe": 0.1 * 45 * KNOT_M_S}
"""Vertical turbulence intensity sigma_w [m/s] of MIL-F-8785C's levels: 0.1 W20 (0.77, 1.54, 2.32 m/s)."""
MIN_ADVECTION_M_S = 1.0
"""Floor of the speed V at which turbulence passes a drone (calm air would freeze it)."""
TURBULENCE_STATES = 5
"""Dryden state per drone: u (1), v (2), w (2)."""


@dataclass(frozen=True)
class Gust:
    """One 1-cosine gust (module docstring)."""

    speed_m_s: float
    """Peak speed A, reached halfway through."""
    duration_s: float
    """Duration T, from calm back to calm."""
    start_s: float
    """Start t0 on the simulation's clock."""
    from_deg: float | None = None
    """Where it blows from (meteorological); None: the steady wind's direction."""


@dataclass(frozen=True)
class Wind:
    """The air around the swarm."""

    speed_m_s: float = 0.0
    """Steady wind speed, the same everywhere."""
    from_deg: float = 0.0
    """Where the steady wind blows from, clockwise from north (meteorological)."""
    turbulence_sigma_w_m_s: float = 0.0
    """Vertical turbulence intensity sigma_w (``TURBULENCE_SIGMA_W_M_S`` for the named levels); 0: none."""
    turbulence_altitude_m: float = 20.0
    """Height at which the turbulence's intensities and length scales are taken (the case study's
    formation altitude); 3 m to 300 m, the low-altitude model's range."""
    air_density_kg_m3: float = SEA_LEVEL_AIR_DENSITY_KG_M3
    gusts: tuple[Gust, ...] = ()

    def __post_init__(self) -> None:
        def check(name: str, value, *, positive=False, non_negative=False, lo=None, hi=None) -> None:
            finite_number(f"wind.{name}", value, positive=positive, non_negative=non_negative)
            if lo is not None and not lo <= value <= hi:
                raise ParameterError(f"wind.{name} must be between {lo:g} and {hi:g}, got {value!r}")

        check("speed_m_s", self.speed_m_s, non_negative=True)
        check("from_deg", self.from_deg)
        check("turbulence_sigma_w_m_s", self.turbulence_sigma_w_m_s, non_negative=True)
        check("turbulence_altitude_m", self.turbulence_altitude_m, lo=3.0, hi=300.0)
        check("air_density_kg_m3", self.air_density_kg_m3, positive=True)
        for k, g in enumerate(self.gusts):
            check(f"gusts[{k}].speed_m_s", g.speed_m_s, non_negative=True)
            check(f"gusts[{k}].duration_s", g.duration_s, positive=True)
            check(f"gusts[{k}].start_s", g.start_s, non_negative=True)
            if g.from_deg is not None:
                check(f"gusts[{k}].from_deg", g.from_deg)

    @property
    def steady_e_m_s(self) -> np.ndarray:
        """The steady wind in the earth frame [m/s]."""
        return wind_vector_e(self.speed_m_s, self.from_deg)

    @property
    def advection_speed_m_s(self) -> float:
        """V of the Dryden spectra: the mean wind, at least ``MIN_ADVECTION_M_S``."""
        return max(self.speed_m_s, MIN_ADVECTION_M_S)

    def gust_table(self) -> np.ndarray:
        """(G, 5): start [s], duration [s], peak velocity in the earth frame [m/s] of each gust."""
        rows = [(g.start_s, g.duration_s, *wind_vector_e(g.speed_m_s, self.from_deg if g.from_deg is None else g.from_deg))
                for g in self.gusts]
        return np.array(rows, dtype=float).reshape(len(rows), 5)

    def intensities_m_s(self) -> np.ndarray:
        """(sigma_u, sigma_v, sigma_w) [m/s] at ``turbulence_altitude_m`` (MIL-F-8785C)."""
        h_ft = self.turbulence_altitude_m / FOOT_M
        sw = self.turbulence_sigma_w_m_s
        su = sw / (0.177 + 0.000823 * h_ft) ** 0.4
        return np.array([su, su, sw])

    def length_scales_m(self) -> np.ndarray:
        """(L_u, L_v, L_w) [m] at ``turbulence_altitude_m`` (MIL-F-8785C)."""
        h_ft = self.turbulence_altitude_m / FOOT_M
        lu = h_ft / (0.177 + 0.000823 * h_ft) ** 1.2
        return np.array([lu, lu, h_ft]) * FOOT_M

    def describe(self) -> dict:
        """The wind as plain numbers (a run's summary)."""
        return {"speed_m_s": self.speed_m_s, "from_deg": self.from_deg,
                "turbulence_sigma_w_m_s": self.turbulence_sigma_w_m_s,
                "turbulence_altitude_m": self.turbulence_altitude_m, "air_density_kg_m3": self.air_density_kg_m3,
                "gusts": [{"speed_m_s": g.speed_m_s, "duration_s": g.duration_s, "start_s": g.start_s,
                           "from_deg": g.from_deg} for g in self.gusts]}


def wind_vector_e(speed_m_s: float, from_deg: float) -> np.ndarray:
    """A horizontal wind of this speed blowing from ``from_deg`` (meteorological), earth frame
    (x north, y west): from the north it blows towards -x, from the east towards +y."""
    a = math.radians(from_deg)
    return np.array([-speed_m_s * math.cos(a), speed_m_s * math.sin(a), 0.0])


def turbulence_axes_e(from_deg: float) -> np.ndarray:
    """(3, 3): the turbulence's u, v, w axes (along the mean wind, across it to its left, up) as
    columns in the earth frame: what turns a turbulence in (u, v, w) into the earth frame."""
    along = wind_vector_e(1.0, from_deg)
    return np.column_stack([along, [-along[1], along[0], 0.0], [0.0, 0.0, 1.0]])


def turbulence_sigma_w(level: str | float, what: str = "turbulence") -> float:
    """sigma_w [m/s] of a named level (none, light, moderate, severe) or of a number in m/s."""
    if isinstance(level, str):
        name = level.strip().lower()
        if name in TURBULENCE_SIGMA_W_M_S:
            return TURBULENCE_SIGMA_W_M_S[name]
        try:
            level = float(name)
        except ValueError:
            raise ParameterError(f"{what} must be none, light, moderate, severe or sigma_w in m/s, "
                                 f"got {level!r}") from None
    if isinstance(level, bool) or not isinstance(level, (int, float)) or not (math.isfinite(level) and level >= 0):
        raise ParameterError(f"{what} must be none, light, moderate, severe or sigma_w in m/s (not negative), "
                             f"got {level!r}")
    return float(level)


@njit(inline="always")
def one_minus_cosine(t_s, start_s, duration_s):
    """The 1-cosine gust's speed over its peak at time t: 0 outside [start, start + duration]."""
    if t_s < start_s or t_s > start_s + duration_s:
        return 0.0
    return 0.5 * (1.0 - math.cos(2.0 * math.pi * (t_s - start_s) / duration_s))


@njit(inline="always")
def gusts_at(t_s, gusts):
    """Sum of every gust of a ``gust_table`` at time t, earth frame [m/s], as (x, y, z)."""
    gx = gy = gz = 0.0
    for k in range(gusts.shape[0]):
        s = one_minus_cosine(t_s, gusts[k, 0], gusts[k, 1])
        if s != 0.0:
            gx += s * gusts[k, 2]
            gy += s * gusts[k, 3]
            gz += s * gusts[k, 4]
    return gx, gy, gz


@njit(inline="always")
def turbulence_step(x, noise, Phi, L, C, scratch):
    """One step of a drone's Dryden state x (5,): returns the turbulence C x now (earth frame, m/s,
    as (x, y, z)) and advances x to Phi x + L noise (noise: 5 standard normals; scratch: 5 floats)."""
    n = x.shape[0]
    tx = ty = tz = 0.0
    for c in range(n):
        tx += C[0, c] * x[c]
        ty += C[1, c] * x[c]
        tz += C[2, c] * x[c]
    for r in range(n):
        acc = 0.0
        for c in range(n):
            acc += Phi[r, c] * x[c] + L[r, c] * noise[c]
        scratch[r] = acc
    for r in range(n):
        x[r] = scratch[r]
    return tx, ty, tz


@dataclass(frozen=True)
class Dryden:
    """The Dryden filters of one ``Wind`` in discrete time (step dt_s), stacked for u, v, w:
    x' = Phi x + L n with n standard normal; (u, v, w) = C_uvw x along, across and up the wind, and
    C = axes C_uvw the same in the earth frame [m/s]. P is the stationary covariance of x: a first
    state drawn from it makes the process stationary from the start."""

    Phi: np.ndarray    # (5, 5)
    L: np.ndarray      # (5, 5)
    C_uvw: np.ndarray  # (3, 5)
    C: np.ndarray      # (3, 5)
    P: np.ndarray      # (5, 5)
    time_constants_s: np.ndarray
    """(3,): L / V of u, v, w."""

    @classmethod
    def of(cls, wind: Wind, dt_s: float) -> "Dryden":
        sigma, scale = wind.intensities_m_s(), wind.length_scales_m()
        T = scale / wind.advection_speed_m_s
        parts = [_component(sigma[0], T[0], first_order=True), _component(sigma[1], T[1]), _component(sigma[2], T[2])]
        A = scipy.linalg.block_diag(*(p[0] for p in parts))
        B = scipy.linalg.block_diag(*(p[1] for p in parts))
        C_uvw = scipy.linalg.block_diag(*(p[2][None, :] for p in parts))
        P = scipy.linalg.block_diag(*(p[3] for p in parts))
        # Van Loan: Phi = e^(A dt) and Q = int_0^dt e^(A s) B B^T e^(A^T s) ds, exactly
        n = A.shape[0]
        M = np.zeros((2 * n, 2 * n))
        M[:n, :n], M[:n, n:], M[n:, n:] = -A, B @ B.T, A.T
        E = scipy.linalg.expm(M * dt_s)
        Phi = E[n:, n:].T
        Q = Phi @ E[:n, n:]
        w, V = np.linalg.eigh(0.5 * (Q + Q.T))
        L = V * np.sqrt(np.clip(w, 0.0, None))  # L L^T = Q
        return cls(Phi, L, C_uvw, turbulence_axes_e(wind.from_deg) @ C_uvw, P, T)

    def correlation(self, lag_steps: int) -> np.ndarray:
        """E[c(t) c(t + lag)] of u, v and w of this discrete process, exactly (from P and Phi)."""
        Phi_k = np.linalg.matrix_power(self.Phi, lag_steps)
        return np.einsum("ij,jk,ik->i", self.C_uvw @ Phi_k, self.P, self.C_uvw)


def _component(sigma: float, T: float, first_order: bool = False):
    """(A, B, c, P) of one Dryden component with time constant T = L / V, c scaled so that
    c P c^T = sigma^2: 1 / (1 + T s) for u, (1 + sqrt(3) T s) / (1 + T s)^2 for v and w."""
    if first_order:
        A, B, c = np.array([[-1.0 / T]]), np.array([[1.0]]), np.array([1.0])
    else:
        A = np.array([[0.0, 1.0], [-1.0 / T**2, -2.0 / T]])
        B = np.array([[0.0], [1.0]])
        c = np.array([1.0, math.sqrt(3.0) * T])
    P = scipy.linalg.solve_continuous_lyapunov(A, -B @ B.T)
    return A, B, c * (sigma / math.sqrt(c @ P @ c)), P


def wind_from_table(table) -> Wind:
    """A plan's ``[wind]`` table (``docs/plans.md``) as a Wind; ParameterError naming the field."""
    if not isinstance(table, dict):
        raise ParameterError("[wind] must be a table")
    known = {"speed_m_s", "from_deg", "turbulence", "turbulence_altitude_m", "air_density_kg_m3", "gusts"}
    for key in table:
        if key not in known:
            raise ParameterError(f"wind.{key} is not a known field")
    gusts = table.get("gusts", [])
    if not isinstance(gusts, list) or not all(isinstance(g, dict) for g in gusts):
        raise ParameterError("wind.gusts must be a list of tables ([[wind.gusts]])")
    parsed = []
    for k, g in enumerate(gusts):
        for key in g:
            if key not in ("speed_m_s", "duration_s", "start_s", "from_deg"):
                raise ParameterError(f"wind.gusts[{k}].{key} is not a known field")
        for key in ("speed_m_s", "duration_s", "start_s"):
            if key not in g:
                raise ParameterError(f"wind.gusts[{k}].{key} is required")
        parsed.append(Gust(g["speed_m_s"], g["duration_s"], g["start_s"], g.get("from_deg")))
    defaults = Wind()
    return Wind(speed_m_s=table.get("speed_m_s", defaults.speed_m_s), from_deg=table.get("from_deg", defaults.from_deg),
                turbulence_sigma_w_m_s=turbulence_sigma_w(table.get("turbulence", 0.0), "wind.turbulence"),
                turbulence_altitude_m=table.get("turbulence_altitude_m", defaults.turbulence_altitude_m),
                air_density_kg_m3=table.get("air_density_kg_m3", defaults.air_density_kg_m3), gusts=tuple(parsed))
