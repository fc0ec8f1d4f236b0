"""The ports a stack picks for its companions' listeners (which peers must know before they start):
free for TCP and UDP, below the kernel's ephemeral range, and never one picked twice. A stack (and the
demo) that cannot start says why in one sentence and leaves no process behind."""

import os
import signal
import subprocess
import sys

import pytest

from triswarm.gcs.stack import Stack, StackError, _below_ephemeral, free_ports


def test_ports_are_free_below_the_ephemeral_range_and_apart():
    lo, hi = _below_ephemeral()
    for _ in range(20):
        zenoh = free_ports(200, contiguous=True)
        assert zenoh == list(range(zenoh[0], zenoh[0] + 200))
        gcs = free_ports(200, exclude=frozenset(zenoh))
        assert len(set(gcs)) == 200 and not set(gcs) & set(zenoh)
        assert all(lo <= p < hi for p in zenoh + gcs)


def test_a_sitl_that_does_not_start_is_one_sentence_and_leaves_nothing(tmp_path):
    stack = Stack(None, tmp_path / "stack", 2, sitl_args=["--no-such-option"])
    with pytest.raises(StackError) as got:
        stack.__enter__()
    message = str(got.value)
    assert message.startswith("sitl did not start: ") and "--no-such-option" in message, message
    assert f"(log: {tmp_path / 'stack' / 'logs' / 'sitl.log'})" in message, message
    assert all(p.poll() is not None for p in stack.procs.values())


def test_the_demo_says_in_one_sentence_what_stops_it(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    r = subprocess.run([sys.executable, "-m", "triswarm.gcs.cli", "demo", "--out", str(blocker / "run")],
                       capture_output=True, text=True, timeout=120)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert lines[0].startswith(f"triswarm: error: cannot write the run folder {blocker / 'run'}"), lines


def test_no_free_ports_is_one_sentence():
    lo, hi = _below_ephemeral()
    with pytest.raises(StackError, match=rf"^no 5 free ports found below the ephemeral range \({lo}-{hi - 1}\)$"):
        free_ports(5, exclude=frozenset(range(lo, hi)), tries=3)
    with pytest.raises(StackError, match=rf"^no {hi - lo} free ports found below the ephemeral range .*: it has fewer$"):
        free_ports(hi - lo, contiguous=True)


def test_the_demo_says_in_one_sentence_that_the_sitl_did_not_start(tmp_path):
    run = tmp_path / "run"
    (run / "stack" / "manifest.json").mkdir(parents=True)  # where the sitl writes its manifest: it cannot
    r = subprocess.run([sys.executable, "-m", "triswarm.gcs.cli", "demo", "--out", str(run)],
                       capture_output=True, text=True, timeout=120)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 1 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    log = run / "stack" / "logs" / "sitl.log"
    assert lines[0] == (f"triswarm demo: the stack did not start: sitl did not start: triswarm: error: --manifest "
                        f"{run / 'stack' / 'manifest.json'}: cannot write it (Is a directory) (log: {log})"), lines


def test_the_demo_names_a_companion_that_stopped_at_start(tmp_path, capsys):
    """The demo's waits end, in one sentence, as soon as a process of the stack stops: which one, its
    exit status and the last line of its log (here a companion refusing its options)."""
    import typer

    from triswarm.gcs.demo import _wait

    stack = Stack(None, tmp_path / "stack", 2, companion_args={2: ["--rate-hz", "0"]})
    with stack:
        with pytest.raises(typer.Exit) as got:
            _wait(stack, "heartbeat from every drone and companion", lambda: "drones 1, 2 not heard", 60.0)
        assert got.value.exit_code == 1
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    log = tmp_path / "stack" / "logs" / "companion-2.log"
    assert lines == [f"triswarm demo: waiting for heartbeat from every drone and companion: companion-2 stopped "
                     f"(exit status 2): triswarm-companion: error: --rate-hz must be between 1 and 2000, got 0.0 "
                     f"(log: {log})"], lines
    assert all(p.poll() is not None for p in stack.procs.values())


def test_the_demo_gives_up_on_flight_controllers_gone_silent(tmp_path):
    """Flight controllers that fall silent while every process of the stack runs (a firmware that
    died, its simulator alive) end the demo's formation flight in one sentence: here the SITL is
    frozen (SIGSTOP), and both vehicles go unheard."""
    from triswarm.gcs.demo import _flight_problem
    from triswarm.gcs.link import GroundLink

    from .poll import poll

    stack = Stack(None, tmp_path / "stack", 2)
    with stack, GroundLink(stack.endpoints()) as link:
        poll(lambda: all(link.autopilot(i).heartbeat is not None for i in (1, 2)), 60.0, "both vehicles heard")
        assert _flight_problem(stack, link, [1, 2], silent_s=5.0) is None
        sitl = stack.procs["sitl"].pid
        os.kill(sitl, signal.SIGSTOP)
        try:
            poll(lambda: _flight_problem(stack, link, [1, 2], silent_s=5.0) is not None, 60.0, "the silence said")
        finally:
            os.kill(sitl, signal.SIGCONT)
        problem = _flight_problem(stack, link, [1, 2], silent_s=5.0)
    assert problem == f"the flight controllers of drones 1, 2 unheard for 5 s (logs in {tmp_path / 'stack' / 'logs'})"
    assert all(p.poll() is not None for p in stack.procs.values())
