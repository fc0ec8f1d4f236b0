"""Two lockstep runs of the same plan and seed give the same telemetry: the whole stack (sitl up
--lockstep, the companions in one process, Zenoh) flies the paper's plan for three drones twice, with
sensor noise on, and the flight controllers' own ATTITUDE and LOCAL_POSITION_NED agree to the last
bit at every instant both recorded. What still varies between runs is when things happen on the
wall clock, never what happens on the simulated one."""

import tomli_w
import pytest

from triswarm.gcs.recorder import Recorder
from triswarm.gcs.stack import Stack

from .stack_helpers import small_plan, wait_sim

pytestmark = pytest.mark.slow
N = 3
END = 12.0  # the climb, the start of the blend and two switches of graph


def fly(tmp_path, spec: dict) -> dict[int, dict[tuple[str, float], tuple]]:
    tmp_path.mkdir()
    plan_file = tmp_path / "plan.toml"
    plan_file.write_text(tomli_w.dumps(spec))
    noise = ["--param", "NOISE_POS_M=0.02", "--param", "NOISE_ATT_RAD=0.005"]
    with Stack(plan_file, tmp_path / "run", N, start_delay_s=4.0, lockstep=True, agents_per_process=0,
               sitl_args=noise) as stack, Recorder(stack.manifest) as rec:
        wait_sim(rec.now, stack.start_at + END, stack)
    # (stream, plan time rounded to the millisecond of the flight controller's clock) -> the sample
    return {sysid: {**{("position", round(t, 3)): tuple(p) for t, p in zip(tr.position_t_s, tr.position_m)},
                    **{("attitude", round(t, 3)): tuple(e) for t, e in zip(tr.attitude_t_s, tr.euler_rad)}}
            for sysid, tr in rec.tracks(stack.start_at).items()}


def test_two_lockstep_runs_give_the_same_telemetry(tmp_path, paper_spec):
    spec = small_plan(paper_spec, N, "trio")
    spec["topology"]["families"] = ["two-chain", "reverse-two-chain"]  # switching, and neighbours both ways
    one, two = fly(tmp_path / "one", spec), fly(tmp_path / "two", spec)
    for sysid in range(1, N + 1):
        common = sorted(set(one[sysid]) & set(two[sysid]))
        assert len(common) > 2 * 25 * END * 0.8, (sysid, len(common))  # the recorder's 25 Hz per stream
        flying = [(kind, t) for kind, t in common if kind == "position" and t > 5.0]
        assert flying, common[-5:]
        moved = {one[sysid][k][0] for k in flying}
        assert len(moved) > 100  # (it flew: the samples differ from one another)
        differ = [t for t in common if one[sysid][t] != two[sysid][t]]
        assert not differ, f"drone {sysid}: first difference at plan time {differ[0]} s: " \
                           f"{one[sysid][differ[0]]} vs {two[sysid][differ[0]]}"
