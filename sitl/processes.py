"""Child processes that never outlive their launcher (the stack's SITL and companions, a SITL's
firmwares):

- each starts in a process group of its own, which its launcher signals to stop it (its own
  children with it), and which a terminal's Ctrl-C does not reach (the launcher stops it, in turn);
- each is told to end (SIGTERM) when the thread that started it ends, whatever ends it: a
  launcher killed outright (SIGKILL, pytest-timeout, a crash) leaves nothing running (Linux's
  PR_SET_PDEATHSIG; elsewhere only the launcher's own stop). Start children from a thread that
  lives as long as they should: the main thread, or an executor's, which lives until shut down.

A group, not a session: the children stay in their launcher's session, so a scheduler's autogroup
(and a niceness given to that session) covers them too.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import subprocess

_PR_SET_PDEATHSIG = 1
_prctl = getattr(ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True), "prctl", None)


def _dies_with(parent_pid: int):
    def in_child() -> None:
        if _prctl is not None:
            _prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM))
            if os.getppid() != parent_pid:  # (the launcher ended before the request took effect)
                os.kill(os.getpid(), signal.SIGTERM)
    return in_child


def spawn(cmd: list[str], new_session: bool = False, **popen_args) -> subprocess.Popen:
    """``subprocess.Popen(cmd, **popen_args)``, in a process group of its own (with ``new_session``,
    in a session of its own, which is a group of its own too: for a wrapper that sets the
    session's priority), ending with its launcher."""
    group = {"start_new_session": True} if new_session else {"process_group": 0}
    return subprocess.Popen(cmd, preexec_fn=_dies_with(os.getpid()), **group, **popen_args)


def signal_group(proc: subprocess.Popen, sig: int) -> None:
    """``sig`` to the process group ``proc`` leads (``spawn``), or to ``proc`` alone if it leads none;
    nothing if it is gone."""
    try:
        if os.getpgid(proc.pid) == proc.pid:
            os.killpg(proc.pid, sig)
        else:
            proc.send_signal(sig)
    except ProcessLookupError:
        pass
