"""Every option of ``triswarm-companion``, described once: its name, kind, default, help, key in the
per-drone configuration file and the check of its value. The command line (``cli.py``), the
configuration file (``config.py``) and the options an agent runs with (``CompanionOptions``) are all
made from ``OPTIONS``.

Names: the dataclass field and the file key are the option's name (``rate_hz``; the Zenoh options'
keys are in the file's ``[zenoh]`` table: ``zenoh_listen`` is ``listen`` there), the command-line
option is the name with dashes (``--rate-hz``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from triswarm.protocol.frames import parse_home

from .autopilots.registry import PROFILES

DEFAULT_ZENOH_BASE_PORT = 17447
"""Default peers on one machine: agent i listens on TCP port base + i."""
PYTHON_TYPE = {"int": int, "float": float, "str": str, "path": Path, "bool": bool, "strlist": tuple}


@dataclass(frozen=True)
class Opt:
    name: str
    kind: str
    """int, float, str, path (relative to the configuration file's folder), bool or strlist."""
    default: Any
    help: str
    check: Callable[[Any], str | None] | None = None
    """The problem with a value (one sentence, naming the option by its flag), or None."""
    per_agent: bool = False
    """Given once for each agent a process flies (--id, --fc, --gcs)."""
    metavar: str | None = None

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def file_key(self) -> str:
        return "zenoh." + self.name.removeprefix("zenoh_") if self.name.startswith("zenoh_") else self.name


def _between(flag: str, lo: float, hi: float, what: str = "") -> Callable[[Any], str | None]:
    def check(value):
        if not (math.isfinite(value) and lo <= value <= hi):
            return f"{flag} must be {what or f'between {lo:g} and {hi:g}'}, got {value}"
        return None
    return check


def _one_of(flag: str, choices: tuple[str, ...]) -> Callable[[Any], str | None]:
    return lambda value: None if value in choices else f"{flag} must be one of {', '.join(choices)}, got {value!r}"


def _home(value) -> str | None:
    try:
        parse_home(value)
    except ValueError as exc:
        return str(exc) if str(exc).startswith("--home") else f"--home {value}: {exc}"
    return None


OPTIONS: tuple[Opt, ...] = (
    Opt("id", "int", None, "This drone's number in the swarm (its MAVLink system id). Repeat, with --fc and --gcs for "
        "each, to fly several simulated drones in this process.", _between("--id", 1, 255, "a MAVLink system id between 1 "
                                                                             "and 255"), per_agent=True, metavar="N"),
    Opt("fc", "str", None, "Flight-controller link (pymavlink connection string, a serial port DEVICE:BAUD, or PX4's Zenoh bridge "
        "px4-zenoh://ROUTER_HOST:PORT/NAMESPACE).",
        per_agent=True, metavar="URL"),
    Opt("gcs", "str", None, "Ground-station link (pymavlink connection string).", per_agent=True, metavar="URL"),
    Opt("plan", "path", None, "A plan file (TOML) to load at start; without one, the ground station uploads it "
        "(triswarm plan upload).", metavar="PLAN"),
    Opt("autostart", "bool", False, "Arm, take off and start the plan at the common start time."),
    Opt("start_at", "float", None, "Common start time [s since the Unix epoch] (default with --autostart: the next "
        "multiple of 10 s, 5 s ahead).", lambda v: None if math.isfinite(v) else
        f"--start-at must be a finite number of seconds, got {v}"),
    Opt("fc_profile", "str", "auto", "The kind of flight controller: auto (as its HEARTBEAT says), triswarm "
        "(triswarm's simulated ones), ardupilot (ArduCopter with deploy/ardupilot/triswarm.lua) or px4.",
        _one_of("--fc-profile", PROFILES)),
    Opt("home", "str", None, "The swarm's home LAT,LON,ALT_M: the common origin of every drone's positions (an "
        "ArduPilot flight controller's EKF origin is set there).", _home, metavar="LAT,LON,ALT_M"),
    Opt("zenoh_config", "path", None, "Zenoh configuration file (JSON5): client or router modes across machines."),
    Opt("zenoh_listen", "strlist", (), "Zenoh endpoint to listen on (repeat)."),
    Opt("zenoh_connect", "strlist", (), "Zenoh endpoint to connect to (repeat)."),
    Opt("zenoh_mode", "str", "peer", "Zenoh mode with --zenoh-listen/--zenoh-connect: peer or client.",
        _one_of("--zenoh-mode", ("peer", "client"))),
    Opt("zenoh_base_port", "int", DEFAULT_ZENOH_BASE_PORT, "Default peers on one machine: agent i listens on TCP "
        "port base+i.", _between("--zenoh-base-port", 1, 65535 - 255)),
    Opt("rate_hz", "float", 200.0, "Control rate [Hz] (the telemetry rate it asks for).",
        _between("--rate-hz", 1.0, 2000.0)),
    Opt("gcs_frames_per_s", "float", 100.0, "Frames a second one ground station may send beyond a burst of twice "
        "that; beyond: dropped, counted and said once (0: no limit).",
        _between("--gcs-frames-per-s", 0.0, math.inf, "a non-negative number (0: no limit)")),
    Opt("state_dir", "path", None, "Keep the plan and mission here, to resume after a restart ({id} in the path: "
        "the drone's number)."),
    Opt("swarm", "str", None, "Swarm name in the Zenoh key space (default: the plan's name)."),
    Opt("stats", "path", None, "Write loop statistics here at exit (JSON; {id} in the path: the drone's number)."),
    Opt("signing_key", "path", None, "MAVLink 2 signing key file (32 bytes, or 64 hex digits): sign the "
        "ground-station link and refuse its unsigned commands, plans and parameter changes."),
    Opt("verbose", "bool", False, "Log more."),
)
BY_NAME = {o.name: o for o in OPTIONS}
BY_FILE_KEY = {o.file_key: o for o in OPTIONS}
REQUIRED = ("id", "fc", "gcs")


def _field(o: Opt):
    kind = PYTHON_TYPE[o.kind]
    return o.name, (kind if o.default is not None else kind | None), dataclasses.field(default=o.default)


CompanionOptions = dataclasses.make_dataclass(
    "CompanionOptions", [_field(o) for o in OPTIONS], frozen=True)
CompanionOptions.__module__ = __name__
CompanionOptions.__doc__ = "The options one agent runs with: one field per ``OPTIONS`` entry, of the same name."


def home_of(opts) -> tuple[float, float, float] | None:
    """The swarm's home as numbers (checked already), or None."""
    return None if opts.home is None else parse_home(opts.home)
