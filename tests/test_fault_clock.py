"""A fault survived: the flight controller's clock jumps. Its Unix time (SYSTEM_TIME) is what a
scheduled start and plan time are read on; its boot time is what every sample is stamped with.

* On the ground, SYSTEM_TIME is taken as it comes (a GPS fix setting the clock before a flight).
* In flight, plan time runs on the boot clock: a step of the Unix time above OFFSET_STEP_US
  (forwards or backwards) is not taken and is said once; a smaller disagreement is followed at
  OFFSET_SLEW_PPM at most (a crystal's drift), so plan time never jumps.
* A boot time that goes back by REBOOT_JUMP_US or more is a reboot (the agent is lost until the
  flight controller is set up anew: ``test_fault_fc_lost.py``).

The unit tests check ``FcClock`` against the closed forms; the stack test sets the Unix clock of
flight controller 1 (as a ground station may: SYSTEM_TIME sent to it) 30 s forwards, then 60 s
back, mid-flight, on simulated time, and judges the formation against the paper's bounds on the
simulator's own clock."""

import re
import socket

import pytest
import tomli_w

from triswarm.companion.clock import OFFSET_SLEW_PPM, OFFSET_STEP_US, FcClock
from triswarm.gcs.recorder import Recorder
from triswarm.gcs.scenarios import load_plan
from triswarm.gcs.stack import Stack
from triswarm.protocol.mavlink import mavlink, new_codec

from .stack_helpers import judge, small_plan, wait_sim
from .poll import poll

UNIX_US = 1_800_000_000_000_000


def test_on_the_ground_a_step_is_taken():
    c = FcClock()
    c.set_offset(UNIX_US, 1000)
    c.set_offset(UNIX_US + 30_000_000 + 1_000_000, 2000)  # 1 s later, the clock set 30 s on
    assert c.offset_us == UNIX_US - 1_000_000 + 30_000_000
    assert c.refused_step_us is None


@pytest.mark.parametrize("step_us", [30_000_000, -30_000_000, OFFSET_STEP_US + 1, -(OFFSET_STEP_US + 1)])
def test_in_flight_a_step_is_refused_and_told(step_us):
    c = FcClock()
    c.set_offset(UNIX_US, 1000)
    c.steady = True
    c.set_offset(UNIX_US + 1_000_000 + step_us, 2000)
    assert c.offset_us == UNIX_US - 1_000_000  # plan time runs on as if nothing happened
    assert c.refused_step_us == step_us


@pytest.mark.parametrize("diff_us", [100_000, -100_000, 3_000])
def test_in_flight_a_drift_is_followed_no_faster_than_the_slew(diff_us):
    c = FcClock()
    c.set_offset(UNIX_US, 0)
    c.steady = True
    offsets = [c.offset_us]
    for k in range(1, 601):  # SYSTEM_TIME once a second for 10 min, every one diff_us off
        c.set_offset(UNIX_US + k * 1_000_000 + diff_us, k * 1000)
        offsets.append(c.offset_us)
    steps = [b - a for a, b in zip(offsets, offsets[1:])]
    assert max(abs(s) for s in steps) <= OFFSET_SLEW_PPM  # us per 1 s of boot time
    assert c.offset_us == UNIX_US + diff_us  # caught up: 100 ms takes 500 s at 200 ppm
    assert c.refused_step_us is None


def test_a_new_flight_controller_is_learnt_again():
    c = FcClock()
    c.set_offset(UNIX_US, 0)
    c.steady = True
    c.set_offset(UNIX_US + 60_000_000, 1000)
    c.forget()
    assert not c.known and c.refused_step_us is None and not c.steady
    c.set_offset(UNIX_US + 60_000_000, 1000)
    assert c.offset_us == UNIX_US + 59_000_000


def told_steps(log: str) -> list[float]:
    return [float(s) for s in re.findall(r"Unix time stepped ([-+][0-9.]+) s in flight: not taken", log)]


N = 2
STEPS = ((17.0, 30.0), (19.0, -60.0))
"""(plan time [s] to step at, the step of flight controller 1's Unix time [s]): forwards, then back
past where it was."""
JUDGED = (16.0, 26.0)  # plan time: the entry is over at 15 s


@pytest.mark.slow
def test_unix_clock_steps_in_flight_are_refused_and_the_formation_holds(tmp_path, paper_spec):
    plan_file = tmp_path / "pair.toml"
    plan_file.write_text(tomli_w.dumps(small_plan(paper_spec, N, "pair")))
    plan = load_plan(str(plan_file))
    codec = new_codec(255, 190)
    with Stack(plan_file, tmp_path / "stack", N, start_delay_s=5.0, lockstep=True, agents_per_process=0) as stack, \
            Recorder(stack.manifest) as rec, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        link = stack.manifest["vehicles"][0]["links"]["gcs"]
        sock.connect((link["host"], link["port"]))
        shift_s, told = 0.0, []
        for at_s, step_s in STEPS:
            wait_sim(rec.now, stack.start_at + at_s, stack)
            shift_s += step_s
            fc_unix_s = rec.now() + shift_s  # (the recorder's clock is vehicle 1's boot clock, unshifted)
            sock.send(mavlink.MAVLink_system_time_message(round(fc_unix_s * 1e6), 0).pack(codec))
            poll(lambda: len(told_steps(stack.log("companion-1"))) > len(told), 10.0,
                     f"companion 1 says its flight controller's clock stepped {shift_s:+.0f} s")
            told = told_steps(stack.log("companion-1"))
            # what it says: how far the Unix time now is from the one it flies on (the clock it
            # set aside), to within the recorder's lag behind the simulator
            assert abs(told[-1] - shift_s) < 1.0, (told, shift_s)
        wait_sim(rec.now, stack.start_at + JUDGED[1], stack)
    ok, worst = judge(plan, rec, stack.start_at, *JUDGED)
    assert ok, f"worst (position m, attitude rad) per drone over {JUDGED} s: {worst}"
    log = stack.log("companion-1")
    assert len(told_steps(log)) == len(STEPS), log[-3000:]  # each said once
    assert "flight controller lost" not in log and "holding" not in log, log[-3000:]
    assert stack.stats("sitl")["vehicles"][0]["counters"]["clock_set"] == len(STEPS)
    assert all(stack.stats(str(i))["tick_errors"] == 0 for i in range(1, N + 1))
