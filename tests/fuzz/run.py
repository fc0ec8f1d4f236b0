"""``make fuzz``: every face of the companion with at least 100,000 inputs each; prints, per face,
the inputs, their rate and the companion's counters against what they should be. Exits 1 if a face
found a problem (a crash, a counter off, a companion that stopped answering), keeping the
companions' logs.

    python -m tests.fuzz.run [--count 100000] [--faces gcs,gcs-signed,fc,missions,zenoh,plan-files,sitl-gcs,...]

The faces ``sitl-gcs``, ``sitl-companion`` and ``routed`` get valid messages with hostile values
(``stack_faces.py``), and fly afterwards.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

from .mavlink_faces import fuzz_fc, fuzz_gcs
from .missions import fuzz_missions
from .plan_files import fuzz_plan_files
from .stack_faces import FACES as STACK_FACES, fuzz_stack
from .zenoh_face import fuzz_zenoh

FACES = {
    "gcs": lambda n, d: fuzz_gcs(n, d),
    "gcs-signed": lambda n, d: fuzz_gcs(n, d, signed=True),
    "fc": lambda n, d: fuzz_fc(n, d),
    "missions": lambda n, d: fuzz_missions(n, d),
    "zenoh": lambda n, d: fuzz_zenoh(n, d),
    "plan-files": lambda n, d: fuzz_plan_files(n),
    **{face: (lambda n, d, face=face: fuzz_stack(face, n, d)) for face in STACK_FACES},
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=100_000, help="inputs per face")
    ap.add_argument("--faces", default=",".join(FACES), help="which faces, comma-separated")
    args = ap.parse_args(argv)
    workdir = Path(tempfile.mkdtemp(prefix="triswarm-fuzz-"))
    failed = []
    for face in args.faces.split(","):
        report = FACES[face](args.count, workdir / face)
        print(report.text(), flush=True)
        if report.problems or report.inputs < args.count:
            failed.append(face)
    if failed:
        print(f"problems in: {', '.join(failed)} (the companions' logs are in {workdir})")
        return 1
    shutil.rmtree(workdir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
