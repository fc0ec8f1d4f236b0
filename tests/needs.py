"""Tests that need something of the machine (root, a Debian package): without it, a skip that says
what is missing, except under CI (``CI`` set, as CI services do), where a missing tool is a broken
set-up and fails the test with the tool's name (``make test`` installs what it can when run as root)."""

from __future__ import annotations

import os
from typing import NoReturn

import pytest


def under_ci() -> bool:
    return os.environ.get("CI", "").lower() not in ("", "0", "false")


def missing(problem: str) -> NoReturn:
    """Stop the test: ``problem`` names what is missing (e.g. "systemd-analyze is not installed")."""
    if under_ci():
        pytest.fail(f"CI: {problem}")
    pytest.skip(problem)
