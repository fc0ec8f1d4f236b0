"""A serial line for tests: a pseudo-terminal pair whose slave side a companion opens as its
flight controller's serial port (``--fc /dev/pts/N:921600``), and whose master side is carried, byte
for byte, to and from a SITL vehicle's companion link (UDP). Nothing is decoded on the way: bytes
from the vehicle are written to the line as they come; bytes from the companion are cut into
datagrams at frame ends, found from each MAVLink 2 header's length byte and signed flag, as a
serial-to-UDP router must (the vehicle's link takes whole frames per datagram). Everything carried
is kept, per direction, for the test to read afterwards.
"""

from __future__ import annotations

import os
import selectors
import socket
import threading
import tty
from collections import Counter

STX_V2 = 0xFD
HEADER_AND_CRC = 12  # STX, 9 header bytes, 2 CRC bytes
SIGNATURE = 13
IFLAG_SIGNED = 0x01


def complete_frames(buf: bytes | bytearray) -> tuple[int, int]:
    """(bytes at the start of ``buf`` that are whole MAVLink 2 frames, bytes skipped before a start
    byte). Only the header's length and flags are read."""
    i = skipped = 0
    while i < len(buf):
        if buf[i] != STX_V2:
            i += 1
            skipped += 1
            continue
        if i + 3 > len(buf):
            break
        n = HEADER_AND_CRC + buf[i + 1] + (SIGNATURE if buf[i + 2] & IFLAG_SIGNED else 0)
        if i + n > len(buf):
            break
        i += n
    return i, skipped


class PtyLine:
    """One serial line between a companion (``path``) and the vehicle's UDP link at (host, port)."""

    def __init__(self, host: str, port: int) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # (the slave is held open: the line's settings stay, the master never sees EIO)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect((host, port))
        self.sock.setblocking(False)
        self.to_fc = bytearray()
        """Every byte the companion wrote to the line, in order."""
        self.to_companion = bytearray()
        """Every byte the vehicle sent, in order."""
        self.counters: Counter[str] = Counter()
        self._pending = bytearray()

    def from_line(self) -> None:
        try:
            data = os.read(self.master, 65536)
        except (BlockingIOError, InterruptedError):
            return
        self.to_fc += data
        self._pending += data
        n, skipped = complete_frames(self._pending)
        self.counters["skipped"] += skipped
        if n:
            try:
                self.sock.send(bytes(self._pending[:n]))
            except OSError:
                self.counters["udp_send_errors"] += 1
            del self._pending[:n]

    def from_vehicle(self) -> None:
        try:
            data = self.sock.recv(65536)
        except (BlockingIOError, InterruptedError, ConnectionRefusedError):
            return
        self.to_companion += data
        try:
            n = os.write(self.master, data)
        except BlockingIOError:
            n = 0
        if n < len(data):  # (a companion that stopped reading: its line overflows)
            self.counters["overrun_bytes"] += len(data) - n

    def close(self) -> None:
        for fd in (self.master, self.slave):
            os.close(fd)
        self.sock.close()


class PtyBridge:
    """Lines to vehicles (``{sysid: (host, port)}``) carried by one thread until the context ends."""

    def __init__(self, endpoints: dict[int, tuple[str, int]]) -> None:
        self.lines = {i: PtyLine(host, port) for i, (host, port) in endpoints.items()}
        self._sel = selectors.DefaultSelector()
        for line in self.lines.values():
            self._sel.register(line.master, selectors.EVENT_READ, line.from_line)
            self._sel.register(line.sock, selectors.EVENT_READ, line.from_vehicle)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pty-bridge", daemon=True)

    def __enter__(self) -> "PtyBridge":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._sel.close()
        for line in self.lines.values():
            line.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            for key, _ in self._sel.select(timeout=0.1):
                key.data()
