"""The design's solved Riccati equations kept on disk (companion/design_cache.py): a design that finds
them kept gives the same bits as one that solves them, without importing python-control; a damaged
file is solved again; other weights are other equations; a folder that cannot be written keeps
nothing and changes nothing. Each design runs in a fresh interpreter, as a companion starts."""

import json
import subprocess
import sys
from pathlib import Path

from .conftest import PAPER_PLAN_FILE, paper_plan_variant

DESIGN = """
import hashlib, json, sys, tomllib
from pathlib import Path
from triswarm.companion.design_cache import keep_on_disk
keep_on_disk(Path(sys.argv[1]))
from triswarm.protocol.plan import plan_from_dict
d = plan_from_dict(tomllib.loads(Path(sys.argv[2]).read_text())).design
arrays = (d.K, d.P, d.F, d.P_bar, d.F_aug, *d.F_measured)
print(json.dumps({"bits": hashlib.sha256(b"".join(a.tobytes() for a in arrays)).hexdigest(),
                  "control": "control" in sys.modules}))
"""


def design(folder: Path, plan: Path = PAPER_PLAN_FILE) -> dict:
    """The design's arrays (a digest of their bits), and whether it imported python-control."""
    r = subprocess.run([sys.executable, "-c", DESIGN, str(folder), str(plan)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout)


def test_kept_solutions_are_the_same_bits_without_python_control(tmp_path):
    kept = tmp_path / "kept"
    kept.mkdir()
    first = design(kept)
    assert first["control"] is True
    assert len(list(kept.iterdir())) == 6  # K (89), F (98), and the observers' gains it runs: alone, with rates,
    # with the acceleration, with both
    second = design(kept)
    assert second == {"bits": first["bits"], "control": False}
    (tmp_path / "a-file").write_text("")
    assert design(tmp_path / "a-file") == first  # (a folder that cannot be written: solved, the same bits)


def test_a_damaged_solution_is_solved_again(tmp_path):
    first = design(tmp_path)
    for f in tmp_path.iterdir():
        blob = bytearray(f.read_bytes())
        blob[-1] ^= 1  # (the last bit of the Riccati solution)
        f.write_bytes(bytes(blob))
    assert design(tmp_path) == first  # (solved again: python-control imported)
    assert design(tmp_path) == {"bits": first["bits"], "control": False}  # (and written whole again)


def test_other_weights_are_other_equations(tmp_path):
    paper = design(tmp_path)
    other = paper_plan_variant(tmp_path, [("Q_diag = [1.0, 1.0, 1.0,", "Q_diag = [2.0, 1.0, 1.0,")])
    heavier = design(tmp_path, other)
    assert heavier["control"] is True and heavier["bits"] != paper["bits"]
    assert design(tmp_path / "nothing-kept-here" / "x", other)["bits"] == heavier["bits"]
