"""What flying a plan asks of each drone's rotors and servos in the air the plan is designed for,
and the margin that leaves to the motor limit and the servo range.

The demand (``actuator_demand``): the RFL (49) at the reference x_r = x0 + h_i(t) with the input
that keeps it there, v = B_tilde (x_r_dot - A_r x_r) (exact when (76) holds), through Remark 1 to
rotor speeds and servo angles. In air the law's b(x) holds the body's drag -(k/m) |r| r, r the
reference velocity through the air lambda_dot - w (``rfl``: the law that flies; the plant feels the
same force, ``dynamics.drag``): u is then exactly what holds the reference in the wind w.

The design air (``design_winds_e_m_s``) of a plan's [wind]: its steady wind, from its stated
direction; plus its gusts at their peak (at any instant of the plan: a design gust may come at the
worst moment, wherever the simulation's clock puts it), each gust's peak instant a case of its own
beside the steady wind alone; plus ``turbulence_sigmas`` times the Dryden intensities (sigma_u along
the mean wind, sigma_v across it, sigma_w up, at the wind's turbulence_altitude_m) from the worst
direction: the surface of that ellipsoid, sampled in ``TURBULENCE_DIRECTIONS`` directions. Each
drone at each instant takes the worst of these winds for its fastest rotor and, separately, for its
most tilted servo.

Pure math: the plan's pieces in, arrays and sentences out.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .airframe import RPM_TO_RAD_S, Airframe
from .formation import Formation
from .model import actuator_inverse
from .rfl import MAX_PITCH_RAD, RFL, XR_EULER
from .wind import Wind, gusts_at, turbulence_axes_e

DEFAULT_ROTOR_SPEED_MARGIN_PCT = 10.0
"""Rotor speed kept free for the feedback on top of the design air's demand, in % of the motor
limit: 90 % of the top speed is 81 % of the top thrust (thrust goes with the square), so a fifth of
each rotor's thrust stays for the feedback's corrections (docs/plans.md)."""
DEFAULT_TILT_MARGIN_DEG = 10.0
"""Servo angle kept free for the feedback, in degrees short of the servo range (docs/plans.md)."""
DEFAULT_TURBULENCE_SIGMAS = 3.0
"""The design turbulence: this many times its intensities (a 3-sigma gust of the Dryden turbulence:
a Gaussian component passes 3 sigma 0.27 % of the time)."""
TILT_FORCE_FRACTION = 0.1
"""A rotor's servo angle counts where the rotor pushes at least this fraction of its share of the
hover thrust (m g / 3). Where it pushes less, the direction of its force is free to swing: when a
wind turns a rotor's push around, the force passes near zero and its angle sweeps through 180 deg
in a fraction of a second, while a servo held at its range misses at most this fraction (times
sin 60 deg for a 120 deg range) of one rotor's hover share."""
TURBULENCE_DIRECTIONS = 64
"""Directions in which the turbulence's ellipsoid is sampled for its worst direction (a golden-angle
spiral: about 25 deg apart)."""


@dataclass(frozen=True)
class ActuatorDemand:
    """At each plan time checked (T,) and for each drone: its slowest and fastest rotor [rad/s]
    and the largest servo angle from the untilted position of its rotors that push
    (``TILT_FORCE_FRACTION``) [rad], (T, N) each."""

    times_s: np.ndarray
    omega_min_rad_s: np.ndarray
    omega_max_rad_s: np.ndarray
    tilt_max_rad: np.ndarray
    pitch_rad: np.ndarray
    """|pitch| of the reference: the RFL holds for |pitch| < 90 deg, the controller to MAX_PITCH_RAD."""

    def problem(self, af: Airframe) -> str | None:
        """One sentence on the first drone whose reference pitches past the controller's limit or
        whose rotors pass the motor limit or the servo range (its peak, and when it first passes);
        None when every drone stays inside all three."""
        deg = 180.0 / math.pi
        limits = ((self.pitch_rad, MAX_PITCH_RAD, "a pitch of {:.1f} deg", deg, "the controller's limit ({:.1f} deg)"),
                  (self.omega_max_rad_s, af.max_rotor_speed_rad_s, "a rotor at {:.0f} RPM", 1.0 / RPM_TO_RAD_S,
                   "the motor limit ({:.0f} RPM)"),
                  (self.tilt_max_rad, af.servo_limit_rad, "a rotor tilted {:.1f} deg", deg,
                   "the servo range (+-{:.1f} deg)"))
        for i in range(self.tilt_max_rad.shape[1]):
            for series, limit, need, scale, what in limits:
                over = np.flatnonzero(~(series[:, i] <= limit))  # (NaN counts as over)
                if over.size:
                    return (f"drone {i + 1} needs {need.format(series[:, i].max() * scale)}, past "
                            f"{what.format(limit * scale)} from t = {self.times_s[over[0]]:g} s")
        return None

    def rotor_speed_margin_pct(self, af: Airframe) -> np.ndarray:
        """(N,): what each drone's fastest rotor leaves of the motor limit at its peak, in % of the
        limit (negative: past it)."""
        return 100.0 * (1.0 - self.omega_max_rad_s.max(axis=0) / af.max_rotor_speed_rad_s)

    def tilt_margin_rad(self, af: Airframe) -> np.ndarray:
        """(N,): what each drone's most tilted servo leaves of the servo range at its peak [rad]
        (negative: past it)."""
        return af.servo_limit_rad - self.tilt_max_rad.max(axis=0)


def actuator_demand(rfl: RFL, leader: Formation, formation: Formation, times_s: np.ndarray,
                    air_density_kg_m3: float = 0.0, winds_e_m_s: np.ndarray | None = None) -> ActuatorDemand:
    """What flying ``formation`` about ``leader`` exactly asks of each drone's rotors at the given
    plan times (module docstring): in no air (air_density_kg_m3 0, the paper's model), or in air of
    that density [kg/m^3] in each of the winds ``winds_e_m_s`` (K, 3) [m/s, earth frame] (None:
    still air), the worst of them per drone and instant. The feedback needs room on top of this."""
    times = np.atleast_1d(np.asarray(times_s, dtype=float))
    x_r, x_r_dot = [], []
    for t in times:
        (x0, x0_dot), (h, h_dot) = (f.offsets(float(t)) for f in (leader, formation))
        x_r.append(x0[0] + h)
        x_r_dot.append(x0_dot[0] + h_dot)
    x_r, x_r_dot = np.stack(x_r), np.stack(x_r_dot)  # (T, N, 12)
    v = (x_r_dot - x_r @ rfl.A_r.T) @ np.linalg.pinv(rfl.B_r).T
    winds = [None] if winds_e_m_s is None or air_density_kg_m3 == 0.0 else np.atleast_2d(winds_e_m_s)
    af = rfl.airframe
    pushing_rad_s = math.sqrt(TILT_FORCE_FRACTION * af.mass_kg * af.gravity_m_s2 / (3.0 * af.k_f_N_s2))
    lo = hi = tilt = None
    for wind in winds:
        u, _ = rfl.control_xr(x_r, v, air_density_kg_m3=air_density_kg_m3, wind_e_m_s=wind)
        omega, alpha = actuator_inverse(u)  # (T, N, 3) each
        w_lo, w_hi = omega.min(axis=2), omega.max(axis=2)
        w_tilt = np.where(~(omega < pushing_rad_s), np.abs(alpha), 0.0).max(axis=2)  # (NaN counts)
        lo, hi, tilt = ((w_lo, w_hi, w_tilt) if lo is None else
                        (np.fmin(lo, w_lo), np.fmax(hi, w_hi), np.fmax(tilt, w_tilt)))
    return ActuatorDemand(times, lo, hi, tilt, np.abs(x_r[..., XR_EULER][..., 1]))


def design_winds_e_m_s(wind: Wind, turbulence_sigmas: float = DEFAULT_TURBULENCE_SIGMAS,
                       directions: int = TURBULENCE_DIRECTIONS) -> np.ndarray:
    """(K, 3) [m/s, earth frame]: the winds of ``wind``'s design air (module docstring): the steady
    wind and the steady wind plus the gusts at each gust's peak instant, each plus every sampled
    direction of ``turbulence_sigmas`` times the turbulence's intensities."""
    steady = wind.steady_e_m_s
    table = wind.gust_table()
    bases = [steady] + [steady + np.array(gusts_at(start + 0.5 * duration, table)) for start, duration in table[:, :2]]
    sigma = turbulence_sigmas * wind.intensities_m_s()
    if not np.any(sigma > 0.0):
        return np.array(bases)
    turbulence = (sphere_directions(directions) * sigma) @ turbulence_axes_e(wind.from_deg).T
    return (np.array(bases)[:, None, :] + turbulence[None, :, :]).reshape(-1, 3)


def sphere_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (a golden-angle spiral, from pole to pole)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def demand_in_air(rfl: RFL, leader: Formation, formation: Formation, times_s: np.ndarray, wind: Wind | None,
                  turbulence_sigmas: float = DEFAULT_TURBULENCE_SIGMAS) -> ActuatorDemand:
    """``actuator_demand`` in ``wind``'s design air (``design_winds_e_m_s``); in no air (the
    paper's model) when ``wind`` is None."""
    if wind is None:
        return actuator_demand(rfl, leader, formation, times_s)
    return actuator_demand(rfl, leader, formation, times_s, wind.air_density_kg_m3,
                           design_winds_e_m_s(wind, turbulence_sigmas))


def describe_design_air(wind: Wind | None, turbulence_sigmas: float = DEFAULT_TURBULENCE_SIGMAS) -> str:
    """The design air in a few words: "no air (no [wind])" or "a steady 8 m/s from 270 deg, gusts
    to 6 m/s at their peak, 3 sigma of its turbulence (4.6 m/s along, 4.6 across, 4.6 up) from the
    worst direction"."""
    if wind is None:
        return "no air (the plan has no [wind])"
    parts = [f"a steady {wind.speed_m_s:g} m/s from {wind.from_deg:g} deg" if wind.speed_m_s > 0 else "still air"]
    if wind.gusts:
        parts.append(f"gusts to {max(g.speed_m_s for g in wind.gusts):g} m/s at their peak")
    sigma = turbulence_sigmas * wind.intensities_m_s()
    if np.any(sigma > 0.0):
        parts.append(f"{turbulence_sigmas:g} sigma of its turbulence ({sigma[0]:.2g} m/s along, {sigma[1]:.2g} across, "
                     f"{sigma[2]:.2g} up) from the worst direction")
    return ", ".join(parts) + f", air density {wind.air_density_kg_m3:g} kg/m^3"


def margin_problem(demand: ActuatorDemand, af: Airframe, rotor_speed_margin_pct: float, tilt_margin_deg: float,
                   air: str, calm: ActuatorDemand | None = None) -> str | None:
    """One sentence on the drone that keeps least of the margin asked of the motor limit
    (``rotor_speed_margin_pct``, % of it) or of the servo range (``tilt_margin_deg``) when flying
    the plan in the air ``demand`` was computed in (described as ``air``): the drone, the instant,
    the limit, by how much; ``calm`` (the same in still air), when given, says what still air would
    leave. None when every drone keeps both."""
    speed = demand.rotor_speed_margin_pct(af)
    tilt_deg = np.degrees(demand.tilt_margin_rad(af))
    limit_rpm = af.max_rotor_speed_rad_s / RPM_TO_RAD_S
    cases = ((speed, rotor_speed_margin_pct, demand.omega_max_rad_s,
              lambda peak: f"a rotor at {peak / RPM_TO_RAD_S:.0f} RPM",
              lambda m: (f"which leaves {m:.1f} % of the motor limit ({limit_rpm:.0f} RPM)" if m >= 0 else
                         f"past the motor limit ({limit_rpm:.0f} RPM) by {-m:.1f} % of it"),
              lambda short: f"{short:.1f} points ({short / 100.0 * limit_rpm:.0f} RPM) short of",
              "% check.rotor_speed_margin_pct", None if calm is None else calm.rotor_speed_margin_pct(af), "%"),
             (tilt_deg, tilt_margin_deg, demand.tilt_max_rad,
              lambda peak: f"a rotor tilted {math.degrees(peak):.1f} deg",
              lambda m: (f"which leaves {m:.1f} deg of the servo range (+-{math.degrees(af.servo_limit_rad):.1f} deg)"
                         if m >= 0 else f"past the servo range (+-{math.degrees(af.servo_limit_rad):.1f} deg) by {-m:.1f} deg"),
              lambda short: f"{short:.1f} deg short of", " deg check.tilt_margin_deg",
              None if calm is None else np.degrees(calm.tilt_margin_rad(af)), " deg"))
    for margin, required, series, need, left, short, setting, calm_margin, unit in cases:
        i = int(np.argmin(np.nan_to_num(margin, nan=-np.inf)))
        if margin[i] >= required:
            continue
        k = int(np.nanargmax(series[:, i])) if np.any(np.isfinite(series[:, i])) else 0
        sentence = (f"drone {i + 1} needs {need(series[k, i])} at t = {demand.times_s[k]:g} s in its design air "
                    f"({air}), {left(margin[i])}: {short(required - margin[i])} the {required:g}"
                    f"{setting} keeps for the feedback")
        if calm_margin is not None:
            sentence += (f"; in still air it would leave {calm_margin[i]:.1f}{unit}" if calm_margin[i] >= required else
                         f"; even still air leaves only {calm_margin[i]:.1f}{unit}")
        return sentence
    return None


STEADY_WIND_DIRECTIONS_DEG = tuple(range(0, 360, 15))
"""Where ``largest_steady_wind_m_s`` lets the steady wind blow from."""


def largest_steady_wind_m_s(rfl: RFL, leader: Formation, formation: Formation, times_s: np.ndarray,
                            wind: Wind | None, turbulence_sigmas: float, rotor_speed_margin_pct: float,
                            tilt_margin_deg: float, resolution_m_s: float = 0.1, ceiling_m_s: float = 64.0) -> float:
    """The largest steady wind speed [m/s] (to ``resolution_m_s``, at most ``ceiling_m_s``) in
    which every drone keeps both margins whichever of ``STEADY_WIND_DIRECTIONS_DEG`` it blows from,
    with ``wind``'s turbulence, gusts and air density on top (still air at sea level when None):
    the margins hold at the speed returned and not at the next step up (bisection from still air,
    which assumes they shrink with the speed). 0 when even still air leaves less."""
    base = wind if wind is not None else Wind()

    def holds(speed_m_s: float) -> bool:
        winds = [design_winds_e_m_s(dataclasses.replace(base, speed_m_s=speed_m_s, from_deg=float(d)), turbulence_sigmas)
                 for d in STEADY_WIND_DIRECTIONS_DEG]
        demand = actuator_demand(rfl, leader, formation, times_s, base.air_density_kg_m3, np.concatenate(winds))
        return margin_problem(demand, rfl.airframe, rotor_speed_margin_pct, tilt_margin_deg, "") is None

    if not holds(0.0):
        return 0.0
    lo, hi = 0.0, 1.0
    while holds(hi):
        lo, hi = hi, 2.0 * hi
        if lo >= ceiling_m_s:
            return ceiling_m_s
    while hi - lo > resolution_m_s * (1.0 + 1e-9):
        mid = round(0.5 * (lo + hi) / resolution_m_s) * resolution_m_s
        if mid <= lo or mid >= hi:
            break
        lo, hi = (mid, hi) if holds(mid) else (lo, mid)
    return round(lo, 6)
