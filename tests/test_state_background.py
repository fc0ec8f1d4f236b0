"""A companion's state is written in a thread of its own: the control loop hands the newest data
over and goes on, however long the disk takes to say it has it (fsync: milliseconds on a quiet
machine, seconds on a busy one or an SD card, longer than a flight controller waits for its next
command). Here the disk's wait is held open by the test (``os.fsync`` of the state module blocks
until released), so what is checked is the order of events, not a duration."""

import threading

import pytest

from triswarm.companion import state
from triswarm.companion.state import Mission, StateStore

WAIT_S = 10.0  # (a bound on each wait, never reached when it works)


def mission(phase: str) -> Mission:
    return Mission({"drones": 1}, 7, 1, 100.0, phase)


@pytest.fixture
def held_disk(monkeypatch):
    """os.fsync in the store's module waits until ``release`` is set; ``entered`` counts its calls."""
    release, entered = threading.Event(), threading.Semaphore(0)
    real = state.os.fsync

    def fsync(fd):
        entered.release()
        assert release.wait(WAIT_S), "the test never released the disk"
        real(fd)
    monkeypatch.setattr(state.os, "fsync", fsync)
    yield release, entered
    release.set()


def test_a_save_returns_while_the_disk_waits_and_the_newest_state_is_written_once(tmp_path, held_disk):
    release, entered = held_disk
    said = []
    store = StateStore(tmp_path, said.append)
    store.write_in_background(said.append)
    assert store.save(mission("scheduled")) is True
    assert entered.acquire(timeout=WAIT_S)  # the writer is inside the disk's wait with "scheduled"...
    for phase in ("flying", "landing", "done"):  # ...and the loop's saves return all the same
        assert store.save(mission(phase)) is True
    assert not (tmp_path / "mission.json").exists()
    release.set()
    assert store.close(WAIT_S)
    assert store.load().phase == "done"
    assert store.failed_writes == 0 and said == []
    # "scheduled" (file, folder) and then only the newest, "done" (file, folder): four waits in all
    assert [entered.acquire(timeout=0) for _ in range(4)] == [True, True, True, False]


def test_a_clear_after_a_pending_save_removes_the_file(tmp_path, held_disk):
    release, entered = held_disk
    store = StateStore(tmp_path)
    store.write_in_background(lambda text: None)
    store.save(mission("flying"))
    assert entered.acquire(timeout=WAIT_S)
    store.save(mission("done"))
    store.clear()  # (after the saves: the file goes, and the pending "done" is not written after it)
    release.set()
    assert store.close(WAIT_S)
    assert not (tmp_path / "mission.json").exists() and store.load() is None


def test_a_failing_write_in_the_background_is_said_once_and_the_next_save_knows(tmp_path):
    said = []
    store = StateStore(tmp_path, lambda text: None)
    store.write_in_background(said.append)
    (tmp_path / "mission.json").mkdir()
    assert store.save(mission("flying")) is True  # (handed over: not known yet)
    assert store.close(WAIT_S)
    assert store.failed_writes == 1 and len(said) == 1 and "cannot write" in said[0], said
    store.write_in_background(said.append)
    assert store.save(mission("landing")) is False  # its last write failed
    (tmp_path / "mission.json").rmdir()
    assert store.close(WAIT_S)
    assert store.load().phase == "landing" and "written again" in said[-1], said
