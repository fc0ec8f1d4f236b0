"""numba's ``njit`` for the compiled code of protocol/ (``dynamics``, ``kernels``, ``wind``), with
numba's on-disk cache switched on by the edges.

``numba.njit(cache=True)`` finds its cache folder when a function is decorated, that is when its
module is imported, and makes it and writes a file there to see that it can: an import that writes
files (beside the source, else in ``$NUMBA_CACHE_DIR`` or the home folder's cache), and fails where
none of them is writable. Here the functions are decorated without the cache, and a program that
wants compiled code kept across runs (the companion, the SITL, the ground station's CLI, the tests:
each package but protocol/ does it on import) calls ``cache_on_disk()`` before anything is compiled;
functions decorated after that call are cached too.
"""

from __future__ import annotations

from collections.abc import Callable

_compiled: list = []  # every dispatcher ``njit`` made
_on_disk = False


def njit(**options) -> Callable:
    """``numba.njit(**options)`` (not ``cache``): kept in numba's on-disk cache once ``cache_on_disk`` is called."""
    import numba

    def compile_(function: Callable) -> Callable:
        dispatcher = numba.njit(**options)(function)
        _compiled.append(dispatcher)
        if _on_disk:
            dispatcher.enable_caching()
        return dispatcher

    return compile_


def cache_on_disk() -> None:
    """Keep protocol/'s compiled code in numba's cache, as ``numba.njit(cache=True)`` does: the
    functions decorated so far and those decorated later. For the edges only (numba writes files);
    call it before the first call of a compiled function, or what that compiles is not kept."""
    global _on_disk
    if not _on_disk:
        _on_disk = True
        for dispatcher in _compiled:
            dispatcher.enable_caching()


def caching() -> bool:
    """Whether an edge has called ``cache_on_disk``."""
    return _on_disk
