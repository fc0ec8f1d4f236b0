"""Nothing left behind: a launcher killed outright (SIGKILL: what pytest-timeout's thread method, an
out-of-memory kill or a crash of the interpreter does, with no chance to stop anything) leaves
none of the processes it started running: not the SITL, not a companion, not a firmware
(``sitl/processes.py``). Survivors are looked for by the run folder in their command lines."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .firmware_helpers import arducopter

ROOT = Path(__file__).resolve().parents[1]
GONE_WITHIN_S = 20.0  # (the companions end on SIGTERM; a firmware's group gets SIGKILL 2 s after)


def running_with(marker: str) -> list[str]:
    """Command lines of the processes (but this one) that name ``marker``."""
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        if int(pid) == os.getpid():
            continue
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # (gone meanwhile)
            continue
        if marker in cmdline:
            found.append(f"{pid}: {cmdline[:160]}")
    return found


def kill_when(cmd: list[str], ready, timeout_s: float, out: Path, marker: str) -> list[str]:
    """Start ``cmd``, SIGKILL it once ``ready()`` holds (within ``timeout_s``); what ran with
    ``marker`` just before."""
    with out.open("w") as log:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + timeout_s
            while not ready():
                assert proc.poll() is None, f"it ended before it was killed: {out.read_text()[-2000:]}"
                assert time.monotonic() < deadline, f"not ready within {timeout_s} s: {out.read_text()[-2000:]}"
                time.sleep(0.2)
            before = running_with(marker)
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
    return [line for line in before if not line.startswith(f"{proc.pid}:")]


def assert_nothing_left(marker: str) -> None:
    deadline = time.monotonic() + GONE_WITHIN_S
    while (left := running_with(marker)) and time.monotonic() < deadline:
        time.sleep(0.2)
    for line in left:  # (leave nothing behind ourselves either)
        os.kill(int(line.split(":")[0]), signal.SIGKILL)
    assert not left, f"still running {GONE_WITHIN_S:g} s after their launcher was killed: {left}"


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_demo_killed_in_flight_leaves_nothing_running(tmp_path):
    run = tmp_path / "run"
    out = tmp_path / "demo.out"
    started = kill_when([sys.executable, "-m", "triswarm.gcs.cli", "demo", "--lockstep", "--max-rtf", "1", "--out",
                         str(run)], lambda: "plan start" in out.read_text(errors="replace"), 240.0, out, str(run))
    assert len(started) >= 2, started  # (the SITL and the companions flew)
    assert_nothing_left(str(run))


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_firmware_sitl_killed_leaves_no_firmware_running(tmp_path):
    run = tmp_path / "firmwares"
    manifest = tmp_path / "manifest.json"
    started = kill_when([sys.executable, "-m", "triswarm.gcs.cli", "sitl", "up", "--autopilot", "ardupilot", "-n", "2",
                         "--firmware", str(arducopter()), "--run-dir", str(run), "--manifest", str(manifest), "--quiet"],
                        manifest.is_file, 120.0, tmp_path / "sitl.out", str(run))
    assert len(started) >= 2, started  # (both firmwares ran)
    assert_nothing_left(str(run))
