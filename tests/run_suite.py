"""`make test` and `make test-slow`: the tests, in the least wall time that keeps the real-time ones
honest.

Two tiers: `make test` runs every test not marked ``slow``, `make test-slow` the ``slow`` ones (a whole
scenario flown for tens of seconds: the whole stack's long flights, the firmwares' formations,
swarms in-process); CI runs both. Each tier is two pytest runs:
- the tests on simulated time or with no clock at all, on two workers (pytest-xdist; a worker
  that runs out of tests takes some of the other's, so neither idles while a long one is queued).
  (Measured: a third worker on two cores took a minute off, but starved whole-stack tests for over
  a second now and then, longer than Zenoh's lease, which is on the wall clock: agents lost each
  other's liveliness and held, and a verdict failed; not seen with two workers);
- the few that judge something on the wall clock (marked ``realtime``), in one process.

As root, the real-time run goes beside the other, ahead of it: niceness -10 in a session of its own
(tests/priority.py), and the workers behind everything, at niceness 19 in a session of their own,
so the busy workers slow themselves and not the flights. (Measured: beside workers at niceness 0,
the processes they start by the hundred stalled the real-time flights for 60-300 ms now and then,
and two runs of four failed; pure CPU load at niceness 0 never did. The simulated-time tests do not
mind: their verdicts do not depend on the machine's speed.) Without root nothing can run ahead of
the workers, so the real-time run waits for them and has the machine to itself. Its output follows
the other's. The exit status is the worse of the two.

    python tests/run_suite.py [--quick | --slow | --all] [pytest arguments for both runs...]
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.priority import command  # noqa: E402
from tests.warm_up import PARTS  # noqa: E402

PYTEST = [sys.executable, "-m", "pytest"]


def warm_up() -> None:
    """Compile the numba kernels before both runs, one part per process, all at once (tests/warm_up.py):
    each run's start then loads them from numba's cache. (Else, on a fresh clone, both runs compiled
    all of them at the same time, 10 s of both cores.) A failure shows its traceback here, and again
    where the runs start."""
    parts = {part: subprocess.Popen([sys.executable, "-m", "tests.warm_up", part], cwd=ROOT) for part in PARTS}
    for part, p in parts.items():
        if p.wait() != 0:
            print(f"run_suite: compiling the kernels of the {part} failed (exit status {p.returncode})", flush=True)


TIERS = {"--quick": "not slow", "--slow": "slow", "--all": None}  # make test, make test-slow, both at once
NO_TESTS = 5  # pytest's exit status when the selection is empty: no failure


def main(args: list[str]) -> int:
    tier = TIERS[args.pop(0)] if args and args[0] in TIERS else TIERS["--quick"]
    within = "" if tier is None else f" and {tier}"
    warm_up()
    simulated = PYTEST + ["-n", "2", "--dist", "worksteal", "-m", "not realtime" + within, "--durations=15", *args]
    realtime = PYTEST + ["-m", "realtime" + within, "-p", "no:cacheprovider", "--durations=25", *args]
    if os.geteuid() != 0:
        first = _status(subprocess.call(simulated, cwd=ROOT))
        return max(first, _status(subprocess.call(realtime, cwd=ROOT)))
    with tempfile.TemporaryFile("w+") as log:
        beside = subprocess.Popen(command(-10) + realtime, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        behind = None
        try:
            behind = subprocess.Popen(command(19) + simulated, cwd=ROOT)
            first = _status(behind.wait())
            second = _status(beside.wait())
        finally:  # (interrupted: leave nothing behind; both run in sessions of their own, out of Ctrl-C's reach)
            for p in (beside, behind):
                if p is not None and p.poll() is None:
                    p.terminate()
                    p.wait()
        log.seek(0)
        print("\n--- the real-time tests, run beside the others at niceness -10 ---", flush=True)
        sys.stdout.write(log.read())
        sys.stdout.flush()
    return max(first, second)


def _status(code: int) -> int:
    return 0 if code == NO_TESTS else code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
