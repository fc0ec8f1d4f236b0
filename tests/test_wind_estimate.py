"""The controllers' wind estimate, in-process on simulated time with seeds, in the law without an
accelerometer ([controller] accelerometer = false: a flight controller that streams none; with one
the accelerometer measures what the wind does, tests/test_accelerometer.py): it finds a steady wind
(the plant's, an independent truth), the circling case study then flies as in no air, and the worst
air of docs/wind.md (12 m/s, severe turbulence, a 6 m/s gust) and an 8 m/s wind with moderate
turbulence at 50 drones, which diverged without it, stay bounded. Each flight also runs with the
estimate off ([controller] wind_estimate_rate_1_s = 0), which must fail the same assertions."""

import dataclasses

import numpy as np
import pytest

from triswarm.gcs.scenarios import load_plan
from triswarm.protocol import metrics
from triswarm.protocol.wind import TURBULENCE_SIGMA_W_M_S, Gust, Wind
from triswarm.sitl.simulation import SimConfig, simulate


def fly(n_drones: int, wind: Wind, wind_estimate_rate_1_s: float | None = None, seed: int = 0):
    """The case study resized to n_drones (``triswarm sim --drones N``), flown its 60 s in wind."""
    plan = load_plan("paper-hexagon", n_drones)
    plan = dataclasses.replace(plan, controller=dataclasses.replace(plan.controller, accelerometer=False))
    if wind_estimate_rate_1_s is not None:
        plan = dataclasses.replace(plan, controller=dataclasses.replace(plan.controller,
                                                                        wind_estimate_rate_1_s=wind_estimate_rate_1_s))
    result = simulate(plan, SimConfig(duration_s=plan.duration_s, wind=wind, seed=seed))
    perf, _ = metrics.judge(plan, result.t_s, result.position_m, result.euler_rad,
                            metrics.settled_window_start_s(plan, plan.duration_s))
    return result, perf


@pytest.mark.parametrize("estimated", [True, False], ids=["estimated", "off"])
def test_a_steady_wind_is_found_and_the_circling_case_study_flies_as_in_no_air(estimated):
    """8 m/s from the west. Measured: every drone's estimate within 1e-4 m/s of the plant's wind,
    and 0.0031 m / 0.0092 rad over the settled window (from the north: 4 m/s 1.8e-5 m, as in no
    air); without the estimate the wind's share of the drag turns with each drone and leaves about
    0.35 m and 0.095 rad. Held to the paper's 0.10 m / 0.02 rad."""
    wind = Wind(speed_m_s=8.0, from_deg=270.0)
    result, perf = fly(6, wind, None if estimated else 0.0)
    assert result.diverged_at_s is None
    found = np.abs(result.wind_estimate_e_m_s - wind.steady_e_m_s).max() < 0.01
    held = perf.worst_position_m < 0.10 and perf.worst_attitude_rad < 0.02
    assert (found and held) == estimated, (result.wind_estimate_e_m_s, perf)


WORST_AIR = Wind(speed_m_s=12.0, turbulence_sigma_w_m_s=TURBULENCE_SIGMA_W_M_S["severe"],
                 gusts=(Gust(speed_m_s=6.0, duration_s=2.0, start_s=40.0),))


@pytest.mark.parametrize("estimated", [True, False], ids=["estimated", "off"])
def test_six_drones_in_the_worst_air_stay_bounded(estimated):
    """12 m/s, severe turbulence, a 6 m/s gust at 40 s. Measured (seed 0): 0.56 m; the attitude
    reaches 0.31 rad where the airframe runs out of tilt (docs/wind.md). Without the estimate 0.86 m
    and 0.22 rad (it diverged at 47 s before the observer was told what a rotor at the servo range's
    edge delivers: tests/test_servo_saturation.py). Held to 0.75 m of position, no divergence."""
    result, perf = fly(6, WORST_AIR, None if estimated else 0.0)
    bounded = result.diverged_at_s is None and perf.worst_position_m < 0.75
    assert bounded == estimated, (result.diverged_at_s, perf)


@pytest.mark.slow
@pytest.mark.parametrize("estimated", [True, False], ids=["estimated", "off"])
def test_fifty_drones_in_8_m_s_with_moderate_turbulence_stay_bounded(estimated):
    """8 m/s from the north with moderate turbulence, 50 drones. Measured (seed 0): 0.47 m and
    0.099 rad (outside the 0.25 m / 0.05 rad aimed at: docs/wind.md says where it goes); without
    the estimate the thrust-effectiveness estimate winds down to its limit and the swarm is lost.
    Held to 0.6 m and 0.15 rad."""
    wind = Wind(speed_m_s=8.0, turbulence_sigma_w_m_s=TURBULENCE_SIGMA_W_M_S["moderate"])
    result, perf = fly(50, wind, None if estimated else 0.0)
    bounded = result.diverged_at_s is None and perf.worst_position_m < 0.6 and perf.worst_attitude_rad < 0.15
    assert bounded == estimated, (result.diverged_at_s, perf)
