"""The latency a plan's controllers compensate ([controller] latency_s): from the instant a
measurement is stamped with to the flight controller taking the command that answers it. A compensated
latency is flown as no latency at all (the loop is the latency-free loop, shifted); one that is not
compensated, or not there, costs centimetres. Judged on simulated time."""

import dataclasses

import pytest

from triswarm.protocol import metrics
from triswarm.sitl.simulation import SimConfig, command_latency_s, simulate


def with_latency(plan, latency_s):
    return dataclasses.replace(plan, controller=dataclasses.replace(plan.controller, latency_s=latency_s))


def worst(plan, world_latency_s):
    """The worst position and attitude errors of a 30 s flight, over [25, 30] s."""
    r = simulate(plan, SimConfig(duration_s=30.0, latency_s=world_latency_s))
    assert r.diverged_at_s is None
    perf, _ = metrics.judge(plan, r.t_s, r.position_m, r.euler_rad, window_start_s=25.0)
    return perf.worst_position_m, perf.worst_attitude_rad


def test_a_compensated_latency_is_flown_as_none(paper_plan):
    none = worst(paper_plan, 0.0)
    late = worst(paper_plan, 0.02)  # measured: 0.025 m, 0.0055 rad
    compensated = worst(with_latency(paper_plan, 0.02), 0.02)  # measured: as without latency, 1.8e-5 m
    assumed = worst(with_latency(paper_plan, 0.02), 0.0)  # measured: 0.027 m
    assert none[0] < 1e-4 and none[1] < 1e-5
    assert compensated[0] == pytest.approx(none[0], rel=0.05) and compensated[1] == pytest.approx(none[1], rel=0.05)
    assert late[0] > 100 * none[0] and assumed[0] > 100 * none[0]


def test_a_simulation_flies_the_plans_latency_unless_told_another(paper_plan):
    assert command_latency_s(with_latency(paper_plan, 0.01), SimConfig()) == 0.01
    assert command_latency_s(with_latency(paper_plan, 0.01), SimConfig(latency_s=0.0)) == 0.0
    assert command_latency_s(paper_plan, SimConfig(latency_s=0.03)) == 0.03
    with pytest.raises(ValueError, match="latency must be between 0 and 1 s, got -0.01"):
        SimConfig(latency_s=-0.01)
