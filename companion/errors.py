"""CompanionError: the base of every error the companion raises on purpose (its configuration, its
flight controller, its start-up), each one sentence for the operator. triswarm-companion catches it,
with protocol/'s ProtocolError, once: one line and exit status 2; anything else is a bug and shows
its traceback. Here, in a module that imports nothing, so that any module can name it."""

from __future__ import annotations


class CompanionError(Exception):
    """Something the operator asked of the companion that it cannot do (one sentence)."""
