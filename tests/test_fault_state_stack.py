"""A fault survived, through the whole stack on simulated time: companion 1's state folder will not
take its mission (the path of mission.json is a folder: as root, mode bits would not stop a write).
Its flight is unharmed: both drones take off, enter and hold the formation within the paper's bounds,
judged from the flight controllers' own telemetry; the companion says so once, in its log and to its
ground station (if one is listening then: the first attempt comes as the plan is scheduled at start),
although it tries to write the mission at every change (scheduled, flying), and counts the failures
in its health report and stats."""

import pytest
import tomli_w

from triswarm.gcs.recorder import Recorder
from triswarm.gcs.scenarios import load_plan
from triswarm.gcs.stack import Stack

from .stack_helpers import GroundStation, judge, small_plan, wait_sim

pytestmark = pytest.mark.slow
N = 2
JUDGED = (16.0, 22.0)  # plan time: the entry is over at 15 s


def test_flight_unharmed_with_a_state_folder_that_takes_no_write(tmp_path, paper_spec):
    plan_file = tmp_path / "pair.toml"
    plan_file.write_text(tomli_w.dumps(small_plan(paper_spec, N, "pair")))
    plan = load_plan(str(plan_file))
    workdir = tmp_path / "stack"
    (workdir / "state" / "1" / "mission.json").mkdir(parents=True)
    with Stack(plan_file, workdir, N, start_delay_s=5.0, lockstep=True, agents_per_process=0) as stack, \
            Recorder(stack.manifest) as rec, GroundStation(stack.gcs_ports[0]) as gcs:
        wait_sim(rec.now, stack.start_at + JUDGED[1], stack)
        texts = "".join(m.text for m in gcs.heard("STATUSTEXT", srcSystem=1, srcComponent=191))
    ok, worst = judge(plan, rec, stack.start_at, *JUDGED)
    assert ok, f"worst (position m, attitude rad) per drone over {JUDGED} s: {worst}"
    log = stack.log("companion-1")
    assert log.count("companion 1: cannot write") == 1, log[-3000:]
    assert "mission.json (Is a directory)" in log and "plan not started" not in log, log[-3000:]
    assert "companion 1: in formation" in texts and texts.count("companion 1: cannot write") <= 1, texts
    assert stack.stats("1")["state_write_failures"] >= 2  # (scheduled, flying)
    assert stack.stats("2")["state_write_failures"] == 0
    assert (workdir / "state" / "2" / "mission.json").is_file()  # (the other's folder works)
    assert stack.procs[stack.process_of[1]].returncode == 0
    assert all(stack.stats(str(i))["tick_errors"] == 0 for i in range(1, N + 1))
