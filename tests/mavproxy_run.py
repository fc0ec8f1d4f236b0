"""MAVProxy, a third-party client, run non-interactively until it has saved a file: its download is
judged by what it says it saved, never by how long it took."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

from .poll import poll

# printed by MAVProxy once the file is closed: "Saved 12 parameters to /x/mav.parm", "Saved 9 waypoints to /x/plan.txt"
SAVED = re.compile(r"^Saved (\d+) (\w+) to (.+)\n", re.MULTILINE)


def mavproxy_until_saved(args: list[str], cmds: str, workdir: Path, timeout_s: float = 60.0) -> tuple[int, Path]:
    """Run ``mavproxy.py ARGS --cmd=CMDS`` in ``workdir`` until it says it saved a file, for at most
    ``timeout_s``; then stop it. Returns the count it saved and the file. AssertionError with what it
    printed if it said nothing of the kind in time."""
    mavproxy = Path(sys.executable).with_name("mavproxy.py")
    assert mavproxy.exists(), "MAVProxy is installed by `make test` (Makefile)"
    home = workdir / "mavproxy-home"
    home.mkdir(parents=True, exist_ok=True)
    printed = workdir / "mavproxy.out"
    cmd = [sys.executable, str(mavproxy), *args, "--non-interactive", f"--state-basedir={workdir / 'mavproxy-state'}",
           f"--cmd={cmds}"]
    env = dict(os.environ, HOME=str(home), PYTHONUNBUFFERED="1")
    with open(printed, "w") as sink:
        proc = subprocess.Popen(cmd, cwd=workdir, env=env, stdin=subprocess.DEVNULL, stdout=sink,
                                stderr=subprocess.STDOUT, start_new_session=True)
        try:
            def said() -> re.Match | None:
                return SAVED.search(printed.read_text(errors="replace"))

            poll(lambda: said() is not None or proc.poll() is not None, timeout_s)
            found = said()
            assert found, f"MAVProxy saved nothing in {timeout_s:g} s (exit {proc.poll()}):\n" + \
                printed.read_text(errors="replace")[-3000:]
            return int(found.group(1)), Path(found.group(3).strip())
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
