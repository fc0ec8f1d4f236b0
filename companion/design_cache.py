"""The design's solved Riccati equations kept on disk across runs (``protocol.design.keep_solutions``),
as numba keeps the compiled code: python-control, which solves them, takes about 0.7 s of CPU to
import (it brings scipy.signal and matplotlib), the design itself 10 ms. Every companion, SITL and
``plan check`` would pay that at its start, and a restarted companion would keep its vehicle in the
failsafe that much longer.

One file per equation, named by a digest of its matrices, in a folder named by the versions of
python-control and SciPy that solved it: beside protocol/'s compiled code (``protocol/__pycache__``)
where that can be written, else in ``$XDG_CACHE_HOME/triswarm`` (``~/.cache/triswarm``). Files are
written whole (a temporary file, then a rename): processes that start together may each solve and
write, and a reader sees a whole file or none. A folder that cannot be written keeps nothing, and
the design is solved each time; nothing else changes."""

from __future__ import annotations

import os
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import triswarm.protocol
from triswarm.protocol import design


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


def keep_on_disk(path: Path | None = None) -> Path | None:
    """Keep the design's solutions in ``path`` (default: ``folder()``); the folder used, or None."""
    path = path if path is not None else folder()
    if path is None:
        return None

    def load(key: str) -> bytes | None:
        try:
            return (path / key).read_bytes()
        except OSError:
            return None

    def save(key: str, blob: bytes) -> None:
        tmp = path / f".{key}.{os.getpid()}.tmp"
        try:
            tmp.write_bytes(blob)
            os.replace(tmp, path / key)
        except OSError:
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass

    design.keep_solutions(load, save)
    return path
