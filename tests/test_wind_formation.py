"""What the formation control holds in wind, in-process: the case study in still air, with the drag
of its own 10 m/s cancelled by the controllers and without; the hexagon of the case study held still
(examples/still-hexagon.toml), so that only the wind moves air past the drones (docs/wind.md has
the whole table, tests/bench/bench_wind.py makes it)."""

import copy
import dataclasses

import pytest

from triswarm.gcs.scenarios import load_plan
from triswarm.protocol import metrics
from triswarm.protocol.plan import plan_from_dict
from triswarm.protocol.wind import TURBULENCE_SIGMA_W_M_S, Wind
from triswarm.sitl.simulation import SimConfig, simulate

from .conftest import ROOT

STILL_HEXAGON = str(ROOT / "examples" / "still-hexagon.toml")


def fly(wind: Wind, seed: int = 0, plan=None, bounds=(0.25, 0.05), accelerometer: bool = True):
    plan = plan or load_plan(STILL_HEXAGON)
    plan = dataclasses.replace(plan, controller=dataclasses.replace(plan.controller, accelerometer=accelerometer))
    result = simulate(plan, SimConfig(duration_s=plan.duration_s, wind=wind, seed=seed))
    pos_err, att_err = metrics.formation_errors(plan, result.t_s, result.position_m, result.euler_rad)
    return result, metrics.assess(result.t_s, pos_err, att_err, window_start_s=plan.settled_from_s,
                                  position_bound_m=bounds[0], attitude_bound_rad=bounds[1])


def test_the_case_study_in_still_air_keeps_the_papers_bounds(paper_plan):
    """Circling at 10 m/s each drone feels 1.2 N of drag turning with it; the controllers cancel it
    in the RFL. Measured 2.0e-5 m and 1.1e-6 rad over the settled window (1.8e-5 m and 8.2e-7 rad in
    no air at all); held here to a tenth of the paper's 0.10 m and 0.02 rad."""
    result, perf = fly(Wind(), plan=paper_plan, bounds=(0.01, 0.002))
    assert result.diverged_at_s is None
    assert perf.within_bounds, perf


@pytest.mark.parametrize("accelerometer", [False, True], ids=["no-accelerometer", "accelerometer"])
def test_without_the_drag_term_the_case_study_in_still_air_needs_the_accelerometer(paper_spec, accelerometer):
    """The same flight with the controllers told there is no air ([controller] air_density_kg_m3 = 0).
    Without the accelerometer the constant-disturbance observer follows the turning drag 15 deg
    late: measured 0.31 m, 0.066 rad, past the paper's bounds. With it the observer measures the
    drag: 0.010 m, 0.0039 rad, within them."""
    spec = copy.deepcopy(paper_spec)
    spec["controller"]["air_density_kg_m3"] = 0.0
    result, perf = fly(Wind(), plan=plan_from_dict(spec), bounds=(0.10, 0.02), accelerometer=accelerometer)
    assert result.diverged_at_s is None
    assert perf.within_bounds == accelerometer, perf
    assert accelerometer or perf.worst_position_m > 0.2, perf


@pytest.mark.slow
def test_an_8_m_s_westerly_with_moderate_turbulence_is_held_within_the_papers_bounds():
    """With the accelerometer, measured (seed 0): 0.0046 m and 0.0030 rad over the settled window,
    held to the paper's 0.10 m / 0.02 rad. Without it, over seeds 0-5: worst 0.097-0.166 m and
    0.022-0.039 rad (the paper's bounds break from 3.5 m/s of wind with this turbulence), held to
    0.25 m and 0.05 rad, 1.5 and 1.3 times the worst measured, and more than 0.05 m: the turbulence
    does move the drones."""
    wind = Wind(speed_m_s=8.0, from_deg=270.0, turbulence_sigma_w_m_s=TURBULENCE_SIGMA_W_M_S["moderate"])
    result, perf = fly(wind, bounds=(0.10, 0.02))
    assert result.diverged_at_s is None
    assert perf.within_bounds, perf
    result, perf = fly(wind, accelerometer=False)
    assert result.diverged_at_s is None
    assert perf.within_bounds and perf.worst_position_m > 0.05, perf


def test_a_wind_far_past_the_measured_limit_breaks_the_formation():
    """The steady wind is rejected to 1e-5 m up to 20 m/s and diverges from 20.5 m/s (a rotor must
    tilt past 90 deg); at 30 m/s the formation is lost."""
    result, perf = fly(Wind(speed_m_s=30.0, from_deg=270.0))
    assert result.diverged_at_s is not None or not perf.within_bounds
