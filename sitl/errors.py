"""SitlError: the base of every error the simulator raises on purpose (a firmware that will not start,
a link it cannot open), each one sentence for the operator. The operator's CLI (`triswarm sitl up`, `triswarm demo`) reports
it as one line and exit status 2; anything else is a bug and shows its traceback. Here, in a module that
imports nothing, so that any module can name it."""

from __future__ import annotations


class SitlError(Exception):
    """Something asked of the simulator that it cannot do (one sentence)."""


class LinkOpenError(SitlError, OSError):
    """A vehicle's UDP link cannot be opened (the port taken, the address not this host's): one sentence."""
