"""The design's solved Riccati equations kept on disk across runs (``protocol.solutions.keep_solutions``),
as numba keeps the compiled code: python-control, which solves them, takes about 0.7 s of CPU to
import (it brings scipy.signal and matplotlib), the design itself 10 ms. Every companion, SITL and
``plan check`` would pay that at its start, and a restarted companion would keep its vehicle in the
failsafe that much longer.

One file per equation, named by a digest of its matrices, in a folder named by the versions of
python-control and SciPy that solved it: beside protocol/'s compiled code (``protocol/__pycache__``)
where that can be written, else in ``$XDG_CACHE_HOME/triswarm`` (``~/.cache/triswarm``). Files are
written whole (``state.write_atomically``: a temporary file, fsync, a rename): processes that start
together may each solve and write, and a reader sees a whole file or none. A folder that cannot be written keeps nothing, and
the design is solved each time; nothing else changes."""

from __future__ import annotations

import functools
import os
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import triswarm.protocol
from triswarm.protocol.solutions import keep_solutions

from .state import write_atomically


def _versions() -> str:
    names = []
    for package in ("control", "scipy"):
        try:
            names.append(f"{package}-{version(package)}")
        except PackageNotFoundError:
            names.append(f"{package}-unknown")
    return "riccati-" + "-".join(names)


def folder() -> Path | None:
    """Where the solutions are kept: the first candidate that can be written, or None."""
    user = Path(os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"))
    for base in (Path(triswarm.protocol.__file__).parent / "__pycache__", user / "triswarm"):
        if not base.is_absolute():  # (no home folder: "~" left as it is)
            continue
        path = base / _versions()
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(path, os.W_OK | os.X_OK):
            return path
    return None


def keep_on_disk(path: Path | None = None) -> None:
    """Keep the design's solutions in ``path`` (default: ``folder()``, looked for at the first
    design: a command that designs nothing makes no folder)."""
    where = functools.cache(lambda: path if path is not None else folder())

    def load(key: str) -> bytes | None:
        try:
            return None if where() is None else (where() / key).read_bytes()
        except OSError:
            return None

    def save(key: str, blob: bytes) -> None:
        try:
            if where() is not None:
                write_atomically(where() / key, blob)
        except OSError:
            pass  # (kept nowhere: solved again next time)

    keep_solutions(load, save)
