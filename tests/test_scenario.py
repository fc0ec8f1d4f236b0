"""The paper's case study, in-process (Section 5), with the servo delay and motor limit on.

Each run flies 50 s from rest on the ground; errors are measured on the plant's true state against
x0 + h_i(t) over [25 s, 50 s]."""


import numpy as np
import pytest

from triswarm.protocol import metrics
from triswarm.sitl.simulation import SensorNoise, SimConfig, delay_margin, simulate

pytestmark = pytest.mark.slow


def fly(plan, **kw):
    result = simulate(plan, SimConfig(**kw))
    pos_err, att_err = metrics.formation_errors(plan, result.t_s, result.position_m, result.euler_rad)
    return result, metrics.assess(result.t_s, pos_err, att_err)


def test_paper_case_study_with_servo_delay_and_motor_limit(paper_plan):
    result, perf = fly(paper_plan)
    assert result.plant_airframe.servo_delay_s == 0.01
    assert result.plant_airframe.max_rotor_speed_rad_s == pytest.approx(1256.637, abs=1e-3)
    assert result.diverged_at_s is None
    assert perf.worst_position_m <= 0.10 and perf.worst_attitude_rad <= 0.02, perf
    assert perf.convergence_time_s is not None and perf.convergence_time_s <= 25.0
    # starts resting level on the ground within 3 m of the origin, ends in the air
    assert np.all(result.position_m[0, :, 2] == 0) and np.all(np.linalg.norm(result.start_position_m, axis=1) <= 3.0)
    # the errata's edge of the actuators: some rotor tilts past ~90 deg
    assert np.degrees(np.abs(result.alpha_rad)).max() > 88.0


def test_with_sensor_noise(paper_plan):
    _, perf = fly(paper_plan, noise=SensorNoise(position_m=0.02, attitude_rad=0.005), seed=7)
    assert perf.worst_position_m <= 0.25 and perf.worst_attitude_rad <= 0.05, perf


def test_measured_body_rates_under_heavy_noise(paper_plan):
    """Noise four times the default (position 0.08 m, attitude 0.02 rad, gyro 0.04 rad/s): the
    observer with the measured rates as three more outputs flies the attitude closer than the
    observer alone (tests/bench/bench_rates.py; why it is not the default: docs/control-design.md).
    (Measured, seed 7: 0.0835 rad against 0.0946. The gap was wider, 0.085 against 0.120, before a
    rotor at the servo range's edge stopped winding up the observer alone's disturbance estimate.)"""
    noise = SensorNoise(position_m=0.08, attitude_rad=0.02, gyro_rad_s=0.04)
    _, alone = fly(paper_plan, noise=noise, seed=7)
    _, rates = fly(paper_plan, noise=noise, seed=7, measured_rates=True)
    assert rates.worst_attitude_rad < 0.95 * alone.worst_attitude_rad, (rates, alone)
    assert rates.worst_position_m < 0.15 and rates.worst_attitude_rad < 0.15, rates


def test_with_model_mismatch(paper_plan):
    """Plant mass and inertias 20 % above, k_f 10 % below the controller's values."""
    result, perf = fly(paper_plan, mismatch_pct=20.0)
    af = result.plant_airframe
    assert af.mass_kg == pytest.approx(0.6) and af.Izz_kg_m2 == pytest.approx(1.7e-3 * 1.2)
    assert af.k_f_N_s2 == pytest.approx(1.97e-5 * 0.9)
    assert perf.worst_position_m <= 0.5 and perf.worst_attitude_rad <= 0.1, perf
    # the thrust-effectiveness estimate found (k_f/m) plant / model = 0.9 / 1.2
    assert np.allclose(result.thrust_scale, 0.75, atol=0.01)


def test_delay_margin(paper_plan):
    """The design tolerates servo delays well past the paper's 0.01 s; without the delay
    compensation the same plant with 0.01 s flies a hundred times worse (the errata's warning; with
    the coupling margin of 2.25 it no longer leaves the bounds, as it did at margin 1)."""
    def within(result):
        pos_err, att_err = metrics.formation_errors(paper_plan, result.t_s, result.position_m, result.euler_rad)
        return result.diverged_at_s is None and metrics.assess(result.t_s, pos_err, att_err).within_bounds

    margin = delay_margin(paper_plan, SimConfig(), within, lo_s=0.01, hi_s=0.03, resolution_s=0.001)
    print(f"largest servo delay within 0.10 m / 0.02 rad: {margin * 1000:.1f} ms")
    assert margin >= 0.015
    # at twice the paper's delay the formation still holds, within the noise-level bounds
    result, perf = fly(paper_plan, servo_delay_s=0.02)
    assert result.diverged_at_s is None and perf.worst_position_m <= 0.25 and perf.worst_attitude_rad <= 0.05, perf

    _, compensated = fly(paper_plan)
    _, perf = fly(paper_plan, controller_delay_s=0.0)
    assert perf.worst_position_m > 100 * compensated.worst_position_m, (perf, compensated)
