"""A fault survived: the companion's state folder will not take a write. ``StateStore`` says so once
(and once again when writing works again), leaves no half-written file, never raises, and keeps the
last good file. Two ways to break the folder, since root writes through any mode bits: a full
filesystem (a 64 KiB tmpfs, filled, mounted in a mount namespace this test creates with
``unshare -m``: the real ENOSPC), and the file's path taken by a folder (EISDIR on the rename).
The whole-stack flight with a broken folder is ``test_fault_state_stack.py``."""

import json
import os
import shutil
import subprocess
import sys
import textwrap

from triswarm.companion.state import Mission, StateStore

from .needs import missing


def mission(phase: str) -> Mission:
    return Mission({"drones": 1}, 7, 1, 100.0, phase)


def test_a_folder_in_the_files_place_is_said_once_and_the_flight_state_kept_in_memory(tmp_path):
    said = []
    store = StateStore(tmp_path, said.append)
    (tmp_path / "mission.json").mkdir()
    for phase in ("scheduled", "flying", "flying", "done"):
        assert store.save(mission(phase)) is False
    assert store.failed_writes == 4
    assert len(said) == 1 and "cannot write" in said[0] and "mission.json" in said[0], said
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mission.json"]  # no temporary file left
    (tmp_path / "mission.json").rmdir()
    assert store.save(mission("done")) is True
    assert len(said) == 2 and "written again (4 write(s) failed)" in said[1], said
    assert store.load().phase == "done"
    # the signing streams likewise, on their own
    (tmp_path / "signing.json").mkdir()
    assert store.save_signing_streams({"1,190,1": 5}) is False and store.save_signing_streams({}) is False
    assert len(said) == 3 and "signing.json" in said[2]


FILL = textwrap.dedent("""
    import json, os, sys
    from pathlib import Path
    from triswarm.companion.state import Mission, StateStore
    folder = Path(sys.argv[1])
    store = StateStore(folder, lambda text: print("SAID", text, flush=True))
    assert store.save(Mission({"drones": 1}, 7, 1, 100.0, "scheduled"))
    fd = os.open(folder / "filler", os.O_WRONLY | os.O_CREAT)
    try:  # fill the filesystem to the last block
        while os.write(fd, b"x" * 512):
            pass
    except OSError:
        pass
    os.close(fd)
    results = [store.save(Mission({"drones": 1, "big": "y" * 8192}, 7, 1, 100.0, "flying")) for _ in range(5)]
    print("RESULTS", json.dumps({"results": results, "failed": store.failed_writes,
                                 "kept": json.loads((folder / "mission.json").read_text())["phase"],
                                 "files": sorted(p.name for p in folder.iterdir())}), flush=True)
""")


def test_a_full_state_folder_is_said_once_and_the_last_good_file_kept(tmp_path):
    if os.geteuid() != 0 or shutil.which("unshare") is None or shutil.which("mount") is None:
        missing("a tmpfs in a mount namespace of its own needs root, unshare and mount (util-linux)")
    folder = tmp_path / "state"
    folder.mkdir()
    script = tmp_path / "fill.py"
    script.write_text(FILL)
    cmd = f"mount -t tmpfs -o size=64k tmpfs {folder} && exec {sys.executable} {script} {folder}"
    out = subprocess.run(["unshare", "-m", "--propagation", "private", "sh", "-c", cmd], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr[-3000:]
    said = [line for line in out.stdout.splitlines() if line.startswith("SAID")]
    result = json.loads(next(line for line in out.stdout.splitlines() if line.startswith("RESULTS")).split(" ", 1)[1])
    assert result["results"] == [False] * 5 and result["failed"] == 5, result
    assert len(said) == 1 and "No space left on device" in said[0], said
    assert result["kept"] == "scheduled"  # the last good file, whole
    assert result["files"] == ["filler", "mission.json"], result  # no half-written temporary file
    assert not list(folder.iterdir())  # (the tmpfs was the namespace's: this side never saw it)
