"""Flying a plan in the in-process simulation before `plan check` says OK, and judging the flight.

The flight: ``sitl.simulation.simulate`` with the plan's own airframe as the plant (nominal: its
servo delay and motor limit, no noise, no mismatch), every drone from rest on the ground, over the
plan's length, in the plan's air (its [wind], turbulence seeded 0; no air when it has none). The verdict: every drone within check.position_bound_m and check.attitude_bound_rad
of its reference x0 + h_i(t) over the settled window [entry end + check.settle_s, end].
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from triswarm.protocol import metrics
from triswarm.protocol.airframe import RPM_TO_RAD_S
from triswarm.protocol.plan import Plan
from triswarm.protocol.wind import Wind
from triswarm.sitl.simulation import SimConfig, SimResult, flown_wind, simulate


@dataclass(frozen=True)
class Flight:
    result: SimResult
    performance: metrics.Performance
    window_s: tuple[float, float]
    problem: str | None
    """Why the flight refuses the plan (one sentence, without the source), or None."""
    wind: Wind | None = None
    """The air it was flown in (None: no air)."""

    def summary(self) -> dict:
        return {"flown": True, "duration_s": self.window_s[1], "settled_window_s": list(self.window_s),
                "wind": None if self.wind is None else self.wind.describe(),
                "wall_time_s": self.result.wall_s, "diverged_at_s": self.result.diverged_at_s,
                "performance": self.performance.as_dict(), "problem": self.problem}


def fly(plan: Plan, duration_s: float | None = None, progress: Callable[[float], None] | None = None) -> Flight:
    """Fly ``plan`` for ``duration_s`` (default: the plan's duration) and judge it."""
    duration = plan.duration_s if duration_s is None else duration_s
    config = SimConfig(duration_s=duration)
    result = simulate(plan, config, progress=progress)
    pos_err, att_err = metrics.formation_errors(plan, result.t_s, result.position_m, result.euler_rad)
    bounds = plan.check_settings
    window = (plan.settled_from_s, duration)
    perf = metrics.assess(result.t_s, pos_err, att_err, window_start_s=window[0], position_bound_m=bounds.position_bound_m,
                          attitude_bound_rad=bounds.attitude_bound_rad)
    return Flight(result, perf, window, flight_problem(plan, result, perf, window), flown_wind(plan, config))


def flight_problem(plan: Plan, result: SimResult, perf: metrics.Performance, window: tuple[float, float]) -> str | None:
    """One sentence on what went wrong in the flight, or None."""
    af = plan.airframe
    late = f", {plan.controller.latency_s * 1000:g} ms latency" if plan.controller.latency_s else ""
    speed = f", servos of {math.degrees(af.servo_rate_rad_s):.0f} deg/s" if af.servo_rate_rad_s else ""
    how = (f"flown in simulation (the plan's airframe: {af.servo_delay_s * 1000:g} ms servo delay{speed}{late}, "
           f"{af.max_rotor_speed_rad_s / RPM_TO_RAD_S:.0f} RPM motor limit; from the ground)")
    if result.diverged_at_s is not None:
        return (f"{how}, the formation diverged: drone {result.diverged_drone}'s state left the valid range at "
                f"t = {result.diverged_at_s:.2f} s")
    span = f"over the settled window [{window[0]:.3g} s, {window[1]:.3g} s]"
    if not math.isfinite(perf.worst_position_m):
        return f"{how}, the flight ended before the settled window began"
    if perf.worst_position_m > perf.position_bound_m:
        return (f"{how}, drone {perf.worst_position_drone} was {perf.worst_position_m:.3g} m from its reference at "
                f"t = {perf.worst_position_t_s:.2f} s, past the {perf.position_bound_m:g} m bound {span} "
                f"(check.position_bound_m)")
    if perf.worst_attitude_rad > perf.attitude_bound_rad:
        return (f"{how}, drone {perf.worst_attitude_drone}'s attitude was {perf.worst_attitude_rad:.3g} rad off its "
                f"reference at t = {perf.worst_attitude_t_s:.2f} s, past the {perf.attitude_bound_rad:g} rad bound "
                f"{span} (check.attitude_bound_rad)")
    return None
