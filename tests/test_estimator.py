"""Estimator profiles (``sitl.estimator``): what a flight controller's estimator reports, against
closed forms (the bias process's stationary spread and correlation, a lag as a shift of a known
ramp), and the formation flown on them in-process (``triswarm sim --estimator``)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from triswarm.sitl.estimator import PROFILES, Estimator, EstimatorProfile, profile
from triswarm.sitl.simulation import SensorNoise, SimConfig, simulate
from triswarm.protocol import metrics

DT = 0.005  # [s]
QUIET = EstimatorProfile("quiet", position_noise_m=0.0, attitude_noise_rad=0.0, gyro_noise_rad_s=0.0,
                         position_bias_m=0.0, attitude_bias_rad=0.0, bias_time_s=60.0, lag_s=0.0)


@pytest.mark.parametrize("smoothing_s", [0.0, 0.5])
def test_the_bias_wanders_with_the_stated_spread_and_correlation_time(smoothing_s):
    """A first-order Gauss-Markov bias (tau) seen through a first-order lag (T): stationary standard
    deviation sigma sqrt(tau / (tau + T)) (vertical: 1.5 times), correlation exp(-t / tau) after t
    without the lag; over 4000 vehicles the estimates are within a few percent."""
    prof = dataclasses.replace(QUIET, position_bias_m=0.5, attitude_bias_rad=0.01, bias_time_s=2.0,
                               smoothing_s=smoothing_s)
    seen = math.sqrt(prof.bias_time_s / (prof.bias_time_s + smoothing_s))
    n, rng = 4000, np.random.default_rng(3)
    est = Estimator(prof, n, rng)
    zero_y, zero_rates = np.zeros((n, 6)), np.zeros((n, 3))
    steps = int(5.0 / DT)
    for k in range(steps):
        est.report(k * DT, zero_y, zero_rates)
    before = est.position_bias_m.copy()
    for k in range(steps, steps + int(prof.bias_time_s / DT)):
        y, _, _ = est.report(k * DT, zero_y, zero_rates)
    std = est.position_bias_m.std(axis=0)
    assert std == pytest.approx(np.array([0.5, 0.5, 0.75]) * seen, rel=0.05)
    assert est.attitude_bias_rad.std() == pytest.approx(0.01 * seen, rel=0.05)
    if smoothing_s == 0.0:
        corr = np.corrcoef(before[:, 0], est.position_bias_m[:, 0])[0, 1]
        assert corr == pytest.approx(math.exp(-1.0), abs=0.04)
    assert np.array_equal(y[:, 3:6], est.position_bias_m)  # (what it reports is the truth plus its bias)


def test_a_lag_reports_the_truth_that_long_ago_even_between_periods():
    """On a ramp, linear interpolation is exact: a lag of 2.4 periods reports y(t - 2.4 dt), angles
    the short way round through +-pi, a velocity too; reports at uneven instants alike."""
    prof = dataclasses.replace(QUIET, lag_s=2.4 * DT)
    est = Estimator(prof, 1, np.random.default_rng(0))
    v, yaw_rate = np.array([1.0, -2.0, 0.5]), 10.0
    t = 0.0
    for k in range(200):
        t += DT * (0.5 if k % 3 else 1.5)  # (uneven: the SITL reports when telemetry is due)
        yaw = (3.0 + yaw_rate * t + math.pi) % (2 * math.pi) - math.pi  # (it crosses +-pi)
        y = np.concatenate([[0.0, 0.0, yaw], v * t])[None, :]
        out, rates, velocity = est.report(t, y, np.full((1, 3), t), v[None, :] * t)
    then = t - 2.4 * DT
    assert out[0, 3:6] == pytest.approx(v * then, abs=1e-12)
    assert velocity[0] == pytest.approx(v * then, abs=1e-12)
    expected_yaw = (3.0 + yaw_rate * then + math.pi) % (2 * math.pi) - math.pi
    assert math.remainder(out[0, 2] - expected_yaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    assert rates[0] == pytest.approx([then] * 3, abs=1e-12)


def test_profiles_are_named_and_an_unknown_one_is_refused():
    assert set(PROFILES) == {"truth", "mocap", "rtk", "gps"}
    assert profile("rtk").position_bias_m < profile("gps").position_bias_m
    with pytest.raises(ValueError, match="no estimator profile 'galileo': one of truth, mocap, rtk, gps"):
        profile("galileo")
    with pytest.raises(ValueError, match="give one"):
        SimConfig(noise=SensorNoise(), estimator=profile("rtk"))


def worst(result) -> tuple[float, float]:
    plan = result.plan
    perf, _ = metrics.judge(plan, result.t_s, result.position_m, result.euler_rad)
    return perf.worst_position_m, perf.worst_attitude_rad


@pytest.mark.parametrize("seed", [0, 1])
def test_the_paper_bounds_need_rtk_class_positioning(paper_plan, seed):
    """The case study in still air, on simulated time: with RTK's estimates the formation keeps the
    paper's 0.10 m / 0.02 rad; with plain GNSS's it misses them by its wandering bias, and stays
    bounded."""
    rtk = worst(simulate(paper_plan, SimConfig(duration_s=40.0, estimator=profile("rtk"), seed=seed)))
    gps = simulate(paper_plan, SimConfig(duration_s=40.0, estimator=profile("gps"), seed=seed))
    assert rtk[0] <= 0.10 and rtk[1] <= 0.02, rtk
    assert gps.diverged_at_s is None and 0.10 < worst(gps)[0] < 5.0, worst(gps)


def test_the_simulated_flight_controllers_report_their_estimators_output():
    """``sitl up --estimator``: a vehicle's snapshot is its estimator's report (the truth lag_s ago
    plus the bias), the quaternion and body velocity made from it, before any NOISE_* noise."""
    from triswarm.sitl.swarm import SitlSwarm

    prof = dataclasses.replace(QUIET, position_bias_m=0.3, attitude_bias_rad=0.01, bias_time_s=1e9, lag_s=0.0)
    plain, estimated = SitlSwarm(2, seed=4), SitlSwarm(2, seed=4, estimator=prof)
    truth, rows = plain.sensor_rows(), estimated.sensor_rows()
    bias = estimated.estimator.position_bias_m
    assert np.abs(bias[:, :2]).max() > 0.01 and np.all(bias[:, 2] == 0.0)  # (the height's starts at zero)
    assert rows.position_m == pytest.approx(truth.position_m + bias, abs=1e-12)
    assert rows.euler_rad == pytest.approx(truth.euler_rad + estimated.estimator.attitude_bias_rad, abs=1e-12)
    from triswarm.sitl.physics import quaternion_from_euler

    assert rows.quaternion == pytest.approx(quaternion_from_euler(rows.euler_rad), abs=1e-12)
