"""Run the stack ahead of the machine's other work, for the tests that judge something on the wall
clock: ``prioritise(nice)`` in a process, or ``python tests/priority.py NICE CMD...`` to start a
command that way (as root, as the network tests run).

Niceness alone does not do it on a kernel with autogroups, which share the CPU fairly between
sessions whatever their niceness: a session of its own at that niceness too. (A real-time policy,
SCHED_FIFO, was tried and dropped: a companion process at that priority once spun at full CPU in its
start-up and starved the machine.)"""

from __future__ import annotations

import os
import sys
from pathlib import Path


def prioritise(nice: int) -> dict:
    """This process, and what it starts from now on, at niceness ``nice`` in a session of its own."""
    os.setpriority(os.PRIO_PROCESS, 0, nice)
    autogroup = Path("/proc/self/autogroup")
    if autogroup.exists() and nice != 0:
        if os.getsid(0) != os.getpid():
            os.setsid()  # (a new session is a new autogroup)
        autogroup.write_text(str(nice))
    return {"nice": os.getpriority(os.PRIO_PROCESS, 0),
            "autogroup": autogroup.read_text().strip() if autogroup.exists() else None}


def command(nice: int) -> list[str]:
    """The prefix that starts a command this way (``Stack(wrap=...)``)."""
    return [sys.executable, str(Path(__file__).resolve()), str(nice)]


if __name__ == "__main__":
    prioritise(int(sys.argv[1]))
    os.execvp(sys.argv[2], sys.argv[2:])
