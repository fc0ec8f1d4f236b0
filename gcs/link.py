"""The ground station's MAVLink links: one per drone (to its companion, which routes to the flight
controller; and for a flight controller the companion does not route, PX4 flown over Zenoh, one to
it beside), a reader thread, a .tlog of everything received, and waiting for answers.

Endpoints come from a swarm manifest (``swarm.json``, written by ``triswarm stack`` and the demo):

    {"swarm": "paper-hexagon", "drones": [{"id": 1, "mavlink": "udpout:127.0.0.1:14601"}, ...]}

(each drone with ``"fc_mavlink"`` too where its flight controller has a link of its own)

or from ``--endpoint ID=URL`` (pymavlink connection strings).

With a signing key, every frame sent is signed (MAVLink 2 signing; the link id is this process's
id modulo 256, so ground stations running at once are, but for a chance of 1/256, separate streams
of signed frames) and signed frames received are checked: one with a wrong signature or a replayed timestamp is dropped and counted
(``counters["refused_*"]``). Unsigned frames are taken: the flight controllers' own, which their
companions forward as they came, are not signed.
"""

from __future__ import annotations

import json
import os
import queue
import select
import struct
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from triswarm.protocol.mavlink import COMP_ONBOARD, SIGNATURE_REFUSED, mavlink, new_codec, setup_signing

from .errors import GcsError

GCS_SYSID = 255
GCS_COMPID = mavlink.MAV_COMP_ID_MISSIONPLANNER  # 190, as ground stations do


NETWORK_SCHEMES = ("udp", "udpin", "udpout", "udpbcast", "tcp", "tcpin")
"""pymavlink's connection strings that name a HOST:PORT (the others are serial devices and files)."""


class LinkError(GcsError):
    """An endpoint that cannot be opened or a manifest that cannot be read (one sentence)."""


def parse_endpoints(manifest: Path | None, endpoints: list[str] | None) -> tuple[dict[int, str], dict[int, str]]:
    """Drone id -> pymavlink URL of each companion, from a manifest and/or ``ID=URL`` strings (these
    win); and of each flight controller the manifest gives a link of its own (``fc_mavlink``: PX4
    flown over Zenoh)."""
    out: dict[int, str] = {}
    fc: dict[int, str] = {}
    if manifest is not None:
        try:
            data = json.loads(Path(manifest).read_text(encoding="utf-8"))
            for d in data["drones"]:
                out[int(d["id"])] = str(d["mavlink"])
                if "fc_mavlink" in d:
                    fc[int(d["id"])] = str(d["fc_mavlink"])
        except FileNotFoundError:
            raise LinkError(f"{manifest}: no such swarm manifest") from None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise LinkError(f"{manifest}: not a swarm manifest ({exc.__class__.__name__}: {exc})") from None
    for spec in endpoints or []:
        ident, sep, url = spec.partition("=")
        if not sep or not ident.strip().isdigit() or not 1 <= int(ident) <= 254 or not url:
            raise LinkError(f"--endpoint {spec!r}: expected ID=URL with ID in 1..254, e.g. 1=udpout:127.0.0.1:14601")
        scheme, _, address = url.partition(":")
        host, _, port = address.rpartition(":")
        if scheme in NETWORK_SCHEMES and not (host and port.isdigit() and int(port) <= 65535):
            raise LinkError(f"--endpoint {spec!r}: expected {scheme}:HOST:PORT with PORT in 0..65535")
        out[int(ident)] = url
    if not out:
        raise LinkError("no drones: give --manifest (swarm.json) or --endpoint ID=URL")
    return out, fc


def write_manifest(path: Path, swarm: str, endpoints: dict[int, str], fc_endpoints: dict[int, str] | None = None) -> None:
    fc = fc_endpoints or {}
    data = {"swarm": swarm, "drones": [{"id": i, "mavlink": url, **({"fc_mavlink": fc[i]} if i in fc else {})}
                                       for i, url in sorted(endpoints.items())]}
    Path(path).write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


@dataclass
class Seen:
    """What the ground station last heard from one (system, component)."""

    heartbeat: object = None
    heartbeat_at: float = 0.0
    heartbeats: int = 0
    """How many heartbeats were heard."""
    named: dict = field(default_factory=dict)
    """NAMED_VALUE_FLOAT name -> (value, Unix time received)."""
    texts: list = field(default_factory=list)
    """(Unix time, severity, text) of the STATUSTEXTs, chunks joined."""
    landed_state: int | None = None
    """EXTENDED_SYS_STATE's newest MAV_LANDED_STATE."""


class Subscription:
    def __init__(self, link: "GroundLink", sysid: int | None, compid: int | None, types: set[str]) -> None:
        self.link, self.sysid, self.compid, self.types = link, sysid, compid, types
        self.queue: queue.Queue = queue.Queue()

    def matches(self, msg) -> bool:
        return (msg.get_type() in self.types and (self.sysid is None or msg.get_srcSystem() == self.sysid)
                and (self.compid is None or msg.get_srcComponent() == self.compid))

    def get(self, timeout_s: float):
        try:
            return self.queue.get(timeout=max(0.0, timeout_s))
        except queue.Empty:
            return None

    def get_nowait(self):
        try:
            return self.queue.get_nowait()
        except queue.Empty:
            return None

    def __enter__(self) -> "Subscription":
        return self

    def __exit__(self, *exc) -> None:
        with self.link._lock:
            self.link._subs.remove(self)


class GroundLink:
    """Use as a context manager. ``tlog``: every message received, with its arrival time.
    ``signing_key``: sign what is sent, check what is received signed (see the module's text)."""

    def __init__(self, endpoints: dict[int, str], tlog: Path | None = None, heartbeat_hz: float = 1.0,
                 signing_key: bytes | None = None, fc_endpoints: dict[int, str] | None = None) -> None:
        """``endpoints``: each drone's companion. ``fc_endpoints``: the flight controllers reached
        by a link of their own beside it (PX4, which its companion flies over Zenoh and whose MAVLink
        it does not route): what is sent to such a drone's component 1 goes there."""
        from pymavlink import mavutil

        self.endpoints = dict(endpoints)
        urls = {(i, COMP_ONBOARD): url for i, url in self.endpoints.items()}
        urls.update({(i, mavlink.MAV_COMP_ID_AUTOPILOT1): url for i, url in (fc_endpoints or {}).items()})
        self.conns = {}
        self.codecs = {}
        self.seen: dict[tuple[int, int], Seen] = defaultdict(Seen)
        self.counters: dict[str, int] = defaultdict(int)
        self._subs: list[Subscription] = []
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._chunks: dict[tuple, list] = {}
        self._stop = threading.Event()
        self._heartbeat_s = 1.0 / heartbeat_hz
        self._fc_offset_us: dict[int, int] = {}
        self._fc_now: dict[int, float] = {}
        self.tlog = None
        self._thread = threading.Thread(target=self._run, name="gcs-link", daemon=True)
        for key, url in urls.items():
            try:
                self.conns[key] = mavutil.mavlink_connection(url, source_system=GCS_SYSID, source_component=GCS_COMPID,
                                                             autoreconnect=True)
            except (OSError, ValueError) as exc:  # what the socket or serial layer raises for this URL
                self.close()
                what = "companion" if key[1] == COMP_ONBOARD else "flight controller"
                raise LinkError(f"cannot open the link to drone {key[0]}'s {what} at {url}: {exc}") from None
            self.codecs[key] = new_codec(GCS_SYSID, GCS_COMPID)
            if signing_key is not None:
                setup_signing(self.codecs[key], signing_key, os.getpid() % 256, lambda msg_id: True, self.counters,
                              clock=time.time)
        if tlog is not None:
            try:
                self.tlog = open(tlog, "ab")
            except OSError as exc:
                self.close()
                raise LinkError(f"{tlog}: cannot open the MAVLink log ({exc.strerror})") from None

    def __enter__(self) -> "GroundLink":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        for c in self.conns.values():
            c.close()
        if self.tlog is not None:
            self.tlog.close()
            self.tlog = None

    # -- sending --------------------------------------------------------------------------------

    def send(self, drone: int, msg) -> None:
        """To the drone's companion, or to its flight controller's own link if it has one and the
        message is for component 1."""
        key = (drone, mavlink.MAV_COMP_ID_AUTOPILOT1)
        if key not in self.conns or getattr(msg, "target_component", None) != mavlink.MAV_COMP_ID_AUTOPILOT1:
            key = (drone, COMP_ONBOARD)
        self._write(key, msg)

    def _write(self, key: tuple[int, int], msg) -> None:
        with self._send_lock:  # the reader thread sends heartbeats meanwhile
            self.conns[key].write(msg.pack(self.codecs[key]))

    def subscribe(self, sysid: int | None, compid: int | None, *types: str) -> Subscription:
        sub = Subscription(self, sysid, compid, set(types))
        with self._lock:
            self._subs.append(sub)
        return sub

    def command(self, drone: int, compid: int, command: int, params=(), *, use_int: bool = False,
                x: int = 0, y: int = 0, timeout_s: float = 0.6, retries: int = 4) -> tuple[int | None, str]:
        """COMMAND_LONG (or COMMAND_INT) with retries; (MAV_RESULT or None on no answer, the
        STATUSTEXT reasons the component gave meanwhile)."""
        p = list(params) + [0.0] * (7 - len(params))
        with self.subscribe(drone, compid, "COMMAND_ACK", "STATUSTEXT") as sub:
            texts: list[str] = []
            for attempt in range(retries + 1):
                if use_int:
                    msg = mavlink.MAVLink_command_int_message(drone, compid, 0, command, 0, 0, *p[:4], x, y, p[6])
                else:
                    msg = mavlink.MAVLink_command_long_message(drone, compid, command, attempt, *p)
                self.send(drone, msg)
                deadline = time.monotonic() + timeout_s
                while (answer := sub.get(deadline - time.monotonic())) is not None:
                    if answer.get_type() == "STATUSTEXT":
                        texts.append(answer.text)
                    elif answer.command == command:
                        if answer.result == mavlink.MAV_RESULT_IN_PROGRESS:
                            deadline = time.monotonic() + timeout_s
                            continue
                        time.sleep(0.02)  # a reason sent with the answer may trail it
                        while (more := sub.get(0.0)) is not None:
                            if more.get_type() == "STATUSTEXT":
                                texts.append(more.text)
                        return answer.result, "; ".join(texts)
        return None, "; ".join(texts)

    def param(self, drone: int, compid: int, name: str, timeout_s: float = 0.5, retries: int = 4) -> float | None:
        with self.subscribe(drone, compid, "PARAM_VALUE") as sub:
            for _ in range(retries + 1):
                self.send(drone, mavlink.MAVLink_param_request_read_message(drone, compid, name.encode(), -1))
                deadline = time.monotonic() + timeout_s
                while (answer := sub.get(deadline - time.monotonic())) is not None:
                    if answer.param_id == name:
                        return answer.param_value
        return None

    # -- receiving ------------------------------------------------------------------------------

    def _run(self) -> None:
        by_fd = {c.fd: (key, c) for key, c in self.conns.items() if getattr(c, "fd", None) is not None}
        next_heartbeat = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_heartbeat:
                next_heartbeat = now + self._heartbeat_s
                for key in self.conns:
                    self._send_quietly(key, mavlink.MAVLink_heartbeat_message(
                        mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3))
            try:
                ready, _, _ = select.select(list(by_fd), [], [], 0.05)
            except (OSError, ValueError):
                break
            for fd in ready:
                key, conn = by_fd[fd]
                try:
                    data = conn.recv(65536)
                except OSError:
                    self.counters["receive_errors"] += 1
                    continue
                if data:
                    self._take(key, bytes(data))

    def _send_quietly(self, key: tuple[int, int], msg) -> None:
        try:
            self._write(key, msg)
        except OSError:
            self.counters["send_errors"] += 1

    def _take(self, key: tuple[int, int], data: bytes) -> None:
        try:
            with self._send_lock:  # a signed frame parsed may move the signing timestamp the senders use
                msgs = self.codecs[key].parse_buffer(data) or []
        except Exception:  # pymavlink raises MAVError and struct errors on garbage
            self.counters["bad_frames"] += 1
            return
        now = time.time()
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                if msg.reason != SIGNATURE_REFUSED:  # (the signing counted those)
                    self.counters["bad_frames"] += 1
                continue
            self.counters["messages"] += 1
            if self.tlog is not None:
                self.tlog.write(struct.pack(">Q", int(now * 1e6)) + msg.get_msgbuf())
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            seen = self.seen[src]
            t = msg.get_type()
            if src[1] == mavlink.MAV_COMP_ID_AUTOPILOT1 and t in ("SYSTEM_TIME", "ATTITUDE"):
                self._fc_clock(src[0], msg)
            if t == "HEARTBEAT":
                seen.heartbeat, seen.heartbeat_at = msg, now
                seen.heartbeats += 1
            elif t == "NAMED_VALUE_FLOAT":
                seen.named[msg.name] = (msg.value, now)
            elif t == "EXTENDED_SYS_STATE":
                seen.landed_state = msg.landed_state
            elif t == "STATUSTEXT":
                msg = self._joined(msg, src)
                if msg is None:
                    continue
                seen.texts.append((now, msg.severity, msg.text))
                del seen.texts[:-50]
            with self._lock:
                subs = [s for s in self._subs if s.matches(msg)]
            for s in subs:
                s.queue.put(msg)

    def _joined(self, msg, src):
        """A whole STATUSTEXT: chunks (MAVLink 2 id != 0) joined; None while more are to come."""
        if not getattr(msg, "id", 0):
            return msg
        key = (*src, msg.id)
        parts = self._chunks.setdefault(key, [])
        parts.append(msg.text)
        if len(msg.text.encode()) == 50:
            return None
        del self._chunks[key]
        msg.text = "".join(parts)
        return msg

    def _fc_clock(self, drone: int, msg) -> None:
        if msg.get_type() == "SYSTEM_TIME":
            if msg.time_unix_usec > 0:
                self._fc_offset_us[drone] = msg.time_unix_usec - msg.time_boot_ms * 1000
                self._fc_now[drone] = msg.time_unix_usec / 1e6
        elif drone in self._fc_offset_us:
            self._fc_now[drone] = (self._fc_offset_us[drone] + msg.time_boot_ms * 1000) / 1e6

    def fc_now(self) -> float:
        """The flight controllers' clock as last heard (their SYSTEM_TIME and telemetry), as Unix
        time: the slowest one's; NaN before every drone's was heard. On a simulator in lockstep this
        is simulated time, not the wall's."""
        times = [self._fc_now.get(i) for i in self.endpoints]
        return float("nan") if None in times else min(times)

    def companion(self, drone: int) -> Seen:
        return self.seen[(drone, COMP_ONBOARD)]

    def autopilot(self, drone: int) -> Seen:
        return self.seen[(drone, mavlink.MAV_COMP_ID_AUTOPILOT1)]
