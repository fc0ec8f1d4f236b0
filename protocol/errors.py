"""The errors protocol/ raises for what a user supplied: a plan file, a parameter, a formation, a graph,
bytes from the wire. Each says in one sentence what is wrong; the edges report them as the user's
mistake, not as a bug.

ProtocolError is their base: every error class of protocol/ derives from it, and the edges catch it
once. Here, in a module that imports nothing, so that an edge can name them without importing the math."""

from __future__ import annotations


class ProtocolError(ValueError):
    """Something supplied to protocol/ that it cannot use (one sentence)."""


class ParameterError(ProtocolError):
    """A physical or design parameter a user supplied is not usable (one sentence)."""


class GraphError(ProtocolError):
    """A topology that the protocol cannot use (one sentence)."""


class FormationError(ProtocolError):
    """A formation that fails the feasibility condition (76) (one sentence)."""


class PlanError(ProtocolError):
    """A plan that cannot be flown, with the reason in one sentence."""
