"""`triswarm monitor`: a live table of the swarm, one row per drone, from what the ground station hears:
the flight controller's heartbeat (armed, mode, failsafe) and position, and the companion's heartbeat
(phase) and health values (formation error, neighbour ages, loop timing)."""

from __future__ import annotations

import contextlib
import math
import signal
import threading
import time
from collections.abc import Iterable, Iterator, Mapping
from typing import Annotated, Optional

import typer
from pymavlink import mavutil
from rich.console import Console
from rich.live import Live
from rich.table import Table
from rich.text import Text

from triswarm.protocol.autopilots import COMPANION_MODES, is_ardupilot
from triswarm.protocol.mavlink import COMP_AUTOPILOT, COMP_ONBOARD, mavlink, mode_name

from .errors import console, require_positive, user_errors
from .link import Seen, Subscription
from .swarm_cmd import DEFAULT_TLOG, Drones, Endpoints, Manifest, SigningKey, Tlog, swarm_link

LOST_S = 2.0
"""A drone heard from longer ago than this is shown as lost."""
STALE_S = 3.0
"""A companion value (sent at 1 Hz) not repeated for this long is no longer shown."""
FAILSAFE_TEXT_S = 10.0
"""A flight controller's STATUSTEXT about a failsafe counts this long (unless it says it cleared)."""
ONCE_WAIT_S = 5.0
"""``--once`` waits this long at most [s] for a whole second of every drone (``_heard_a_second``)."""
TEXT_CHARS = 40
PLAIN_WIDTH = 200


def _mode(heartbeat) -> str:
    """A flight controller's mode by its name in its own autopilot's terms."""
    if is_ardupilot(heartbeat.autopilot):
        return mavutil.mode_mapping_acm.get(heartbeat.custom_mode, f"mode {heartbeat.custom_mode}")
    return mode_name(heartbeat.custom_mode)


def rows(seen: Mapping[tuple[int, int], Seen], positions: Mapping[int, tuple[float, object]],
         drones: Iterable[int], now: float) -> list[dict]:
    """One dict per drone from what the link heard (``seen``: GroundLink.seen) and the last
    LOCAL_POSITION_NED of each flight controller (``positions``: drone -> (Unix time, message)),
    judged at Unix time ``now``."""
    out = []
    for i in drones:
        fc, comp = seen.get((i, COMP_AUTOPILOT), Seen()), seen.get((i, COMP_ONBOARD), Seen())
        hb, comp_hb = fc.heartbeat, comp.heartbeat
        comp_named = dict(comp.named)  # copies: the link's reader thread adds to these meanwhile
        named = {name: value for name, (value, at) in comp_named.items() if now - at <= STALE_S}
        fc_texts, comp_texts = list(fc.texts), list(comp.texts)
        position = positions.get(i)
        times = [s.heartbeat_at for s in (fc, comp) if s.heartbeat is not None]
        times += [at for _, at in comp_named.values()] + [at for at, _, _ in fc_texts + comp_texts]
        times += [position[0]] if position else []
        armed = None if hb is None else bool(hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        last_text = max(fc_texts + comp_texts, default=None, key=lambda t: t[0])
        neighbours = sorted(int(name[2:-6]) for name in comp_named
                            if name.startswith("NB") and name.endswith("_AGEMS") and name[2:-6].isdigit())
        out.append({
            "drone": i,
            "age_s": now - max(times) if times else None,
            "armed": armed,
            "mode": None if hb is None else _mode(hb),
            "failsafe": bool(armed and hb.system_status == mavlink.MAV_STATE_CRITICAL) or _failsafe_said(fc_texts, now),
            "phase": None if comp_hb is None else COMPANION_MODES.get(comp_hb.custom_mode, f"phase {comp_hb.custom_mode}"),
            "form_err_m": named.get("FORM_ERRM"),
            "neighbours_ms": {j: named.get(f"NB{j}_AGEMS") for j in neighbours},
            "loop_hz": named.get("LOOP_HZ"),
            "jitter_p99_ms": named.get("JIT_P99MS"),
            "misses": named.get("MISSES"),
            "position_ned_m": None if position is None else (position[1].x, position[1].y, position[1].z),
            "text": None if last_text is None else last_text[2],
        })
    return out


def _heard_a_second(seen: Mapping[tuple[int, int], Seen], drones: Iterable[int]) -> bool:
    """Two heartbeats of every drone's flight controller and of its companion: a second of each
    (both send one a second; the companion sends its values after each, so the values of a whole
    second came between its two). Judged on what came, not on the wall clock: a busy machine, or a
    simulator running slower than real time, only makes the wait longer."""
    return all(seen.get((i, comp), Seen()).heartbeats >= 2 for i in drones for comp in (COMP_AUTOPILOT, COMP_ONBOARD))


def _failsafe_said(texts: list[tuple[float, int, str]], now: float) -> bool:
    """The flight controller's last word on a failsafe is recent and did not clear it."""
    said = [text.lower() for at, _, text in texts if "failsafe" in text.lower() and now - at <= FAILSAFE_TEXT_S]
    return bool(said) and "cleared" not in said[-1]


def table(rows: list[dict]) -> Table:
    t = Table(title="triswarm monitor", title_justify="left")
    for name in ("drone", "link", "armed", "mode", "failsafe", "phase", "form err [m]", "neighbours",
                 "loop", "position NED [m]", "last message"):
        t.add_column(Text(name), justify="right" if name in ("drone", "link", "form err [m]") else "left", no_wrap=True)
    for r in rows:
        age = r["age_s"]
        link = (Text("lost", style="red") if age is None else
                Text(f"lost {age:.1f} s", style="red") if age > LOST_S else Text(f"{age:.1f} s"))
        armed = "-" if r["armed"] is None else "yes" if r["armed"] else "no"
        failsafe = Text("yes", style="bold red") if r["failsafe"] else Text("no")
        neighbours = " ".join(f"{j}:{'-' if a is None else f'{a:.1f}'}" for j, a in r["neighbours_ms"].items())
        loop = " ".join(s for s in (_fmt(r["loop_hz"], "{:.0f} Hz"), _fmt(r["jitter_p99_ms"], "p99 {:.2f} ms"),
                                    _fmt(r["misses"], "{:.0f} missed")) if s)
        position = r["position_ned_m"]
        text = r["text"] or ""
        t.add_row(str(r["drone"]), link, armed, r["mode"] or "-", failsafe, r["phase"] or "-",
                  _fmt(r["form_err_m"], "{:.3f}") or "-", f"{neighbours} ms" if neighbours else "-", loop or "-",
                  "-" if position is None else ", ".join(f"{v:.1f}" for v in position),
                  Text(text if len(text) <= TEXT_CHARS else text[:TEXT_CHARS - 1] + "…"))
    return t


def _fmt(value: float | None, spec: str) -> str:
    return "" if value is None else spec.format(value)


def monitor(
    manifest: Manifest = None, endpoint: Endpoints = None, drone: Drones = None, tlog: Tlog = DEFAULT_TLOG,
    signing_key: SigningKey = None,
    rate_hz: Annotated[float, typer.Option("--rate-hz", help="Refresh rate [Hz].")] = 5.0,
    duration_s: Annotated[Optional[float], typer.Option("--duration-s", help="Stop after this long [s].")] = None,
    once: Annotated[bool, typer.Option("--once", help="Listen until a whole second of every drone has come (two heartbeats of its flight controller and of its companion), print one table and exit.")] = False,
    wait_s: Annotated[float, typer.Option("--wait-s", help="With --once: print after this long [s] at most; the drones not heard by then show what came, or lost.")] = ONCE_WAIT_S,
) -> None:
    """Watch the swarm: a live table, one row per drone (plain tables when stdout is not a terminal).
    Ctrl-C stops."""
    with user_errors():
        require_positive(rate_hz=rate_hz, duration_s=duration_s, wait_s=wait_s)
    plain = console if console.is_terminal else Console(width=PLAIN_WIDTH)
    with _ctrl_c() as stop, swarm_link(manifest, endpoint, drone, tlog, signing_key, require_all=False) as (link, chosen), \
            link.subscribe(None, COMP_AUTOPILOT, "LOCAL_POSITION_NED") as sub:
        positions: dict[int, tuple[float, object]] = {}

        def current() -> Table:
            _drain(sub, positions)
            return table(rows(link.seen, positions, chosen, time.time()))

        if once:
            deadline = time.monotonic() + wait_s
            while not (stop.is_set() or time.monotonic() >= deadline or _heard_a_second(link.seen, chosen)):
                stop.wait(0.05)
            plain.print(current())
        elif not console.is_terminal:
            for _ in _ticks(1.0 / rate_hz, duration_s, stop):
                plain.print(current())
        else:
            with Live(current(), console=console, screen=False, refresh_per_second=rate_hz) as live:
                for _ in _ticks(1.0 / rate_hz, duration_s, stop):
                    live.update(current())


@contextlib.contextmanager
def _ctrl_c() -> Iterator[threading.Event]:
    """Ctrl-C (SIGINT) sets the event the monitor's loop waits on, so it stops between two tables
    and closes its links. (A KeyboardInterrupt could land anywhere, inside a lock the link's reader
    thread needs too, and hang the exit.)"""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = signal.signal(signal.SIGINT, lambda signum, frame: stop.set())
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)


def _drain(sub: Subscription, positions: dict[int, tuple[float, object]]) -> None:
    """Keep the last LOCAL_POSITION_NED per drone."""
    while (msg := sub.get_nowait()) is not None:
        positions[msg.get_srcSystem()] = (time.time(), msg)


def _ticks(period_s: float, duration_s: float | None, stop: threading.Event) -> Iterator[None]:
    """Once now, then every period_s until duration_s has passed (forever without one) or stop is set."""
    end = math.inf if duration_s is None else time.monotonic() + duration_s
    while True:
        yield
        left = end - time.monotonic()
        if left <= 0 or stop.wait(min(period_s, left)):
            return
