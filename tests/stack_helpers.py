"""Observers for whole-stack tests: a ground station on a companion's link (pymavlink, real UDP) and
a Zenoh peer on the swarm's bus (a real session). Both record in background threads; both stop
when their context ends. Both stamp what they hear with the flight controllers' clock, as the
Recorder does, so that a test on simulated time (lockstep) reads its timeline in plan time."""

from __future__ import annotations

import json
import re
import threading
import time
from collections import defaultdict

import numpy as np
import zenoh
from pymavlink import mavutil

from triswarm.companion.zenoh_session import peer_config
from triswarm.protocol import metrics

from .poll import poll


class GroundStation:
    """A GCS on one companion's ground-station link: says hello at 1 Hz, records what it hears. Until
    it hears the companion, it says hello every 0.1 s: a companion still starting misses the first,
    and in lockstep a small swarm can fly its first 20 simulated seconds in two of wall time, so a
    hello a second would miss what the companion says meanwhile, the faster the machine the more."""

    def __init__(self, port: int, sysid: int = 255, compid: int = 190) -> None:
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=sysid,
                                               source_component=compid)
        self.messages: list[tuple[float, object]] = []
        """(the flight controller's time when heard [Unix s; NaN before it was heard], message)"""
        self._fc_offset: float | None = None
        self._fc_now = float("nan")
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> "GroundStation":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.conn.close()

    def _run(self) -> None:
        next_hello = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hello:
                self.send(self.conn.mav.heartbeat_encode(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID,
                                                         0, 0, 0))
                next_hello = now + (1.0 if self.messages else 0.1)
            msg = self.conn.recv_match(blocking=True, timeout=0.1)
            if msg is not None and msg.get_type() != "BAD_DATA":
                self._clock(msg)
                with self._lock:
                    self.messages.append((self._fc_now, msg))

    def _clock(self, msg) -> None:
        """The flight controller's clock from what it forwards (SYSTEM_TIME, ATTITUDE)."""
        if msg.get_srcComponent() != 1:
            return
        if msg.get_type() == "SYSTEM_TIME" and msg.time_unix_usec > 0:
            self._fc_offset = msg.time_unix_usec / 1e6 - msg.time_boot_ms / 1000.0
            self._fc_now = msg.time_unix_usec / 1e6
        elif msg.get_type() == "ATTITUDE" and self._fc_offset is not None:
            self._fc_now = self._fc_offset + msg.time_boot_ms / 1000.0

    def send(self, msg) -> None:
        with self._lock:
            self.conn.mav.send(msg)

    def heard(self, type_: str, **where) -> list:
        with self._lock:
            found = [m for _, m in self.messages if m.get_type() == type_]
        return [m for m in found if all(_field(m, k) == v for k, v in where.items())]

    def wait_for(self, type_: str, timeout_s: float, **where) -> list:
        """The messages of ``type_`` (with fields ``where``) heard, once there is one (bounded)."""
        poll(lambda: bool(self.heard(type_, **where)), timeout_s)
        return self.heard(type_, **where)


def _field(m, name):
    if name == "srcSystem":
        return m.get_srcSystem()
    if name == "srcComponent":
        return m.get_srcComponent()
    value = getattr(m, name)
    return value.decode(errors="replace") if isinstance(value, bytes) else value


class BusObserver:
    """A Zenoh peer connected to every agent of a stack started with default peers on loopback."""

    def __init__(self, swarm: str, zenoh_base: int, n: int) -> None:
        connect = [f"tcp/127.0.0.1:{zenoh_base + i}" for i in range(1, n + 1)]
        self.swarm = swarm
        self.session = zenoh.open(peer_config([], connect))
        self.statuses: list[tuple[float, int, str, str]] = []
        """(since: the flight controller's time the status began [Unix s], agent, status, reason)"""
        self.health: dict[int, list[dict]] = defaultdict(list)
        self._lock = threading.Lock()
        self._subs = [
            self.session.declare_subscriber(f"triswarm/{swarm}/agent/*/status", self._on_status),
            self.session.declare_subscriber(f"triswarm/{swarm}/agent/*/health", self._on_health),
        ]

    def __enter__(self) -> "BusObserver":
        return self

    def __exit__(self, *exc) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()

    def _on_status(self, sample) -> None:
        try:  # (garbage a test puts on the bus comes back here too: json.loads takes b"\x00..." for UTF-16)
            msg = json.loads(sample.payload.to_bytes())
            status = (float(msg["since"]), int(msg["agent"]), msg["status"], msg.get("reason", ""))
        except (ValueError, KeyError, TypeError):
            return
        with self._lock:
            self.statuses.append(status)

    def _on_health(self, sample) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
            agent = int(msg["agent"])
        except (ValueError, KeyError, TypeError):
            return
        with self._lock:
            self.health[agent].append(msg)

    def put(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload)

    def token(self, key: str):
        """Declare a liveliness token (undeclared when the session closes)."""
        return self.session.liveliness().declare_token(key)


def judge(plan, recorder, start_unix: float, t_from: float, t_to: float, drones=None,
          position_bound_m: float = 0.10, attitude_bound_rad: float = 0.02):
    """Worst position and attitude errors of ``drones`` (numbers from 1; all by default) against
    x0 + h_i(t) over [t_from, t_to] of plan time, from the flight controllers' own telemetry."""
    t, pos, eta = recorder.arrays(start_unix, t_from=t_from, t_to=t_to)
    pe, ae = metrics.formation_errors(plan, t, pos, eta)
    cols = np.arange(plan.n_agents) if drones is None else np.asarray(drones) - 1
    worst_p, worst_a = pe[:, cols].max(axis=0), ae[:, cols].max(axis=(0, 2))
    report = {int(c) + 1: (round(float(p), 4), round(float(a), 4)) for c, p, a in zip(cols, worst_p, worst_a)}
    ok = bool((worst_p <= position_bound_m).all() and (worst_a <= attitude_bound_rad).all())
    return ok, report


def judge_truth(plan, truth_path, recorder, start_unix: float, t_from: float, t_to: float,
                position_bound_m: float, attitude_bound_rad: float, rate_hz: float = 50.0):
    """As ``judge``, from a firmware-in-the-loop run's plant truth (``gcs/truth.py``), put on each
    drone's clock as the recorder heard it."""
    from triswarm.gcs.tracks import on_grid
    from triswarm.gcs.truth import read_truth

    offsets = [next((o for o in d.offsets_at(start_unix) if not np.isnan(o)), np.nan)
               for _, d in sorted(recorder.samples.snapshot().items())]
    t = np.arange(t_from, t_to, 1.0 / rate_hz)
    pos, eta = on_grid(read_truth(truth_path, offsets, start_unix), t)
    pe, ae = metrics.formation_errors(plan, t, pos, eta)
    worst_p, worst_a = pe.max(axis=0), ae.max(axis=(0, 2))
    report = {i + 1: (round(float(p), 4), round(float(a), 4)) for i, (p, a) in enumerate(zip(worst_p, worst_a))}
    return bool((worst_p <= position_bound_m).all() and (worst_a <= attitude_bound_rad).all()), report


def small_plan(spec: dict, drones: int, name: str) -> dict:
    """The paper's plan for fewer drones, over the two-chain graph alone (its families extend to any N)."""
    import copy

    spec = copy.deepcopy(spec)
    spec.update(name=name, drones=drones, topology={"switch_period_s": 5.0, "families": ["two-chain"]})
    return spec


def status_changes(statuses, agent: int) -> list[tuple[float, str, str]]:
    """An agent's status changes (since [Unix s], status, reason); the 1 Hz repeats dropped."""
    out: list[tuple[float, str, str]] = []
    for since, a, status, reason in statuses:
        if a == agent and (not out or out[-1][1] != status or out[-1][0] != since):
            out.append((since, status, reason))
    return out


def log_events(text: str, what: str) -> list[float]:
    """Plan times of a companion's "hold at t_plan X" / "rejoin at t_plan X" log lines."""
    out = []
    for line in text.splitlines():
        if f"{what} at t_plan " in line:
            out.append(float(line.split(f"{what} at t_plan ")[1].split(":")[0]))
    return out


def rejoin_ends(text: str) -> list[float]:
    """Plan times at which a companion's rejoins end ("rejoin at t_plan X: ... over D s")."""
    return [float(t) + float(d) for t, d in re.findall(r"rejoin at t_plan ([-\d.]+):.* over ([\d.]+) s", text)]


def wait_sim(clock, t_unix: float, stack=None, wall_timeout_s: float = 240.0, poll_s: float = 0.1,
             dead_ok: tuple[str, ...] = ()) -> None:
    """Wait until the flight controllers' clock (``clock()``, e.g. ``Recorder.now``) reaches
    ``t_unix``, checking that every process of ``stack`` (but those named in ``dead_ok``) still
    runs; fail after ``wall_timeout_s`` of wall time (a stack on simulated time runs as fast as
    the machine lets it)."""
    def all_running() -> None:
        dead = [] if stack is None else [name for name, up in stack.alive().items() if not up and name not in dead_ok]
        assert not dead, f"{dead} exited early: {[stack.log(n)[-2000:] for n in dead]}"

    poll(lambda: clock() >= t_unix, wall_timeout_s, f"the simulated clock reaching {t_unix:.1f}", poll_s, all_running)


def flying(link, drone: int) -> bool:
    """Seen from a gcs.link.GroundLink: the flight controller in EXTERNAL, the companion flying."""
    from triswarm.protocol.mavlink import CustomMode

    fc, companion = link.autopilot(drone).heartbeat, link.companion(drone).heartbeat
    return fc is not None and fc.custom_mode == CustomMode.EXTERNAL and companion is not None and companion.custom_mode == 2
