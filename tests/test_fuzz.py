"""Every face of the companion under a few thousand fuzz inputs (``make fuzz`` gives each 100,000):
the companion raises nothing, still answers a valid request afterwards, and its own drop counters
moved by exactly what the oracle says (tests/fuzz/). Bounded in inputs and time, not judged on
speed."""

from __future__ import annotations

import pytest

from .fuzz.mavlink_faces import fuzz_fc, fuzz_gcs
from .fuzz.missions import fuzz_missions
from .fuzz.plan_files import fuzz_plan_files
from .fuzz.stack_faces import FACES as STACK_FACES, fuzz_stack
from .fuzz.zenoh_face import fuzz_zenoh

N = 3000
N_VALUES = 1500
"""Hostile values per stack face: every message of the dialect at least once, several times over."""


def judged(report, *must_move: str):
    assert report.inputs == N, report.text()
    assert not report.problems, report.text()
    for key in must_move:  # (an oracle that expects nothing judges nothing)
        assert report.expected.get(key, 0) > 0, report.text()
    return report


@pytest.mark.timeout(240)
def test_ground_station_link_unsigned(tmp_path):
    judged(fuzz_gcs(N, tmp_path), "drop_bad_data", "drop_partial_frame")


@pytest.mark.timeout(240)
def test_ground_station_link_signed(tmp_path):
    judged(fuzz_gcs(N, tmp_path, signed=True), "drop_bad_data", "refused_unsigned", "refused_bad_signature",
           "refused_replay")


@pytest.mark.timeout(240)
def test_flight_controller_link(tmp_path):
    report = judged(fuzz_fc(N, tmp_path), "drop_bad_data", "drop_partial_frame")
    assert report.other["telemetry.attitude_out_of_order"] > 0, report.text()


@pytest.mark.timeout(240)
def test_mission_protocol(tmp_path):
    judged(fuzz_missions(N, tmp_path), "uploads_started", "items_out_of_order", "items_unexpected", "uploads_refused",
           "uploads_cancelled")


@pytest.mark.timeout(240)
def test_zenoh_keys(tmp_path):
    judged(fuzz_zenoh(N, tmp_path), "estimate_outcomes", "drop_unknown_agent", "drop_other_plan", "drop_bad_status",
           "drop_bad_liveliness")


@pytest.mark.timeout(240)
def test_plan_files():
    report = judged(fuzz_plan_files(N))
    for kind in ("random_document", "mutated_plan", "mutated_text"):
        assert report.counters.get(f"{kind}.refused", 0) > 0, report.text()
    assert report.counters.get("mutated_plan.accepted", 0) > 0, report.text()


@pytest.mark.slow
@pytest.mark.timeout(400)
@pytest.mark.parametrize("face", STACK_FACES)
def test_valid_messages_with_hostile_values(tmp_path, face):
    """Every message of the dialect with its fields at their boundaries, commands and parameter
    sets with hostile values, at the SITL's two links and through the companion's routing: nothing
    raises, both vehicles answer throughout, the other vehicle is untouched, and afterwards the two
    drones fly a plan within its bounds."""
    report = fuzz_stack(face, N_VALUES, tmp_path)
    assert report.inputs == N_VALUES and not report.problems, report.text()
    assert report.sent["one_boundary"] >= 210 and report.sent["command"] > 0 and report.sent["param_set"] > 0
