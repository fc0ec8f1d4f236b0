"""What a companion keeps across a restart: its plan and where the mission is, written atomically;
and the signing key file it reads (as the ground station does).

A state folder that cannot be written (read-only, full, a file's path taken by a folder) costs what
it keeps, never the flight: ``StateStore`` counts the failed writes, says so once (``warn``) when
writing starts to fail and once when it works again, and the companion flies on; a restart would
then not find the newest mission.

A write waits for the disk (fsync), which on a busy machine or an SD card takes from milliseconds
to seconds: longer than a flight controller waits for its next command. So a companion's store
writes in a thread of its own (``write_in_background``): the control loop hands it the newest data
of each file and goes on; the files are written in the order they were handed over, and a file
handed over again before it was written is written once, with the newest data."""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path


def read_signing_key(path: Path) -> bytes:
    """The signing key in the file ``path`` (32 bytes, or 64 hexadecimal digits: see
    ``protocol.mavlink.signing_key``). ValueError (one sentence, naming the file) if it cannot be
    read or is not a key."""
    from triswarm.protocol.mavlink import signing_key

    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the signing key ({exc.strerror})") from None
    return signing_key(data, str(path))


def write_json_atomically(path: Path, data: dict) -> None:
    """``data`` as indented JSON, by ``write_atomically``."""
    write_atomically(path, (json.dumps(data, indent=2) + "\n").encode("utf-8"))


def write_atomically(path: Path, data: bytes) -> None:
    """Write, fsync, rename (and fsync the folder): a reader sees the old file or the new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with tmp.open("wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink(missing_ok=True)  # (a full folder keeps no half-written file)
        except OSError:
            pass  # (the folder is not one: nothing was written)
        raise
    fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@dataclass
class Mission:
    plan_spec: dict
    plan_id: int
    agent: int
    start_unix_s: float | None = None
    """When the plan (its take-off) starts, common to the swarm; None: not scheduled."""
    phase: str = "idle"
    """idle, scheduled, flying, landing (the companion's own) or done (the flight controller took
    the vehicle back, or the landing is over)."""
    leader_moves: list = field(default_factory=list)
    """The operator's leader commands in force, in order (see companion.leader_with_moves)."""
    formation_shift_s: float = 0.0
    """Plan time at which this plan's formation starts (its t = 0): not 0 for a plan put in force
    during a flight, while the swarm's plan time runs on from the first start."""
    next_plan: dict | None = None
    """A plan to put in force during the flight: {"spec", "plan_id", "at_unix_s"}."""


class StateStore:
    """JSON files in the state folder (the mission; the signing streams); None folder: keep nothing.
    ``warn(text)`` hears when writing starts to fail and when it works again (once each)."""

    def __init__(self, folder: Path | None, warn=None) -> None:
        self.path = None if folder is None else Path(folder) / "mission.json"
        self.signing_path = None if folder is None else Path(folder) / "signing.json"
        self.problem: str | None = None
        self.warn = warn or (lambda text: None)
        self.failed_writes = 0
        self._failing: set[Path] = set()
        self._pending: dict[Path, dict | None] = {}
        """In the background: the files to write (None: to remove), oldest first, newest data each."""
        self._wake = threading.Condition()
        self._writer: threading.Thread | None = None
        self._closing = False

    def write_in_background(self, notify: Callable[[str], None]) -> None:
        """From now on, write in a thread of this store's own; what ``warn`` would hear goes to
        ``notify`` from that thread (hand it to the caller's own thread). ``close`` ends it."""
        if self._writer is None and self.path is not None:
            self.warn = notify
            self._writer = threading.Thread(target=self._write_pending, name="state-writer", daemon=True)
            self._writer.start()

    def close(self, timeout_s: float = 5.0) -> bool:
        """Write what is pending and end the writing thread; False if the disk did not let it
        finish within ``timeout_s``."""
        if self._writer is None:
            return True
        with self._wake:
            self._closing = True
            self._wake.notify()
        self._writer.join(timeout_s)
        done = not self._writer.is_alive()
        if done:
            self._writer, self._closing = None, False
        return done

    def _put(self, path: Path, data: dict | None) -> bool:
        """``data`` to ``path`` (None: remove it), now or, in the background, handed to the writing
        thread: then False only if that file's last write failed (said once, as a failed write)."""
        if self._writer is None:
            return self._remove() if data is None else self._write(path, data)
        with self._wake:
            self._pending.pop(path, None)  # (handed over again: written at its new place in the order)
            self._pending[path] = data
            self._wake.notify()
        return path not in self._failing

    def _write_pending(self) -> None:
        while True:
            with self._wake:
                while not self._pending and not self._closing:
                    self._wake.wait()
                if not self._pending:
                    return
                path = next(iter(self._pending))
                data = self._pending.pop(path)
            try:
                self._remove() if data is None else self._write(path, data)
            except Exception as exc:  # (a bug, not the disk: said as one, and the writer goes on)
                self.failed_writes += 1
                self.warn(f"bug: writing {path} raised {exc!r}")

    def _write(self, path: Path, data: dict) -> bool:
        """Write ``data`` to ``path`` atomically; False (and said once) if the folder will not take it."""
        try:
            write_json_atomically(path, data)
        except OSError as exc:
            self.failed_writes += 1
            if path not in self._failing:
                self._failing.add(path)
                self.warn(f"cannot write {path} ({exc.strerror or exc}): flying on without it; a restart "
                          f"would not find the newest state")
            return False
        if path in self._failing:
            self._failing.discard(path)
            self.warn(f"{path} written again ({self.failed_writes} write(s) failed)")
        return True

    def load(self) -> Mission | None:
        """The saved mission, or None (and ``problem`` says why if the file was unusable)."""
        if self.path is None or not self.path.exists():
            return None
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            return Mission(**data)
        except (OSError, ValueError, TypeError) as exc:
            self.problem = f"{self.path}: unusable saved mission ({exc.__class__.__name__}), starting without it"
            return None

    def clear(self) -> None:
        if self.path is not None:
            self._put(self.path, None)

    def _remove(self) -> bool:
        try:
            self.path.unlink(missing_ok=True)
        except OSError as exc:  # (read-only; a folder in its place)
            self.failed_writes += 1
            self.warn(f"cannot remove {self.path} ({exc.strerror or exc})")
            return False
        return True

    def save(self, mission: Mission) -> bool:
        return self.path is None or self._put(self.path, asdict(mission))

    def load_signing_streams(self) -> dict:
        """The signing streams kept by ``save_signing_streams`` ({} if none, or unusable: ``problem``)."""
        if self.signing_path is None or not self.signing_path.exists():
            return {}
        try:
            data = json.loads(self.signing_path.read_text(encoding="utf-8"))
            if not isinstance(data, dict):
                raise ValueError("not a JSON object")
            return data
        except (OSError, ValueError) as exc:
            self.problem = f"{self.signing_path}: unusable signing streams ({exc.__class__.__name__}), starting without them"
            return {}

    def save_signing_streams(self, streams: dict) -> bool:
        return self.signing_path is None or self._put(self.signing_path, dict(streams))
