"""MAVLink links of a process (a pymavlink connection string each) and routing between them.

pymavlink provides the transports (``udpin:``, ``udpout:``, ``tcp:``, serial ports); frames are
parsed and packed by the project's own codec (``protocol.mavlink``, MAVLink 2), so nothing depends on
pymavlink's environment-chosen dialect. Links are read from the asyncio loop (``add_reader``). A link
whose codec has signing set up (``protocol.mavlink.setup_signing``) counts the frames it refuses in
its counters (``refused_*``), not as bad data. On UDP links the datagrams the kernel dropped (its
receive buffer full: a flood faster than the process reads) are counted too (``drop_kernel``).

What a link drops, it counts (``counters``): ``drop_bad_data`` (each piece the parser makes bad
data of: garbage, a wrong checksum, an unknown message), ``drop_partial_frame`` (a datagram that
ends inside a frame), ``drop_empty`` (an empty datagram), ``drop_unparseable`` (the parser gave up
on a datagram); ``rx`` counts the messages taken.

On UDP links every datagram carries the kernel's receive time (SO_TIMESTAMPNS), so the time a
sample "arrived" includes the wait before the process got to read it; other transports fall back
to the time of the read. All receive times are Unix time [s].

A serial port (pymavlink's ``DEVICE,BAUD``, opened through pyserial) is a byte stream: frames are
parsed across reads. Nothing on it blocks the loop: a frame the port's output buffer cannot take
whole is dropped and counted (``drop_tx_full``; the line is over its budget). A port that fails
(a USB flight controller unplugged: readable, but no data; or a read or write error) is closed
once, said once through ``on_event``, and opened again every REOPEN_EVERY_S until it is back.

A TCP link (``tcp:HOST:PORT``: a flight controller's own port, as ArduPilot's SITL offers) is a
byte stream too, read and written on its socket without blocking (pymavlink's own would wait and
retry on the loop): a frame the socket cannot take whole waits, and beyond TCP_TX_QUEUE_BYTES
waiting a frame is dropped and counted (``drop_tx_full``). The peer closing the connection (a
flight controller that restarted) is a link lost, as a serial port's: connected again every
REOPEN_EVERY_S (one try each) until it is back.
"""

from __future__ import annotations

import asyncio
import errno
import os
import socket
import struct
import time
from collections import Counter
from collections.abc import Callable

from pymavlink import mavutil

from triswarm.protocol.mavlink import SIGNATURE_REFUSED, new_codec, reset_parser

MAX_READS_PER_WAKEUP = 64
CLIENT_TIMEOUT_S = 10.0
"""A ``udpin`` link sends to every address that has spoken to it in this long (ground stations send
a heartbeat every second; MAVLink calls a link lost after 5 s without one); when all are silent,
to one of them. Without it every ground-station command line, on a new port each time, would
stay a destination for the rest of the flight."""
MAX_DATAGRAM = 65535
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux's value; Python does not export it
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)  # (Linux's): datagrams the kernel dropped, its receive buffer full
_TIMESPEC = struct.Struct("@qq")
_DROPS = struct.Struct("@I")
_ANCILLARY = socket.CMSG_SPACE(_TIMESPEC.size) + socket.CMSG_SPACE(_DROPS.size)
REOPEN_EVERY_S = 1.0
"""A serial port that failed is tried again this often [s, wall]."""
TCP_TX_QUEUE_BYTES = 65536
"""Bytes a TCP link keeps for a socket that cannot take them yet; a frame beyond is dropped."""
SERIAL_TX_QUEUE_BYTES = 4096
"""A frame that would queue more than this on a serial port is dropped (at 921600 baud, 44 ms of
line; the loop sends a command every 5 ms)."""


class MavLink:
    """One MAVLink link. ``on_receive(link, messages, t_rx_unix_s)`` gets every parsed batch."""

    routes = True
    """Frames are routed through it (between it and the process's other links)."""

    def __init__(self, name: str, url: str, sysid: int, compid: int, client_timeout_s: float = CLIENT_TIMEOUT_S,
                 after_read: Callable[[], None] | None = None,
                 on_event: Callable[[str], None] = lambda text: None) -> None:
        self.name, self.url = name, url
        self.client_timeout_s = client_timeout_s
        self.codec = new_codec(sysid, compid)
        self.conn = None
        self.counters: Counter[str] = Counter()
        self._on_receive: Callable | None = None
        self.peer: tuple | None = None
        """The address the batch being handled came from (UDP; None on other transports)."""
        self.after_read = after_read
        """Called once everything waiting has been read (e.g. to act on the newest sample only)."""
        self.on_event = on_event
        """Told, in one line, that a serial port failed and that it is back."""
        self._datagrams = False
        self._serial = False
        self._tcp = False
        self._tx_pending = b""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reopen: asyncio.TimerHandle | None = None
        self._down = False
        """Said lost, and no frame has come since."""

    @property
    def up(self) -> bool:
        return self.conn is not None

    def open(self, loop: asyncio.AbstractEventLoop, on_receive: Callable) -> None:
        self._loop, self._on_receive = loop, on_receive
        self._connect()

    def _connect(self) -> None:
        try:
            if self.url.startswith("tcp:"):
                self.conn = TcpConnection.open(self.url)
            else:
                self.conn = mavutil.mavlink_connection(self.url, source_system=self.codec.srcSystem,
                                                       source_component=self.codec.srcComponent,
                                                       udp_timeout=self.client_timeout_s)
        except (OSError, ValueError) as exc:  # (pyserial's SerialException is an OSError)
            raise OSError(f"cannot open MAVLink link {self.name} at {self.url}: {exc}") from None
        self._datagrams = isinstance(self.conn, mavutil.mavudp)
        self._serial = isinstance(self.conn, mavutil.mavserial)
        self._tcp = isinstance(self.conn, TcpConnection)
        self._tx_pending = b""
        if self._datagrams:
            for option in (SO_TIMESTAMPNS, SO_RXQ_OVFL):
                try:
                    self.conn.port.setsockopt(socket.SOL_SOCKET, option, 1)
                except OSError:  # not Linux: receive times are read times, the kernel's drops not counted
                    pass
        self._loop.add_reader(self.conn.fd, self._readable)

    def close(self) -> None:
        if self._reopen is not None:
            self._reopen.cancel()
            self._reopen = None
        if self.conn is not None:
            if self._loop is not None and not self._loop.is_closed():  # (the loop it was read from, not a new one)
                try:
                    self._loop.remove_reader(self.conn.fd)
                except (RuntimeError, ValueError):
                    pass
            self.conn.close()
            self.conn = None

    def _readable(self) -> None:
        try:
            self._read_all()
        finally:
            if self.after_read is not None:
                self.after_read()

    def _read_all(self) -> None:
        for _ in range(MAX_READS_PER_WAKEUP):
            if self.conn is None:  # (lost while what was read was handled)
                return
            try:
                if self._datagrams:
                    data, t_rx = self._recv_datagram()
                elif self._tcp:
                    data, t_rx = self._recv_stream()
                else:
                    data, t_rx = self.conn.recv(MAX_DATAGRAM), time.time()
            except OSError as exc:
                self.counters["read_errors"] += 1
                if self._serial or self._tcp:
                    self._lost(exc)
                return
            if data is None:  # (nothing more waiting)
                return
            if not data:
                if not self._datagrams:  # (a stream with nothing more waiting)
                    return
                self.counters["drop_empty"] += 1
                continue
            if isinstance(data, str):
                data = data.encode("latin-1")
            if self._datagrams:
                reset_parser(self.codec)  # whole frames per datagram; leftovers are garbage
            try:
                msgs = self.codec.parse_buffer(data) or []
            except Exception:  # garbage loses itself, never the link
                self.counters["drop_unparseable"] += 1
                reset_parser(self.codec)
                continue
            if self._datagrams and self.codec.buf_len() > 0:  # a datagram that ends inside a frame
                self.counters["drop_partial_frame"] += 1
            good = []
            for m in msgs:
                if m.get_type() == "BAD_DATA":
                    if m.reason != SIGNATURE_REFUSED:  # (the signing counted those)
                        self.counters["drop_bad_data"] += 1
                else:
                    good.append(m)
            self.counters["rx"] += len(good)
            if good and self._down:
                self._down = False
                self.on_event(f"{self.name} link {self.url} open again, frames coming")
            if good:
                self._on_receive(self, good, t_rx)

    def _recv_datagram(self) -> tuple[bytes | None, float]:
        """One datagram and the kernel's receive time; None when none is waiting. Keeps pymavlink's
        record of the peers of a ``udpin`` link, which its ``write`` answers."""
        conn = self.conn
        try:
            data, ancillary, flags, addr = conn.port.recvmsg(MAX_DATAGRAM, _ANCILLARY)
        except BlockingIOError:
            return None, 0.0
        t_rx = time.time()
        self.peer = addr
        for level, kind, value in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(value) >= _TIMESPEC.size:
                sec, nsec = _TIMESPEC.unpack_from(value)
                t_rx = sec + 1e-9 * nsec
            elif level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(value) >= _DROPS.size:
                self.counters["drop_kernel"] = _DROPS.unpack_from(value)[0]  # (the socket's count so far)
        if conn.udp_server:
            conn.clients.add(addr)
            conn.clients_last_alive[addr] = t_rx
        return data, t_rx

    def _recv_stream(self) -> tuple[bytes | None, float]:
        """What the TCP socket holds (None: nothing now); ConnectionError when the peer closed it."""
        try:
            data = self.conn.port.recv(MAX_DATAGRAM)
        except (BlockingIOError, InterruptedError):
            return None, 0.0
        if not data:
            raise ConnectionError("closed by the peer")
        return data, time.time()

    def send(self, msg) -> None:
        """Pack a pymavlink message object as this process (sysid/compid of the link) and send it."""
        self.write(msg.pack(self.codec))

    def write(self, data: bytes) -> None:
        """Send raw frames (e.g. forwarded ones, unchanged)."""
        if self.conn is None:
            self.counters["drop_link_down"] += 1
            return
        if self._serial:
            self._write_serial(data)
            return
        if self._tcp:
            self._write_stream(data)
            return
        try:
            self.conn.write(data)
            self.counters["tx"] += 1
        except OSError:
            self.counters["write_errors"] += 1

    def _write_serial(self, data: bytes) -> None:
        """To the port's non-blocking descriptor (pymavlink's write would wait for room, and say a
        failure on stdout): whole frames or none."""
        if self._queued() + len(data) > SERIAL_TX_QUEUE_BYTES:
            self.counters["drop_tx_full"] += 1
            return
        try:
            n = os.write(self.conn.fd, data)
        except BlockingIOError:
            self.counters["drop_tx_full"] += 1
            return
        except OSError as exc:
            if exc.errno == errno.EINTR:
                self.counters["drop_tx_full"] += 1
                return
            self.counters["write_errors"] += 1
            self._lost(exc)
            return
        self.counters["tx"] += 1
        if n < len(data):
            self.counters["tx_short"] += 1

    def _write_stream(self, data: bytes) -> None:
        """To the TCP socket without waiting: what it cannot take now goes first next time."""
        if len(self._tx_pending) + len(data) > TCP_TX_QUEUE_BYTES:
            self.counters["drop_tx_full"] += 1
            data = b""
        pending = self._tx_pending + data
        try:
            n = self.conn.port.send(pending) if pending else 0
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError as exc:
            self.counters["write_errors"] += 1
            self._lost(exc)
            return
        self._tx_pending = pending[n:]
        if data:
            self.counters["tx"] += 1

    def _queued(self) -> int:
        """Bytes waiting in the port's output buffer (0 where the driver does not say)."""
        try:
            return self.conn.port.out_waiting
        except OSError:
            return 0

    def _lost(self, exc: OSError) -> None:
        """The serial port failed (or the TCP connection ended): close it, say so once, try it again
        every REOPEN_EVERY_S."""
        self.counters["lost"] += 1
        conn, self.conn = self.conn, None
        try:
            self._loop.remove_reader(conn.fd)
        except (RuntimeError, ValueError):
            pass
        try:
            conn.close()
        except OSError:
            pass
        reset_parser(self.codec)
        if not self._down:  # (a port that opens again but fails before a frame came is not news)
            self._down = True
            reason = "disconnected: readable, but no data" if "returned no data" in str(exc) else str(exc)
            self.on_event(f"{self.name} link {self.url} lost ({reason}): opening it again every {REOPEN_EVERY_S:g} s")
        self._reopen = self._loop.call_later(REOPEN_EVERY_S, self._try_reopen)

    def _try_reopen(self) -> None:
        self._reopen = None
        try:
            self._connect()
        except OSError:
            self.counters["reopen_failed"] += 1
            self._reopen = self._loop.call_later(REOPEN_EVERY_S, self._try_reopen)
            return
        self.counters["reopened"] += 1


class TcpConnection:
    """A MAVLink link's TCP connection (``tcp:HOST:PORT``), opened in one try without blocking
    for long: the socket (``port``) and its descriptor (``fd``)."""

    CONNECT_TIMEOUT_S = 1.0

    def __init__(self, sock: socket.socket) -> None:
        self.port = sock
        self.fd = sock.fileno()

    @classmethod
    def open(cls, url: str) -> "TcpConnection":
        host, sep, port = url.removeprefix("tcp:").rpartition(":")
        if not sep or not port.isdigit():
            raise ValueError("expected tcp:HOST:PORT")
        sock = socket.create_connection((host, int(port)), timeout=cls.CONNECT_TIMEOUT_S)
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return cls(sock)

    def close(self) -> None:
        self.port.close()


class Router:
    """MAVLink routing (https://mavlink.io/en/guide/routing.html) between this process's links:

    * remember on which link each (system, component) was heard;
    * a message is forwarded to every other link on which its target was heard, or to every other
      link if it is a broadcast (no target, or target system 0), never back where it came from;
      target component 0 means every component of the target system;
    * a message addressed to this component is handled here and not forwarded; a broadcast is both.
    """

    def __init__(self, sysid: int, compid: int) -> None:
        self.sysid, self.compid = sysid, compid
        self.seen: dict[tuple[int, int], MavLink] = {}

    def learn(self, link: MavLink, msg) -> None:
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if src != (self.sysid, self.compid):
            self.seen[src] = link

    def for_me(self, msg) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.sysid) and tc in (0, self.compid)

    def destinations(self, origin: MavLink, msg, links: list[MavLink]) -> list[MavLink]:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        others = [lk for lk in links if lk is not origin]
        if ts == 0:
            return others
        if ts == self.sysid and tc == self.compid:
            return []
        if tc == 0:
            return [lk for lk in others if any(s == ts and link is lk for (s, _), link in self.seen.items())]
        target = self.seen.get((ts, tc))
        return [target] if target is not None and target is not origin else []
