"""Which ``Autopilot`` flies a flight controller: the one its HEARTBEAT names (autopilot and type
fields, as skybrush-server's registry does), or the one configuration forces (``--fc-profile``)."""

from __future__ import annotations

from .ardupilot import ArduCopter
from .base import Autopilot, AutopilotError
from .px4 import Px4
from .triswarm import TriswarmSitl

KINDS: dict[str, type[Autopilot]] = {k.name: k for k in (TriswarmSitl, ArduCopter, Px4)}
PROFILES = ("auto", *KINDS)
"""What ``--fc-profile`` takes: auto (from the HEARTBEAT) or a kind's name."""


def pick(profile: str, autopilot: int, vehicle_type: int, home: tuple[float, float, float] | None = None) -> Autopilot:
    """The kind ``profile`` names, or with "auto" the one whose HEARTBEAT fields these are
    (AutopilotError: none knows them)."""
    if profile != "auto":
        kind = KINDS.get(profile)
        if kind is None:
            raise AutopilotError(f"--fc-profile must be one of {', '.join(PROFILES)}, got {profile!r}")
    else:
        kind = next((k for k in KINDS.values() if k.matches(autopilot, vehicle_type)), None)
        if kind is None:
            raise AutopilotError(f"the flight controller's HEARTBEAT says autopilot {autopilot}, which the companion "
                                 f"does not know (--fc-profile forces one of {', '.join(KINDS)})")
    return kind(home) if kind in (ArduCopter, Px4) else kind()
