"""The MAVLink face of the simulated swarm: one UDP endpoint per vehicle and link, and the clock.

Each link is a UDP server socket: a client (pymavlink ``udpout:``, MAVSDK ``udpout://``, MAVProxy)
sends first (a heartbeat), and the vehicle then streams to every address heard from in the last
few seconds. One asyncio loop runs the physics of all vehicles, answers every datagram as it
arrives, and sends the telemetry that falls due: all the messages one link owes at one physics
step go out in one datagram. The clock is either the wall clock (times ``speedup``) or, with a
``Lockstep``, the companions' answers (``lockstep.py``): then the plant steps in the very callback
that takes the last answer it waited for, and telemetry leaves at once.
"""

from __future__ import annotations

import asyncio
import gc
import math
import os
import socket
import time
from collections import Counter
from dataclasses import dataclass, field

from triswarm.protocol import frames
from triswarm.protocol.airframe import ParameterError
from triswarm.protocol.mavlink import COMP_AUTOPILOT, mavlink, new_codec, reset_parser
from triswarm.protocol.stall import Stalls

from .errors import LinkOpenError
from .fc import LINKS
from .lockstep import ATTITUDE_IDS, HIGH_RATE_IDS, Lockstep, LockstepOptions
from .profiles import JITTER_TABLE, product_step
from .swarm import SitlSwarm
from .telemetry import CONSTRUCTORS, STREAM_CODE, STREAMS, _ms, _us, batch_args

PEER_TIMEOUT_S = 5.0
MAX_PEERS_PER_LINK = 8
MAX_BURST_STEPS = 200
FINE_WAIT_S = 0.002
MAX_DATAGRAMS_PER_WAKEUP = 256  # drain a flood in slices so the physics keeps its clock
RECV_BUFFER_BYTES = 4 << 20
LOCKSTEP_POLL_S = 0.1  # while the clock waits: look at the watchdog this often [s]
REPORT_EVERY_S = 10.0  # lockstep: say how fast the clock runs this often [s]
STANDING_HEARTBEAT_S = 1.0
"""Lockstep: while the clock stands this long [s, wall], every vehicle sends its heartbeat on the wall
clock (a companion tells a dead flight controller from a waiting one by its silence)."""
ACTUATOR_MSG_ID = mavlink.MAVLINK_MSG_ID_SET_ACTUATOR_CONTROL_TARGET
SCHEDULED = (mavlink.MAVLINK_MSG_ID_HEARTBEAT, *(m for m, _ in STREAMS.values()))
"""Every message a vehicle sends on its own schedule (rates from ``FlightController.stream_rate_hz``)."""


@dataclass
class Link:
    vehicle: int
    name: str
    host: str
    port: int = 0
    sock: socket.socket | None = None
    codec: object = None
    parser: object = None
    peers: dict = field(default_factory=dict)  # address -> wall time last heard
    datagrams_rx: int = 0
    datagrams_tx: int = 0
    send_errors: int = 0

    def live_peers(self, now_wall: float) -> list:
        dead = [a for a, t in self.peers.items() if now_wall - t > PEER_TIMEOUT_S]
        for a in dead:
            del self.peers[a]
        return list(self.peers)

    def urls(self) -> dict:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        return {"pymavlink": f"udpout:{host}:{self.port}", "mavsdk": f"udpout://{host}:{self.port}",
                "host": host, "port": self.port}


class SitlServer:
    def __init__(self, swarm: SitlSwarm, bind_host: str = "127.0.0.1", base_port: int = 14600,
                 speedup: float = 1.0, lockstep: LockstepOptions | None = None,
                 say=lambda text, warning=False: print(text)) -> None:
        if not (speedup > 0 and speedup <= 10000):
            raise ParameterError(f"speedup must be a number above 0 and at most 10000, got {speedup!r}")
        self.lockstep = None if lockstep is None else Lockstep(swarm.n, lockstep)
        self.say = say
        for fc in swarm.fcs:
            fc.params["SIM_LOCKSTEP"] = float(lockstep is not None)
        self.boot_unix_s = math.floor((time.time() - swarm.time_s) * 1000.0) / 1000.0
        """Unix time of the flight controllers' boot, a whole millisecond: their SYSTEM_TIME is this plus
        simulated time (so a start time a whole number of milliseconds after it is one exactly)."""
        self.swarm = swarm
        self.bind_host = bind_host
        self.base_port = base_port
        self.speedup = float(speedup)
        self.links: list[dict[str, Link]] = []
        self._streams: dict[tuple[int, str], dict[int, int]] = {}
        """Per (vehicle, link): each stream's period [physics steps]."""
        self._groups: dict[int, dict[tuple[int, str], list[int]]] = {}
        """The same by period: what is due at every multiple of it."""
        self.profile = swarm.profile
        self._product_periods = {hz: 1.0 / (hz * swarm.dt_s) for hz in
                                 {t.product_hz for t in self.profile.timing.values() if t.product_hz is not None}}
        """Each estimator product rate of the profile -> its period [physics steps, maybe fractional]."""
        self._products: dict[float, tuple[int, object]] = {}
        """Each product rate -> (its newest product's step, the swarm's sensor rows then)."""
        self._pending: dict[int, list[tuple[int, int, object]]] = {i: [] for i in range(swarm.n)}
        """Per vehicle: the companion link's messages made and not sent yet (send step, id, message)."""
        self._stream_state: dict[tuple[int, int], list[int]] = {}
        """Per (vehicle, message id) of a timed stream: [product last sent, last send step]."""
        self._jitter = {code: self.profile.jitter_steps(swarm.seed, code, swarm.dt_s) for code in self.profile.timing}
        self._key_ids: dict[int, frozenset[int]] = {}
        """Per vehicle: the messages whose stamps lockstep awaits answers to."""
        self._last_keyed: dict[int, bytes] = {}
        """Per vehicle: the last datagram awaited (sent again when its answer is overdue)."""
        self.sent = Counter()
        self.max_lag_s = 0.0
        self.overruns = 0
        self.wall_start = 0.0
        self._wall_sim0 = 0.0
        self.wall_elapsed = 0.0
        self.exceptions = 0
        self._bugs_told: set[tuple[str, str]] = set()
        self._lockstep_running = False
        self._advance_pending = False
        self._wall_start_mono = time.monotonic()
        self._report = (self._wall_start_mono, 0.0)  # lockstep: (wall, simulated time) of the last RTF report
        self._join_wall_s = 0.0  # lockstep: wall time until every companion answered [s]
        self._join_mono = 0.0  # lockstep: the monotonic clock then [s]
        self._join_sim_s = 0.0

    # -- sockets ----------------------------------------------------------------------------

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        for i, fc in enumerate(self.swarm.fcs):
            links = {}
            for k, name in enumerate(LINKS):
                port = 0 if self.base_port == 0 else self.base_port + 2 * i + k
                link = Link(i, name, self.bind_host, port, codec=new_codec(fc.sysid, COMP_AUTOPILOT),
                            parser=new_codec(fc.sysid, COMP_AUTOPILOT))
                sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                try:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER_BYTES)
                    sock.bind((self.bind_host, port))
                except OSError as exc:
                    sock.close()
                    self.close()
                    raise LinkOpenError(f"cannot open UDP {self.bind_host}:{port} for vehicle {fc.sysid} "
                                  f"({name} link): {exc.strerror}") from None
                sock.setblocking(False)
                link.sock = sock
                link.port = sock.getsockname()[1]
                loop.add_reader(sock.fileno(), self._drain, link)
                links[name] = link
            self.links.append(links)
        for i in range(self.swarm.n):
            self._schedule_vehicle(i)

    def close(self) -> None:
        loop = asyncio.get_event_loop()
        for links in self.links:
            for link in links.values():
                if link.sock is not None:
                    loop.remove_reader(link.sock.fileno())
                    link.sock.close()
                    link.sock = None

    def manifest(self) -> dict:
        home = self.swarm.home
        vehicles = []
        for i, fc in enumerate(self.swarm.fcs):
            vehicles.append({
                "sysid": fc.sysid,
                "start_ned_m": [float(v) + 0.0 for v in frames.flip(fc.start_m)],
                "links": {name: link.urls() for name, link in self.links[i].items()},
            })
        return {"home": {"lat_deg": home.lat_deg, "lon_deg": home.lon_deg, "alt_m": home.alt_m},
                "frame": "local NED, origin at home", "speedup": self.speedup,
                "clock": {"lockstep": self.lockstep is not None, "boot_unix_s": self.boot_unix_s},
                "physics_hz": self.swarm.physics_hz, "pid": os.getpid(), "vehicles": vehicles}

    # -- incoming ---------------------------------------------------------------------------

    def _drain(self, link: Link) -> None:
        for _ in range(MAX_DATAGRAMS_PER_WAKEUP):
            try:
                data, addr = link.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                link.send_errors += 1  # e.g. ICMP port unreachable from a peer that left
                return
            self.on_datagram(link, data, addr)

    def on_datagram(self, link: Link, data: bytes, addr) -> None:
        now_wall = time.monotonic()
        link.datagrams_rx += 1
        if addr not in link.peers and len(link.peers) >= MAX_PEERS_PER_LINK:
            link.live_peers(now_wall)
            if len(link.peers) >= MAX_PEERS_PER_LINK:
                self.swarm.fcs[link.vehicle].counters["drop_too_many_peers"] += 1
                return
        link.peers[addr] = now_wall
        fc = self.swarm.fcs[link.vehicle]
        if self.lockstep is None and self.wall_start:  # (the autopilot's clock on arrival: the wall's)
            fc.rx_time_s = max(self.swarm.time_s, self._wall_sim0 + (now_wall - self.wall_start) * self.speedup)
        try:
            reset_parser(link.parser)
            msgs = link.parser.parse_buffer(data) or []
        except Exception:  # a parser that chokes on garbage loses the datagram, never the vehicle
            fc.counters["drop_unparseable_datagram"] += 1
            return
        # (an actuator command needs no sensor snapshot: most datagrams in lockstep are those)
        n_actuator = sum(m.get_msgId() == ACTUATOR_MSG_ID for m in msgs)
        snap = None if n_actuator == len(msgs) else self.swarm.snapshot(link.vehicle)
        replies = []
        for msg in msgs:
            try:
                replies.extend(fc.handle(msg, link.name, self.swarm.time_s, snap))
            except Exception:  # a bug: this vehicle loses the message, no vehicle its flight
                self._bug(fc, f"handling {msg.get_type()}", "drop_handler_error")
        if fc.airframe_changed:
            self.swarm.apply_airframe(link.vehicle)
        if self.lockstep is not None and link.name == "companion":
            said = self.lockstep.answered(link.vehicle, fc.answered_us, now_wall, command=n_actuator > 0)
            if said == "started":
                self.say("lockstep: every vehicle's companion answers; the clock runs")
                self._join_mono, self._join_sim_s = time.monotonic(), self.swarm.time_s
                self._join_wall_s = self._join_mono - self._wall_start_mono
                self._report = (time.monotonic(), self.swarm.time_s)
            elif said == "back":
                self.say(f"lockstep: vehicle {fc.sysid}'s companion answers again; it is back in lockstep")
            advance = self._lockstep_running and not self.lockstep.blocked
        else:
            advance = False
        if fc.rates_changed:
            fc.rates_changed = False
            self._schedule_vehicle(link.vehicle)
        for out in replies:
            self._send(link.vehicle, out.msg, out.link)
        self._flush_outbox(link.vehicle)
        if advance:
            self._advance()

    def _bug(self, fc, doing: str, counter: str) -> None:
        """An exception where none should be: counted (``handler_exceptions``, and the vehicle's
        ``counter``), its traceback said once per place and kind (the first 20); the other vehicles
        fly on."""
        import traceback

        self.exceptions += 1
        fc.counters[counter] += 1
        told = (doing, traceback.format_exc(limit=0))
        if told not in self._bugs_told and len(self._bugs_told) < 20:
            self._bugs_told.add(told)
            self.say(f"internal error (a bug) in vehicle {fc.sysid} {doing}; the message is dropped:\n"
                     f"{traceback.format_exc()}", True)

    # -- outgoing ---------------------------------------------------------------------------

    def _flush_outbox(self, i: int) -> None:
        fc = self.swarm.fcs[i]
        while fc.outbox:
            out = fc.outbox.pop(0)
            self._send(i, out.msg, out.link)

    def _send(self, i: int, msg, link_name: str | None) -> None:
        names = LINKS if link_name is None else (link_name,)
        now_wall = time.monotonic()
        for name in names:
            link = self.links[i][name]
            peers = link.live_peers(now_wall)
            if not peers:
                continue
            try:
                frame = msg.pack(link.codec)
            except Exception:  # a bug (a value out of its field's range): this message lost, not the vehicles
                self._bug(self.swarm.fcs[i], f"packing {msg.get_type()}", "drop_unpackable")
                continue
            self._sendto(link, frame, peers)

    def _sendto(self, link: Link, data: bytes, peers) -> None:
        if link.sock is None:
            return
        for addr in peers:
            try:
                link.sock.sendto(data, addr)
                link.datagrams_tx += 1
            except OSError:  # a full send buffer or an unreachable peer loses this datagram only
                link.send_errors += 1

    def _schedule_vehicle(self, i: int) -> None:
        """(Re)build vehicle i's stream schedule from its rate parameters. A stream of period P
        (whole physics steps) is due at every step that is a multiple of P, so the streams of every
        vehicle with one rate leave at the same steps, together."""
        fc = self.swarm.fcs[i]
        dt = self.swarm.dt_s
        for name in LINKS:
            periods = {}
            for msg_id in SCHEDULED:
                rate = fc.stream_rate_hz(name, msg_id)
                if rate > 0:
                    periods[msg_id] = max(1, int(round(1.0 / (rate * dt))))
            self._streams[(i, name)] = periods
        attitude = [m for m in ATTITUDE_IDS if fc.stream_rate_hz("companion", m) > 0]
        self._key_ids[i] = frozenset(attitude[:1]) if attitude else HIGH_RATE_IDS
        groups: dict[int, dict[tuple[int, str], list[int]]] = {}
        for key, periods in self._streams.items():
            for msg_id, period in periods.items():
                groups.setdefault(period, {}).setdefault(key, []).append(msg_id)
        self._groups = groups

    def _send_due(self) -> None:
        """Send every stream message due at this step, one datagram per vehicle and link (on the
        companion link, the profile's timed streams are made now and leave when their delay is up)."""
        step = self.swarm.steps
        for hz, period in self._product_periods.items():
            if product_step(step, hz, self.swarm.dt_s) == step:
                self._products[hz] = (step, self.swarm.sensor_rows())
        batches: dict[tuple[int, str], list[int]] | None = None
        for period, entries in self._groups.items():
            if step % period:
                continue
            if batches is None:
                batches = {key: list(ids) for key, ids in entries.items()}
            else:
                for key, ids in entries.items():
                    batches.setdefault(key, []).extend(ids)
        batches = batches or {}
        if self.profile.timing:
            for (i, name), ids in list(batches.items()):
                if name == "companion":
                    batches[(i, name)] = self._make_timed(i, ids, step)
            for i, pending in self._pending.items():
                if pending and pending[0][0] <= step:
                    batches.setdefault((i, "companion"), [])
        if batches:
            now_wall = time.monotonic()
            for (i, name), ids in batches.items():
                self._send_batch(i, name, sorted(ids), now_wall)

    def _make_timed(self, i: int, ids: list[int], step: int) -> list[int]:
        """Vehicle i's timed streams due now, made from the estimator's newest product and held
        until they leave (``profiles.py``); returns the other ids, sent now."""
        rest = []
        dt = self.swarm.dt_s
        for msg_id in ids:
            code = STREAM_CODE.get(msg_id)
            timing = self.profile.timing.get(code)
            if timing is None:
                rest.append(msg_id)
                continue
            state = self._stream_state.setdefault((i, msg_id), [-1, -1])
            product = product_step(step, timing.product_hz, dt)
            if timing.new_only and product == state[0]:
                continue  # (nothing new since the last one: not sent)
            rows = self.swarm.sensor_rows() if product == step else self._products.get(timing.product_hz, (0, None))[1]
            rows = self.swarm.sensor_rows() if rows is None else rows  # (the first step: no product kept yet)
            delays = self._jitter[code]
            send = step + (0 if delays is None else int(delays[step % JITTER_TABLE]))
            send = max(send, state[1])  # (a stream leaves in order)
            state[:] = [product, send]
            msg = self._build(i, msg_id, product * dt, rows)
            if timing.stamp == "send":
                if hasattr(msg, "time_boot_ms"):
                    msg.time_boot_ms = _ms(send * dt)
                else:
                    msg.time_usec = _us(send * dt)
            pending = self._pending[i]
            pending.append((send, msg_id, msg))
            pending.sort(key=lambda e: e[0])
        return rest

    def _build(self, i: int, msg_id: int, t_s: float, rows):
        # (stamped on the autopilot's clock; every vehicle's runs at the same rate: one batch for all)
        args = batch_args(msg_id, self.swarm.fcs[i].clock_s(t_s), rows)
        if args is not None:
            return CONSTRUCTORS[msg_id](*args[i])
        snap = self.swarm.snapshot(i) if rows is self.swarm.sensor_rows() else rows.row(i)
        return self.swarm.fcs[i].build(msg_id, t_s, snap)

    def _send_batch(self, i: int, name: str, ids, now_wall: float | None = None) -> None:
        """Messages ``ids`` of vehicle i as they are now (and on the companion link, the timed ones
        whose time has come), in one datagram on link ``name``."""
        now_wall = time.monotonic() if now_wall is None else now_wall
        link = self.links[i][name]
        msgs = []
        if name == "companion" and self._pending[i]:
            pending, step = self._pending[i], self.swarm.steps
            k = next((n for n, e in enumerate(pending) if e[0] > step), len(pending))
            msgs, self._pending[i] = [(msg_id, msg) for _, msg_id, msg in pending[:k]], pending[k:]
        peers = link.live_peers(now_wall)
        awaited = self.lockstep is not None and name == "companion"
        if not peers and not awaited:
            return
        # (in lockstep a companion's state is awaited even with no peer to send it to: one silent
        # for PEER_TIMEOUT_S of wall time, or one that a stall of this process made look so, gets
        # it again when it speaks (``_offer``), and the clock stands meanwhile, never steps without it)
        now_s = self.swarm.time_s
        rows = self.swarm.sensor_rows()
        msgs += [(msg_id, self._build(i, msg_id, now_s, rows)) for msg_id in ids]
        msgs.sort(key=lambda e: e[0])
        data = bytearray()
        key_ids, key_us = self._key_ids.get(i, HIGH_RATE_IDS), -1
        for msg_id, msg in msgs:
            try:
                data += msg.pack(link.codec)
            except Exception:  # a bug (a value out of its field's range): this message lost, not the vehicles
                self._bug(self.swarm.fcs[i], f"packing {msg.get_type()}", "drop_unpackable")
                continue
            self.sent[msg_id] += 1
            if msg_id in key_ids:
                key_us = max(key_us, msg.time_boot_ms * 1000 if hasattr(msg, "time_boot_ms") else msg.time_usec)
        self._sendto(link, bytes(data), peers)
        if awaited and key_us >= 0:
            self._last_keyed[i] = bytes(data)
            self.lockstep.sent(i, key_us, now_wall)

    def _offer(self, i: int) -> None:
        """Lockstep: vehicle i's state to its companion again (it answers it): the datagram it has
        not answered, or before the clock runs, the high-rate state now."""
        if self.lockstep.started and i in self._last_keyed:
            self._sendto(self.links[i]["companion"], self._last_keyed[i], self.links[i]["companion"].live_peers(time.monotonic()))
            return
        fc = self.swarm.fcs[i]
        ids = [m for m in HIGH_RATE_IDS if fc.stream_rate_hz("companion", m) > 0]
        # (with a heartbeat while the clock stands: a client waits for one before it starts, and an
        # autopilot that streams nothing until asked, as ArduPilot, has nothing else to offer)
        heartbeat = [] if self.lockstep.started else [mavlink.MAVLINK_MSG_ID_HEARTBEAT]
        if ids or heartbeat:
            self._send_batch(i, "companion", heartbeat + sorted(ids))

    # -- the loop ---------------------------------------------------------------------------

    async def run(self, stop: asyncio.Event, duration_s: float | None = None) -> None:
        """Fly until ``stop`` (or ``duration_s`` of simulated time)."""
        loop = asyncio.get_running_loop()
        self.swarm.step()  # warm up (compiled kernels load on first use) before the clock starts
        self._send_due()
        # The ~10^5 long-lived objects of the imports would make every full garbage collection a
        # pause of tens of milliseconds (hundreds on a busy machine) in which no telemetry leaves:
        # collect once now and keep them out of later collections.
        gc.collect()
        gc.freeze()
        self.wall_start = loop.time()
        self._wall_sim0 = self.swarm.time_s
        self.end_s = math.inf if duration_s is None else self.swarm.time_s + duration_s
        if self.lockstep is None:  # SYSTEM_TIME = the wall clock at start, then sim time
            self.boot_unix_s = math.floor((time.time() - self.swarm.time_s) * 1000.0) / 1000.0
        for fc in self.swarm.fcs:
            fc.boot_unix_s = self.boot_unix_s
        try:
            if self.lockstep is None:
                await self._run_wall_clock(stop, loop)
            else:
                await self._run_lockstep(stop, loop)
        finally:
            self.wall_elapsed = loop.time() - self.wall_start

    def _step(self, to_next_event: bool = False) -> None:
        """One physics step (or, with ``to_next_event``, as many as there are to the next step at
        which a control period starts or telemetry is due: nothing can happen in between in
        lockstep), the telemetry it makes due, and what the autopilots have to say."""
        n = 1
        if to_next_event:
            step = self.swarm.steps
            n = min([self.swarm.steps_to_control()] + [p - step % p for p in self._groups]
                    + [math.floor((math.floor(step / p + 1e-9) + 1) * p + 1e-9) - step for p in self._product_periods.values()]
                    + [pending[0][0] - step for pending in self._pending.values() if pending])
            if math.isfinite(self.end_s):
                n = max(1, min(n, int(math.ceil((self.end_s - self.swarm.time_s) / self.swarm.dt_s - 1e-9))))
        self.swarm.step(n)
        self._send_due()
        for i, fc in enumerate(self.swarm.fcs):
            if fc.outbox:
                self._flush_outbox(i)

    async def _run_wall_clock(self, stop: asyncio.Event, loop) -> None:
        rate = self.swarm.physics_hz * self.speedup  # physics steps per wall second
        start_steps = self.swarm.steps
        while not stop.is_set() and self.swarm.time_s < self.end_s:
            now = loop.time()
            target = start_steps + int((now - self.wall_start) * rate)
            behind = target - self.swarm.steps
            if behind > 0:
                lag = behind / rate
                self.max_lag_s = max(self.max_lag_s, lag)
                if behind > MAX_BURST_STEPS:
                    self.overruns += 1
                for _ in range(min(behind, MAX_BURST_STEPS)):
                    self._step()
            next_wall = self.wall_start + (self.swarm.steps - start_steps + 1) / rate
            # asyncio's timers have millisecond resolution (epoll): wait coarsely while there is
            # time, serving I/O, then sleep the last stretch precisely so telemetry leaves on time.
            wait = next_wall - loop.time()
            if wait > FINE_WAIT_S:
                await asyncio.sleep(wait - FINE_WAIT_S)
            await asyncio.sleep(0)
            wait = next_wall - loop.time()
            if wait > 0:
                time.sleep(wait)

    async def _run_lockstep(self, stop: asyncio.Event, loop) -> None:
        """The plant steps in the callbacks that take the companions' answers (``_advance``); this
        coroutine only watches: the states to offer again, the companions that died, the pace."""
        ls = self.lockstep
        self._wall_start_mono = time.monotonic()
        self._report = (time.monotonic(), self.swarm.time_s)
        told_missing = time.monotonic()
        standing = (time.monotonic(), self.swarm.steps)  # (wall time, step) the clock last moved
        stalls = Stalls(period_s=LOCKSTEP_POLL_S)  # (the SITL's own: not counted as a companion's silence)
        self._lockstep_running = True
        try:
            self._advance()
            while not stop.is_set() and self.swarm.time_s < self.end_s:
                await asyncio.sleep(LOCKSTEP_POLL_S)
                now = time.monotonic()
                if not ls.started:
                    for i in ls.missing():
                        self._offer(i)
                    if now - told_missing > 5.0:
                        told_missing = now
                        self.say("lockstep: the clock waits for the companions of vehicles "
                                 + ", ".join(str(self.swarm.fcs[i].sysid) for i in ls.missing()))
                if self.swarm.steps != standing[1]:
                    standing = (now, self.swarm.steps)
                elif ls.started and now - standing[0] >= STANDING_HEARTBEAT_S:
                    standing = (now, self.swarm.steps)
                    for i in range(self.swarm.n):
                        for name in LINKS:
                            self._send_batch(i, name, [mavlink.MAVLINK_MSG_ID_HEARTBEAT])
                stalls.look(now)
                offer, dropped = ls.overdue(now, self.swarm.time_s, stalls)
                for i in offer:
                    self._offer(i)
                for i in dropped:
                    self.say(f"lockstep: vehicle {self.swarm.fcs[i].sysid}'s companion has not answered for "
                             f"{ls.options.timeout_s:g} s of wall time: it has died or hung; the vehicle flies on "
                             f"without it (its failsafe counts on simulated time) until it answers again", warning=True)
                if dropped:
                    self._advance()
                if ls.started and now - self._report[0] >= REPORT_EVERY_S:
                    rtf = (self.swarm.time_s - self._report[1]) / (now - self._report[0])
                    self.say(f"lockstep: t = {self.swarm.time_s:.1f} s simulated, real-time factor {rtf:.2f}")
                    self._report = (now, self.swarm.time_s)
        finally:
            self._lockstep_running = False

    def _advance(self, resumed: bool = False) -> None:
        """Lockstep: step while nothing is awaited (and the run is not over); a long run of steps
        with nobody to wait for (every companion dropped) yields to the loop now and then, and
        goes on from there (one such run at a time)."""
        if resumed:
            self._advance_pending = False
        elif self._advance_pending:
            return  # (a run of steps goes on at the loop's next turn)
        ls = self.lockstep
        for _ in range(MAX_BURST_STEPS):
            if ls.blocked or self.swarm.time_s >= self.end_s or not self._lockstep_running:
                return
            ahead_s = self._ahead_of_max_rtf()
            if ahead_s > 0.0:  # (--max-rtf: wait for the wall clock)
                self._advance_pending = True
                asyncio.get_running_loop().call_later(ahead_s / ls.options.max_rtf, self._advance, True)
                return
            self._step(to_next_event=True)
        self._advance_pending = True
        asyncio.get_running_loop().call_soon(self._advance, True)

    def _ahead_of_max_rtf(self) -> float:
        """Simulated seconds the clock is ahead of the wall times ``max_rtf`` (counted from the
        moment every companion answered; 0 when it is not, or with no limit)."""
        ls = self.lockstep
        if not (ls.started and math.isfinite(ls.options.max_rtf)):
            return 0.0
        wall0, sim0 = self._join_mono, self._join_sim_s
        return max(0.0, self.swarm.time_s - sim0 - (time.monotonic() - wall0) * ls.options.max_rtf)

    def stats(self) -> dict:
        sim = self.swarm.time_s
        vehicles = []
        for i, fc in enumerate(self.swarm.fcs):
            vehicles.append({
                "sysid": fc.sysid,
                "counters": dict(sorted(fc.counters.items())),
                "drops": fc.drops,
                "datagrams_rx": {n: lk.datagrams_rx for n, lk in self.links[i].items()},
                "datagrams_tx": {n: lk.datagrams_tx for n, lk in self.links[i].items()},
                "armed": fc.armed, "mode": fc.mode.name,
            })
            if self.lockstep is not None:
                vehicles[-1]["lockstep_waited_wall_s"] = round(self.lockstep.waited_wall_s[i], 3)
        out = {
            "sim_time_s": sim,
            "wall_time_s": self.wall_elapsed,
            "speedup_requested": self.speedup,
            "speedup_achieved": sim / self.wall_elapsed if self.wall_elapsed > 0 else None,
            "max_lag_s": self.max_lag_s,
            "overruns": self.overruns,
            "handler_exceptions": self.exceptions,
            "messages_sent": {mavlink.mavlink_map[k].msgname if k in mavlink.mavlink_map else str(k): v
                              for k, v in sorted(self.sent.items())},
            "vehicles": vehicles,
        }
        if self.lockstep is not None:
            ls = self.lockstep
            clock_wall = self.wall_elapsed - self._join_wall_s
            out["lockstep"] = {
                "started": ls.started,
                "join_wall_s": round(self._join_wall_s, 3),
                "real_time_factor": (sim - self._join_sim_s) / clock_wall if ls.started and clock_wall > 0 else None,
                "left": [{"sysid": self.swarm.fcs[i].sysid, "sim_time_s": t} for i, t in ls.left],
            }
        return out
