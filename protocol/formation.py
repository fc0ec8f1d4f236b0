"""Formation offsets h_i(t) with exact derivatives.

Every family here describes, per agent, an earth-frame position p(t) and Euler attitude eta(t) with
their first and second derivatives; the offsets in x_r coordinates are then

    h     = [p_dot, eta_dot, eta, p]
    h_dot = [p_ddot, eta_ddot, eta_dot, p_dot]

so the velocity rows are the derivatives of the position rows by construction and the feasibility
condition (76) holds. A formation given as raw 12-vectors is checked by ``design.check_feasibility``."""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from .airframe import ParameterError


@dataclass(frozen=True)
class Kinematics:
    """Per-agent position and attitude with two derivatives, each (N, 3)."""

    p: np.ndarray
    p_dot: np.ndarray
    p_ddot: np.ndarray
    eta: np.ndarray
    eta_dot: np.ndarray
    eta_ddot: np.ndarray

    def offsets(self) -> tuple[np.ndarray, np.ndarray]:
        return self._offsets

    @cached_property
    def _offsets(self) -> tuple[np.ndarray, np.ndarray]:
        h = np.concatenate([self.p_dot, self.eta_dot, self.eta, self.p], axis=-1)
        h_dot = np.concatenate([self.p_ddot, self.eta_ddot, self.eta_dot, self.p_dot], axis=-1)
        h.setflags(write=False)  # (kept, and shared by every caller)
        h_dot.setflags(write=False)
        return h, h_dot


class Formation:
    """Base of the formation families: ``kinematics(t)`` gives p, eta and derivatives per agent."""

    n_agents: int

    def kinematics(self, t_s: float) -> Kinematics:  # pragma: no cover - interface
        raise NotImplementedError

    def offsets(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """h (N, 12) and h_dot (N, 12) at time t."""
        return self.kinematics(t_s).offsets()


def _as_agents(name: str, value, n: int) -> np.ndarray:
    arr = np.array(value, dtype=float)
    arr = np.tile(arr, (n, 1)) if arr.shape == (3,) else arr
    if arr.shape != (n, 3):
        raise ParameterError(f"formation {name} must be 3 numbers or one triple per agent ({n}), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ParameterError(f"formation {name} must be finite numbers")
    return arr


def _recently(recent: OrderedDict, t_s: float, offsets) -> tuple[np.ndarray, np.ndarray]:
    """``offsets(t_s)``, kept for the last few instants asked (read-only arrays): the agents of one
    companion process fly their rows of one formation and ask for the same instants."""
    found = recent.get(t_s)
    if found is None:
        found = recent[t_s] = offsets(t_s)
        for arr in found:
            arr.setflags(write=False)
        if len(recent) > 8:
            recent.popitem(last=False)
    return found


@dataclass(frozen=True)
class ConstantFormation(Formation):
    """Fixed position [m] and attitude [rad] offsets per agent."""

    position_m: np.ndarray
    attitude_rad: np.ndarray
    _kinematics: Kinematics = field(init=False, repr=False, compare=False)
    _offsets: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        n = np.asarray(self.position_m).shape[0]
        p, a = _as_agents("position", self.position_m, n), _as_agents("attitude", self.attitude_rad, n)
        z = np.zeros_like(p)
        for arr in (p, a, z):
            arr.setflags(write=False)  # shared by every call: nobody may change them
        k = Kinematics(p, z, z, a, z, z)
        offsets = k.offsets()
        for arr in offsets:
            arr.setflags(write=False)
        for name, value in (("position_m", p), ("attitude_rad", a), ("_kinematics", k), ("_offsets", offsets)):
            object.__setattr__(self, name, value)

    @property
    def n_agents(self) -> int:
        return self.position_m.shape[0]

    def kinematics(self, t_s: float) -> Kinematics:
        return self._kinematics

    def offsets(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        return self._offsets


def paper_attitudes(n_agents: int) -> np.ndarray:
    """The case study's attitudes (a plan's ``attitude_rad = "paper-alternating"``): (-0.5, -0.5, 0.5)
    * (-1)^i rad for drone i = 1 .. n, (n, 3)."""
    return np.outer([(-1.0) ** i for i in range(1, n_agents + 1)], [-0.5, -0.5, 0.5])


@dataclass(frozen=True)
class RotatingPolygon(Formation):
    """The paper's formation generalised to N agents: agent i (from 1) at phase 2 pi (i-1)/N on a
    circle of ``radius_m`` at ``altitude_m`` turning at ``rate_rad_s``:

        p_i(t) = [R sin(w t + phase_i), R cos(w t + phase_i), altitude]

    with constant attitude offsets ``attitude_rad`` (N, 3). With N = 6, R = 10, altitude 20, w = 1
    and attitude (-0.5, -0.5, 0.5) * (-1)^i this is the offset h_i of Section 5."""

    n_agents: int
    radius_m: float
    altitude_m: float
    rate_rad_s: float
    attitude_rad: np.ndarray
    phase0_rad: float = 0.0

    def __post_init__(self) -> None:
        if not (isinstance(self.n_agents, int) and self.n_agents >= 1):
            raise ParameterError(f"rotating polygon needs at least one agent, got {self.n_agents!r}")
        for name in ("radius_m", "altitude_m", "rate_rad_s", "phase0_rad"):
            if not np.isfinite(getattr(self, name)):
                raise ParameterError(f"rotating polygon {name} must be a finite number")
        if self.radius_m < 0:
            raise ParameterError(f"rotating polygon radius_m must not be negative, got {self.radius_m}")
        attitude = _as_agents("attitude", self.attitude_rad, self.n_agents)
        attitude.setflags(write=False)
        object.__setattr__(self, "attitude_rad", attitude)
        object.__setattr__(self, "_recent", OrderedDict())

    @classmethod
    def paper(cls, n_agents: int = 6) -> "RotatingPolygon":
        return cls(n_agents, radius_m=10.0, altitude_m=20.0, rate_rad_s=1.0, attitude_rad=paper_attitudes(n_agents))

    def kinematics(self, t_s: float) -> Kinematics:
        n, R, w = self.n_agents, self.radius_m, self.rate_rad_s
        ang = w * t_s + self.phase0_rad + (2.0 * np.pi / n) * np.arange(n)
        s, c = np.sin(ang), np.cos(ang)
        p = np.empty((n, 3))
        p_dot = np.zeros((n, 3))
        p_ddot = np.zeros((n, 3))
        p[:, 0], p[:, 1], p[:, 2] = R * s, R * c, self.altitude_m
        p_dot[:, 0], p_dot[:, 1] = R * w * c, -R * w * s
        p_ddot[:, 0], p_ddot[:, 1] = -R * w * w * s, -R * w * w * c
        z3 = np.zeros((n, 3))
        return Kinematics(p, p_dot, p_ddot, self.attitude_rad, z3, z3)

    def offsets(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """``kinematics(t).offsets()`` written straight into h and h_dot (the control loop's hot
        path), for the last few instants kept (``_recently``)."""
        return _recently(self._recent, t_s, self._offsets)

    def _offsets(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        n, R, w = self.n_agents, self.radius_m, self.rate_rad_s
        ang = w * t_s + self.phase0_rad + (2.0 * np.pi / n) * np.arange(n)
        s, c = np.sin(ang), np.cos(ang)
        h = np.zeros((n, 12))
        h_dot = np.zeros((n, 12))
        h[:, 0], h[:, 1] = R * w * c, -R * w * s              # p_dot
        h[:, 6:9] = self.attitude_rad                          # eta
        h[:, 9], h[:, 10], h[:, 11] = R * s, R * c, self.altitude_m  # p
        h_dot[:, 0], h_dot[:, 1] = -R * w * w * s, -R * w * w * c    # p_ddot
        h_dot[:, 9:11] = h[:, 0:2]                              # p_dot
        return h, h_dot


@dataclass(frozen=True)
class KeyframeFormation(Formation):
    """Shapes at given times joined by a C2 cubic spline (zero velocity at the first and last
    keyframe), so an operator can reshape a formation. Before the first keyframe and after the last
    the formation holds. ``positions_m`` and ``attitudes_rad`` are (K, N, 3)."""

    times_s: np.ndarray
    positions_m: np.ndarray
    attitudes_rad: np.ndarray
    _p: "CubicSpline" = field(init=False, repr=False, compare=False)  # noqa: F821 (imported when needed)
    _eta: "CubicSpline" = field(init=False, repr=False, compare=False)  # noqa: F821

    def __post_init__(self) -> None:
        t = np.array(self.times_s, dtype=float)
        p = np.array(self.positions_m, dtype=float)
        a = np.array(self.attitudes_rad, dtype=float)
        if t.ndim != 1 or t.size < 2:
            raise ParameterError("keyframe formation needs at least two keyframe times")
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise ParameterError("keyframe times must be finite and strictly increasing")
        if p.ndim != 3 or p.shape[0] != t.size or p.shape[2] != 3:
            raise ParameterError(f"keyframe positions must be (keyframes, agents, 3), got {p.shape}")
        if a.shape != p.shape:
            raise ParameterError(f"keyframe attitudes must have the shape of the positions {p.shape}, got {a.shape}")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(a))):
            raise ParameterError("keyframe positions and attitudes must be finite numbers")
        for name, val in (("times_s", t), ("positions_m", p), ("attitudes_rad", a)):
            object.__setattr__(self, name, val)
        from scipy.interpolate import CubicSpline  # (a third of a second to import: only for keyframes)

        object.__setattr__(self, "_p", CubicSpline(t, p, axis=0, bc_type="clamped"))
        object.__setattr__(self, "_eta", CubicSpline(t, a, axis=0, bc_type="clamped"))
        object.__setattr__(self, "_recent", OrderedDict())

    def offsets(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        return _recently(self._recent, t_s, lambda t: self.kinematics(t).offsets())

    @property
    def n_agents(self) -> int:
        return self.positions_m.shape[1]

    def kinematics(self, t_s: float) -> Kinematics:
        t = float(np.clip(t_s, self.times_s[0], self.times_s[-1]))
        inside = self.times_s[0] < t_s < self.times_s[-1]
        def ev(spl, k):
            if k and not inside:
                return np.zeros((self.n_agents, 3))
            return spl(t, k)
        return Kinematics(ev(self._p, 0), ev(self._p, 1), ev(self._p, 2),
                          ev(self._eta, 0), ev(self._eta, 1), ev(self._eta, 2))


def quintic_blend(tau: float) -> tuple[float, float, float]:
    """s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 on [0, 1] (rest to rest) and its first two derivatives
    with respect to tau; 0 before and 1 after."""
    if tau <= 0.0:
        return 0.0, 0.0, 0.0
    if tau >= 1.0:
        return 1.0, 0.0, 0.0
    s = tau**3 * (10.0 + tau * (-15.0 + 6.0 * tau))
    ds = 30.0 * tau**2 * (1.0 - tau) ** 2
    dds = 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau)
    return s, ds, dds


@dataclass(frozen=True)
class _Transition(Formation):
    """From ``source`` to ``target`` over [t0_s, t0_s + duration_s] (the common part of a blend
    and a rejoin)."""

    source: Formation
    target: Formation
    t0_s: float
    duration_s: float

    def __post_init__(self) -> None:
        kind = type(self).__name__.lower()
        if self.source.n_agents != self.target.n_agents:
            raise ParameterError(f"a {kind} needs formations of the same number of agents")
        if not (np.isfinite(self.duration_s) and self.duration_s > 0 and np.isfinite(self.t0_s)):
            raise ParameterError(f"{kind} duration must be a positive number of seconds, got {self.duration_s!r}")

    @property
    def n_agents(self) -> int:
        return self.target.n_agents

    @property
    def end_s(self) -> float:
        return self.t0_s + self.duration_s


@dataclass(frozen=True)
class Blend(_Transition):
    """From one formation to another by a quintic blend over [t0_s, t0_s + duration_s]:

        p(t) = (1 - s(t)) p_from(t) + s(t) p_to(t),   eta likewise,

    differentiated with the product rule, so (76) holds throughout. Before t0 it is ``source``,
    after the blend exactly ``target``. Starting from a moving source (a vehicle braking) it starts
    exactly where and how fast that source is."""

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "_recent", OrderedDict())

    def offsets(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """``kinematics(t).offsets()``, blended in offset coordinates (the control loop's hot path):
        h = [p_dot, eta_dot, eta, p] holds every value and first derivative, h_dot[:, 0:6] the
        second derivatives. The last few instants asked are kept (``_recently``): the agents of a
        companion process that enter a formation together fly rows of one blend."""
        return _recently(self._recent, t_s, self._offsets)

    def _offsets(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        T = self.duration_s
        s, ds, dds = quintic_blend((t_s - self.t0_s) / T)
        if s == 1.0:
            return self.target.offsets(t_s)
        ha, ha_dot = self.source.offsets(t_s)
        if s == 0.0:
            return ha, ha_dot
        hb, hb_dot = self.target.offsets(t_s)
        ds, dds = ds / T, dds / (T * T)
        value = (9, 10, 11, 6, 7, 8)  # p, eta: in the order of the derivatives in h[:, 0:6]
        xa, xb = ha[:, value], hb[:, value]
        d, d_d, d_dd = xb - xa, hb[:, 0:6] - ha[:, 0:6], hb_dot[:, 0:6] - ha_dot[:, 0:6]
        x = xa + s * d
        x_d = ha[:, 0:6] + s * d_d + ds * d
        x_dd = ha_dot[:, 0:6] + s * d_dd + 2.0 * ds * d_d + dds * d
        h = np.concatenate([x_d, x[:, 3:6], x[:, 0:3]], axis=1)
        h_dot = np.concatenate([x_dd, x_d[:, 3:6], x_d[:, 0:3]], axis=1)
        return h, h_dot

    def kinematics(self, t_s: float) -> Kinematics:
        T = self.duration_s
        s, ds, dds = quintic_blend((t_s - self.t0_s) / T)
        if s == 1.0:
            return self.target.kinematics(t_s)
        a = self.source.kinematics(t_s)
        if s == 0.0:
            return a
        b = self.target.kinematics(t_s)
        ds, dds = ds / T, dds / (T * T)

        def mix(xa, xa_d, xa_dd, xb, xb_d, xb_dd):
            d, d_d, d_dd = xb - xa, xb_d - xa_d, xb_dd - xa_dd
            return xa + s * d, xa_d + s * d_d + ds * d, xa_dd + s * d_dd + 2.0 * ds * d_d + dds * d

        p, pd, pdd = mix(a.p, a.p_dot, a.p_ddot, b.p, b.p_dot, b.p_ddot)
        e, ed, edd = mix(a.eta, a.eta_dot, a.eta_ddot, b.eta, b.eta_dot, b.eta_ddot)
        return Kinematics(p, pd, pdd, e, ed, edd)


@dataclass(frozen=True)
class Rejoin(_Transition):
    """Back into ``target`` from wherever ``source`` is at t0: the difference source - target at t0,
    its rate and its second derivative decay to zero by a quintic over [t0_s, t0_s + duration_s]:

        x(t) = x_target(t) + e(t - t0),   e(0), e'(0), e''(0) from the source,   e = e' = e'' = 0 at the end,

    for positions and attitudes alike: the reference continues the source (no step, not even in
    acceleration: a drone taken over at rest is not asked at once for the formation's turn) and is
    exactly the target afterwards. Unlike a ``Blend`` the source is not followed after t0.
    ``rejoin_duration`` picks a duration for a peak acceleration."""

    def __post_init__(self) -> None:
        super().__post_init__()
        a, b = self.source.kinematics(self.t0_s), self.target.kinematics(self.t0_s)
        T = self.duration_s
        coeffs = [_quintic_to_rest(xa - xb, va - vb, aa - ab, T)
                  for xa, va, aa, xb, vb, ab in ((a.p, a.p_dot, a.p_ddot, b.p, b.p_dot, b.p_ddot),
                                                 (a.eta, a.eta_dot, a.eta_ddot, b.eta, b.eta_dot, b.eta_ddot))]
        object.__setattr__(self, "_coeffs", coeffs)

    @property
    def initial_error(self) -> tuple[np.ndarray, np.ndarray]:
        """Position [m] and velocity [m/s] of the source relative to the target at t0, (N, 3) each."""
        return self._coeffs[0][0], self._coeffs[0][1]

    def kinematics(self, t_s: float) -> Kinematics:
        if t_s < self.t0_s:
            return self.source.kinematics(t_s)
        b = self.target.kinematics(t_s)
        if t_s >= self.end_s:
            return b
        tau = t_s - self.t0_s
        (pe, pv, pa), (ee, ev, ea) = (_quintic_eval(c, tau) for c in self._coeffs)
        return Kinematics(b.p + pe, b.p_dot + pv, b.p_ddot + pa, b.eta + ee, b.eta_dot + ev, b.eta_ddot + ea)


def rejoin_duration(position_error_m: float, velocity_error_m_s: float, accel_m_s2: float, min_s: float) -> float:
    """A duration for a ``Rejoin`` whose quintic peaks near ``accel_m_s2``: a position error d alone
    peaks at (10 / sqrt 3) d / T^2, a velocity error v alone at about 3.94 v / T (never below min_s)."""
    return max(min_s, math.sqrt(10.0 / math.sqrt(3.0) * abs(position_error_m) / accel_m_s2),
               3.94 * abs(velocity_error_m_s) / accel_m_s2)


def _quintic_to_rest(x0, v0, a0, T):
    """Coefficients c0..c5 of the quintic with x(0), x'(0), x''(0) given and x = x' = x'' = 0 at T."""
    c3 = (-20.0 * x0 - 12.0 * v0 * T - 3.0 * a0 * T**2) / (2.0 * T**3)
    c4 = (30.0 * x0 + 16.0 * v0 * T + 3.0 * a0 * T**2) / (2.0 * T**4)
    c5 = (-12.0 * x0 - 6.0 * v0 * T - a0 * T**2) / (2.0 * T**5)
    return x0, v0, 0.5 * a0, c3, c4, c5


def _quintic_eval(c, tau: float):
    c0, c1, c2, c3, c4, c5 = c
    x = c0 + tau * (c1 + tau * (c2 + tau * (c3 + tau * (c4 + tau * c5))))
    xd = c1 + tau * (2.0 * c2 + tau * (3.0 * c3 + tau * (4.0 * c4 + tau * 5.0 * c5)))
    xdd = 2.0 * c2 + tau * (6.0 * c3 + tau * (12.0 * c4 + tau * 20.0 * c5))
    return x, xd, xdd


def EntryBlend(target: Formation, start_position_m, start_attitude_rad, t0_s: float, duration_s: float) -> Blend:
    """Reference shaping for formation entry: each agent's offset moves from where it rests
    (``start`` position and attitude offsets, e.g. on the ground) into the target formation by a
    quintic blend over [t0_s, t0_s + duration_s]. At t0 the offset equals the start, so a swarm that
    starts where it is asked to be starts with zero formation error."""
    n = target.n_agents
    start = ConstantFormation(_as_agents("start position", start_position_m, n),
                              _as_agents("start attitude", start_attitude_rad, n))
    return Blend(start, target, t0_s, duration_s)


@dataclass(frozen=True)
class RelativeTo(Formation):
    """An absolute trajectory (e.g. a vehicle braking to a hold) written as offsets from a moving
    leader: p - p0(t), eta - eta0(t), derivatives likewise. ``leader`` is a one-agent formation."""

    absolute: Formation
    leader: Formation

    @property
    def n_agents(self) -> int:
        return self.absolute.n_agents

    def kinematics(self, t_s: float) -> Kinematics:
        a, b = self.absolute.kinematics(t_s), self.leader.kinematics(t_s)
        return Kinematics(a.p - b.p, a.p_dot - b.p_dot, a.p_ddot - b.p_ddot,
                          a.eta - b.eta, a.eta_dot - b.eta_dot, a.eta_ddot - b.eta_ddot)


@dataclass(frozen=True)
class RawOffsets:
    """Offsets given directly as functions of time returning (N, 12) arrays, e.g. from a plan file
    that writes the paper's printed h_i. Nothing guarantees (76): check it."""

    n_agents: int
    h_fn: object
    h_dot_fn: object

    def offsets(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.h_fn(t_s), dtype=float), np.asarray(self.h_dot_fn(t_s), dtype=float)


@dataclass(frozen=True)
class QuinticTransfer(Formation):
    """From a moving state (position, velocity, attitude, attitude rate at t0) to rest at a target
    position and attitude at t0 + duration, by a quintic per axis (zero acceleration at both ends);
    it holds the target afterwards. Used for a flight controller's own manoeuvres (hold, land,
    takeoff) entered at any speed; before t0 it extrapolates the start at its velocity (so a
    reference that switches to it a little early sees no jump). Arrays are (N, 3)."""

    p0: np.ndarray
    p_dot0: np.ndarray
    p1: np.ndarray
    eta0: np.ndarray
    eta_dot0: np.ndarray
    eta1: np.ndarray
    t0_s: float
    duration_s: float

    def __post_init__(self) -> None:
        n = np.asarray(self.p0).reshape(-1, 3).shape[0]
        for name in ("p0", "p_dot0", "p1", "eta0", "eta_dot0", "eta1"):
            object.__setattr__(self, name, _as_agents(name, np.asarray(getattr(self, name), dtype=float).reshape(-1, 3), n))
        if not (np.isfinite(self.duration_s) and self.duration_s > 0 and np.isfinite(self.t0_s)):
            raise ParameterError(f"transfer duration must be a positive number of seconds, got {self.duration_s!r}")
        zero = np.zeros_like(self.p0)
        object.__setattr__(self, "_coeffs", [_quintic_to_rest(x0 - x1, v0, zero, self.duration_s)
                                             for x0, v0, x1 in ((self.p0, self.p_dot0, self.p1),
                                                                (self.eta0, self.eta_dot0, self.eta1))])

    @property
    def n_agents(self) -> int:
        return self.p0.shape[0]

    @property
    def end_s(self) -> float:
        return self.t0_s + self.duration_s

    def kinematics(self, t_s: float) -> Kinematics:
        z = np.zeros_like(self.p0)
        if t_s >= self.end_s:
            return Kinematics(self.p1, z, z, self.eta1, z, z)
        if t_s < self.t0_s:
            dt = t_s - self.t0_s
            return Kinematics(self.p0 + self.p_dot0 * dt, self.p_dot0, z, self.eta0 + self.eta_dot0 * dt, self.eta_dot0, z)
        tau = t_s - self.t0_s
        (pe, pv, pa), (ee, ev, ea) = (_quintic_eval(c, tau) for c in self._coeffs)
        return Kinematics(self.p1 + pe, pv, pa, self.eta1 + ee, ev, ea)


LEADER_MAX_YAW_RATE_RAD_S = 0.5
"""Peak yaw rate of a leader move [rad/s]."""


@dataclass(frozen=True)
class LeaderMove(Formation):
    """The leader x0 (a one-agent formation): ``base`` until ``at_s``, then a quintic from wherever
    base is then (moving or not) to rest at ``target_m`` with a peak speed of ``speed_m_s``, or, with
    no target, a stop at the braking point. The yaw goes to ``yaw_rad`` (None: kept); roll and
    pitch keep the base's values at ``at_s``. Every companion builds the same move from the same
    command, so the swarm's leader stays one."""

    base: Formation
    at_s: float
    target_m: tuple[float, float, float] | None
    yaw_rad: float | None
    speed_m_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.at_s) and math.isfinite(self.speed_m_s) and self.speed_m_s > 0):
            raise ParameterError(f"a leader move needs a finite time and a positive speed, got {self.speed_m_s!r} m/s")
        k = self.base.kinematics(self.at_s)
        p0, v0, eta0 = k.p[0], k.p_dot[0], k.eta[0]
        if self.target_m is None:
            duration = max(2.0, float(np.linalg.norm(v0)) / 2.0)
            p1 = p0 + v0 * duration / 2.0  # the stopping point of a quintic with no acceleration at the ends
        else:
            p1 = np.asarray(self.target_m, dtype=float)
            if p1.shape != (3,) or not np.all(np.isfinite(p1)):
                raise ParameterError(f"a leader target must be three finite numbers, got {self.target_m!r}")
            duration = 1.875 * float(np.linalg.norm(p1 - p0)) / self.speed_m_s  # a quintic peaks at 1.875 d / T
        eta1 = eta0.copy()
        if self.yaw_rad is not None:
            if not math.isfinite(self.yaw_rad):
                raise ParameterError(f"a leader yaw must be finite, got {self.yaw_rad!r}")
            eta1[2] = self.yaw_rad
            duration = max(duration, 1.875 * abs(eta1[2] - eta0[2]) / LEADER_MAX_YAW_RATE_RAD_S)
        object.__setattr__(self, "_move", QuinticTransfer(p0, v0, p1, eta0, k.eta_dot[0], eta1, self.at_s,
                                                          max(1.0, duration)))

    @property
    def n_agents(self) -> int:
        return 1

    @property
    def end_s(self) -> float:
        return self._move.end_s

    def kinematics(self, t_s: float) -> Kinematics:
        return self.base.kinematics(t_s) if t_s < self.at_s else self._move.kinematics(t_s)


@dataclass(frozen=True)
class Row(Formation):
    """Agent ``index``'s row (from 0) of ``formation``, as a one-agent formation. An agent flies its
    own part of the swarm's formation: its entry, hold and rejoin built on this row cost the same
    at 6 or 1000 drones, and ``formation`` (shared by the agents of one process; the polygon and
    keyframe formations keep their recent instants) is evaluated once per instant for all of them."""

    formation: Formation
    index: int

    @property
    def n_agents(self) -> int:
        return 1

    def kinematics(self, t_s: float) -> Kinematics:
        k, r = self.formation.kinematics(t_s), slice(self.index, self.index + 1)
        return Kinematics(k.p[r], k.p_dot[r], k.p_ddot[r], k.eta[r], k.eta_dot[r], k.eta_ddot[r])

    def offsets(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        h, h_dot = self.formation.offsets(t_s)
        return h[self.index:self.index + 1], h_dot[self.index:self.index + 1]


@dataclass(frozen=True)
class Rows(Formation):
    """Rows ``indices`` (from 0) of ``formation``, in order: the part of a swarm's formation some agents fly."""

    formation: Formation
    indices: tuple[int, ...]

    @property
    def n_agents(self) -> int:
        return len(self.indices)

    def kinematics(self, t_s: float) -> Kinematics:
        k, r = self.formation.kinematics(t_s), list(self.indices)
        return Kinematics(k.p[r], k.p_dot[r], k.p_ddot[r], k.eta[r], k.eta_dot[r], k.eta_ddot[r])

    def offsets(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        (h, h_dot), r = self.formation.offsets(t_s), list(self.indices)
        return h[r], h_dot[r]


@dataclass(frozen=True)
class Shifted(Formation):
    """``base`` with its clock starting ``shift_s`` later: a plan put in force in flight flies its
    formation from its own t = 0 while the swarm's plan time runs on."""

    base: Formation
    shift_s: float

    @property
    def n_agents(self) -> int:
        return self.base.n_agents

    def kinematics(self, t_s: float) -> Kinematics:
        return self.base.kinematics(t_s - self.shift_s)

    def offsets(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        return self.base.offsets(t_s - self.shift_s)
