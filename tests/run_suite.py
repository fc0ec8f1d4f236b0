"""`make test`: every test, in the least wall time that keeps the real-time ones honest.

Two pytest runs:
- the tests on simulated time or with no clock at all, on two workers (pytest-xdist);
- the few that judge something on the wall clock (marked ``realtime``), in one process.

As root, the real-time run goes beside the other, ahead of it: niceness -10 in a session of its own
(tests/priority.py), so the busy workers slow themselves and not the flights. Without root nothing
can run ahead of the workers, so the real-time run waits for them and has the machine to itself.
Its output follows the other's. The exit status is the worse of the two.

    python tests/run_suite.py [pytest arguments for both runs...]
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

PYTEST = [sys.executable, "-m", "pytest"]


def main(args: list[str]) -> int:
    simulated = PYTEST + ["-n", "2", "-m", "not realtime", *args]
    realtime = PYTEST + ["-m", "realtime", "-p", "no:cacheprovider", *args]
    if os.geteuid() != 0:
        first = subprocess.call(simulated, cwd=ROOT)
        return max(first, subprocess.call(realtime, cwd=ROOT))
    with tempfile.TemporaryFile("w+") as log:
        beside = subprocess.Popen(command(-10) + realtime, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        try:
            first = subprocess.call(simulated, cwd=ROOT)
            second = beside.wait()
        finally:
            if beside.poll() is None:  # (interrupted: leave nothing behind)
                beside.terminate()
                beside.wait()
        log.seek(0)
        print("\n--- the real-time tests, run beside the others at niceness -10 ---", flush=True)
        sys.stdout.write(log.read())
        sys.stdout.flush()
    return max(first, second)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
