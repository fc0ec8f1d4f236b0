"""The errors protocol/ raises for what a user supplied: a plan file, a parameter, a formation, a graph.
Each says in one sentence what is wrong; the edges report them as the user's mistake, not as a bug.

Here, in a module that imports nothing, so that an edge can name them without importing the math."""

from __future__ import annotations


class ParameterError(ValueError):
    """A physical or design parameter a user supplied is not usable (one sentence)."""


class GraphError(ValueError):
    """A topology that the protocol cannot use (one sentence)."""


class FormationError(ValueError):
    """A formation that fails the feasibility condition (76) (one sentence)."""


class PlanError(ValueError):
    """A plan that cannot be flown, with the reason in one sentence."""
