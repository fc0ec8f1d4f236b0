"""Where the design keeps its solved Riccati equations across runs: the edges say how
(``keep_solutions``: ``companion/design_cache.py`` keeps them on disk), and ``design`` asks (``kept``).
A module of its own, so that saying it imports none of the design's numerics."""

from __future__ import annotations

from collections.abc import Callable

Load = Callable[[str], bytes | None]
Save = Callable[[str, bytes], None]

_kept: tuple[Load, Save] | None = None


def keep_solutions(load: Load, save: Save) -> None:
    """Keep the design's solved Riccati equations across runs, as ``jit.cache_on_disk`` keeps the
    compiled code: ``save(key, blob)`` stores a solution, ``load(key)`` gives it back (None when it
    has none). For the edges, which read and write the files. A design whose equations are all kept
    does not import python-control (about 0.7 s: it brings scipy.signal and matplotlib) for its 10 ms
    of work. A blob that is not whole (its digest) is solved again."""
    global _kept
    _kept = (load, save)


def kept() -> tuple[Load, Save] | None:
    """The ``(load, save)`` pair given to ``keep_solutions``, or None: nothing is kept."""
    return _kept
