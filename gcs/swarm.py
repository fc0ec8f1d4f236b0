"""Operations on several drones at once over a ground station's link (``GroundLink``): each drone
in a thread of its own, each outcome as (accepted, detail). The operator's commands (``swarm_cmd``),
the demo and the tests use them."""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

from triswarm.protocol.autopilots import takeoff_commands
from triswarm.protocol.mavlink import COMP_AUTOPILOT, COMP_ONBOARD, mavlink

from . import missions
from .errors import console
from .link import GroundLink


def for_each(chosen: list[int], fn: Callable[[int], tuple[bool, str]]) -> dict[int, tuple[bool, str]]:
    with ThreadPoolExecutor(max_workers=len(chosen)) as pool:
        return dict(zip(chosen, pool.map(fn, chosen)))

def result_text(result: int | None, reasons: str) -> tuple[bool, str]:
    if result is None:
        return False, reasons or "no answer"
    name = mavlink.enums["MAV_RESULT"][result].name.removeprefix("MAV_RESULT_") if result in mavlink.enums["MAV_RESULT"] else str(result)
    return result == mavlink.MAV_RESULT_ACCEPTED, reasons or name.lower()

def flight_clock(link: GroundLink, wait_s: float = 2.0) -> float:
    """The flight controllers' clock (a simulator's in lockstep), as Unix time; the wall clock if
    none has told its time within ``wait_s`` (they send SYSTEM_TIME once a second)."""
    deadline = time.monotonic() + wait_s
    now = link.fc_now()  # (NaN until one has told its time)
    while math.isnan(now) and time.monotonic() < deadline:
        time.sleep(0.05)
        now = link.fc_now()
    return time.time() if math.isnan(now) else now


def upload_all(link: GroundLink, chosen: list[int], items) -> dict[int, tuple[bool, str]]:
    """The items to every chosen drone at once, a progress bar each."""
    with Progress(TextColumn("drone {task.fields[drone]}"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[state]}"),
                  console=console) as bars:
        tasks = {i: bars.add_task("", total=len(items), drone=i, state="") for i in chosen}

        def send(i: int) -> tuple[bool, str]:
            out = missions.upload(link, i, items, progress=lambda k: bars.update(tasks[i], completed=k))
            bars.update(tasks[i], state="accepted" if out.ok else "[red]refused[/]")
            return out.ok, out.detail

        return for_each(chosen, send)


def start_all(link: GroundLink, chosen: list[int], pid: int, start_unix_s: float) -> dict[int, tuple[bool, str]]:
    """MAV_CMD_TRISWARM_PLAN_START to every chosen drone: the plan in force from start_unix_s (to the
    millisecond: whole seconds in x, milliseconds in y)."""
    whole_ms = round(start_unix_s * 1000.0)  # (rounding seconds and milliseconds apart could lose a second)
    return for_each(chosen, lambda i: result_text(*link.command(
        i, COMP_ONBOARD, mavlink.MAV_CMD_TRISWARM_PLAN_START, [pid >> 16, pid & 0xFFFF], use_int=True,
        x=whole_ms // 1000, y=whole_ms % 1000)))


def command_all(link: GroundLink, chosen: list[int], compid: int, command: int, params: list[float]) -> dict:
    return for_each(chosen, lambda i: result_text(*link.command(i, compid, command, params)))

def take_off_all(link: GroundLink, chosen: list[int], height_m: float | None = None) -> dict[int, tuple[bool, str]]:
    """Each chosen drone's flight controller takes off by itself, as its kind is asked to
    (``protocol.autopilots.takeoff_commands``); stops at the first command one refuses."""
    def one(i: int) -> tuple[bool, str]:
        heartbeat = link.autopilot(i).heartbeat
        kind = heartbeat.autopilot if heartbeat is not None else mavlink.MAV_AUTOPILOT_GENERIC
        for command, params in takeoff_commands(kind, height_m):
            ok, detail = result_text(*link.command(i, COMP_AUTOPILOT, command, list(params)))
            if not ok:
                return ok, detail
        return True, "accepted"

    return for_each(chosen, one)
