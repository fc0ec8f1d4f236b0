"""The tests' one way to wait for something: poll a condition, bounded in wall time."""

from __future__ import annotations

import asyncio
import time


def _turns(cond, timeout_s: float, what: str | None, step):
    """Yields while ``cond()`` does not hold yet and time is left; returns whether it held."""
    deadline = time.monotonic() + timeout_s
    while True:
        if step is not None:
            step()
        if cond():
            return True
        if time.monotonic() >= deadline:
            assert what is None, f"{what} within {timeout_s:g} s"
            return False
        yield


def poll(cond, timeout_s: float, what: str | None = None, every_s: float = 0.05, step=None) -> bool:
    """Call ``step()`` (if given) and check ``cond()`` every ``every_s`` until it holds, for at most
    ``timeout_s`` of wall time. With ``what``: AssertionError "<what> within <timeout_s> s" if it
    never held; without: whether it held."""
    turns = _turns(cond, timeout_s, what, step)
    try:
        while True:
            next(turns)
            time.sleep(every_s)
    except StopIteration as done:
        return done.value


async def poll_async(cond, timeout_s: float, what: str | None = None, every_s: float = 0.01, step=None) -> bool:
    """``poll`` inside an event loop: it sleeps with ``asyncio.sleep``, so the loop runs meanwhile."""
    turns = _turns(cond, timeout_s, what, step)
    try:
        while True:
            next(turns)
            await asyncio.sleep(every_s)
    except StopIteration as done:
        return done.value
