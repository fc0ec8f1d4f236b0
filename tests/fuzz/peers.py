"""The companion's MAVLink peers in the fuzzers, on real UDP sockets of their own on loopback:

- ``Station``: a ground station on the companion's ground-station port;
- ``FakeFC``: a flight controller of the test's own (system ``sysid``, component 1), enough of one for
  a companion to set up and stay set up: heartbeat, parameters, command acks, SYSTEM_TIME, and
  ATTITUDE with LOCAL_POSITION_NED in one datagram at ``rate_hz``, as triswarm's SITL sends them.

Both read their socket in a thread of their own. Both can ``probe`` the companion with a
PARAM_SET of its component 191 (the companion answers one from any link) and wait for the
answer: the fuzzers send a batch of inputs, then a probe, and go on when it is answered, so that no
more than a batch waits in the companion's socket (the kernel would drop what does not fit, and
the counts would no longer add up) and a companion that stops answering is seen at once.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from collections import Counter

from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink as M, new_codec, reset_parser

PARAMS = {"MOT_MAX_RPM": 8000.0, "SERVO_LIM_DEG": 90.0, "SIM_LOCKSTEP": 0.0}
PROBE_PARAM = "NB_WAIT_MS"  # a parameter of the companion's that nothing flies on while the fuzz runs (no plan flying)


class Peer:
    """A UDP socket bound on loopback (port 0: the kernel's choice), read in a thread."""

    def __init__(self, sysid: int, compid: int, remote: tuple[str, int] | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self.remote = remote
        self.codec = new_codec(sysid, compid)
        self.reader = new_codec(sysid, compid)
        self.heard: Counter[str] = Counter()
        """What came from the companion's side, by message type."""
        self.probe_value: float | None = None
        """The value of the newest PARAM_VALUE of PROBE_PARAM from component 191."""
        self.probe_codec = None
        """What probes are packed with (e.g. a signing codec), if not ``codec``."""
        self._probes = 0
        self.tap = None
        """Called with every datagram sent (the fuzzers' oracle sees what the companion gets)."""
        self._tap_lock = threading.Lock()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def send(self, data: bytes) -> bool:
        """Send one datagram to the companion (once it is known); False if it could not be sent."""
        if self.remote is None:
            return False
        for _ in range(100):
            try:
                self.sock.sendto(data, self.remote)
            except BlockingIOError:  # (the send buffer is full for a moment)
                time.sleep(0.001)
                continue
            except OSError:  # e.g. ICMP port unreachable from a companion not up yet
                return False
            if self.tap is not None:
                with self._tap_lock:
                    self.tap(data)
            return True
        return False

    def send_msg(self, msg) -> None:
        self.send(msg.pack(self.codec))

    def _run(self) -> None:
        while not self._stop.is_set():
            timeout = self.tick()
            ready, _, _ = select.select([self.sock], [], [], timeout)
            if not ready:
                continue
            for _ in range(256):
                try:
                    data, addr = self.sock.recvfrom(65536)
                except OSError:  # (nothing more waiting, or an ICMP error from the other side)
                    break
                self.remote = self.remote or addr
                reset_parser(self.reader)
                for m in self.reader.parse_buffer(data) or []:
                    t = m.get_type()
                    if t == "BAD_DATA":
                        continue
                    self.heard[t] += 1
                    if t == "PARAM_VALUE" and m.get_srcComponent() == COMP_ONBOARD and m.param_id == PROBE_PARAM:
                        with self._cond:
                            self.probe_value = m.param_value
                            self._cond.notify_all()
                    self.on_message(m)

    def tick(self) -> float:
        """Periodic work; returns how long the reader may wait for the next datagram [s]."""
        return 0.05

    def on_message(self, msg) -> None:
        """A message from the companion's side."""

    def probe(self, target: int, timeout_s: float = 10.0, source: tuple[int, int] | None = None) -> bool:
        """Set companion ``target``'s NB_WAIT_MS to a value of this probe's own and wait for the
        PARAM_VALUE that says so (an answer nothing else sends: the fuzz's own parameter reads and
        lists cannot pass for it); False after ``timeout_s``. Signed with ``probe_codec`` if set."""
        self._probes += 1
        value = (self._probes % 1024) / 256.0  # (in [0, 4), exact in float32)
        codec = new_codec(*source) if source is not None else (self.probe_codec or self.codec)
        with self._cond:
            self.probe_value = None
            self.send(M.MAVLink_param_set_message(target, COMP_ONBOARD, PROBE_PARAM.encode(), value,
                                                  M.MAV_PARAM_TYPE_REAL32).pack(codec))
            return self._cond.wait_for(lambda: self.probe_value == value, timeout_s)


class Station(Peer):
    """A ground station (system 255, component 190) on the companion's ground-station port."""

    def __init__(self, port: int, sysid: int = 255, compid: int = 190) -> None:
        super().__init__(sysid, compid, ("127.0.0.1", port))

    def heartbeat_answered(self, target: int, timeout_s: float = 10.0) -> bool:
        """A heartbeat, then the companion's own (it sends one a second): whether one came."""
        before = self.heard["HEARTBEAT"]
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.send_msg(M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))
            time.sleep(0.2)
            if self.heard["HEARTBEAT"] > before:
                return True
        return False


class FakeFC(Peer):
    """A flight controller of the test's own: the companion's ``--fc udpout:127.0.0.1:<port>``."""

    def __init__(self, sysid: int = 1, rate_hz: float = 100.0) -> None:
        self.sysid = sysid
        self.period_s = 1.0 / rate_hz
        self.t0 = time.monotonic()
        self.unix0 = time.time()
        self._next = self.t0
        self._next_slow = self.t0
        self.set_up = threading.Event()
        """The companion asked for SYSTEM_TIME's rate: the last request of its set-up (then it
        measures the telemetry's rates for half a second of this clock)."""
        super().__init__(sysid, 1)

    def boot_ms(self) -> int:
        return int((time.monotonic() - self.t0) * 1000)

    def telemetry(self, boot_ms: int | None = None) -> list:
        """ATTITUDE and LOCAL_POSITION_NED of one instant (level, still, 2 m up)."""
        ms = self.boot_ms() if boot_ms is None else boot_ms
        return [M.MAVLink_attitude_message(ms, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0),
                M.MAVLink_local_position_ned_message(ms, 1.0, -1.0, -2.0, 0.0, 0.0, 0.0)]

    def system_time(self):
        ms = self.boot_ms()
        return M.MAVLink_system_time_message(int((self.unix0 + ms / 1000.0) * 1e6), ms)

    def tick(self) -> float:
        if self.remote is None:
            return 0.05
        now = time.monotonic()
        if now >= self._next_slow:
            self._next_slow = now + 1.0
            self.send_msg(M.MAVLink_heartbeat_message(M.MAV_TYPE_GENERIC, M.MAV_AUTOPILOT_GENERIC,
                                                      M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 2, M.MAV_STATE_STANDBY, 3))
            self.send_msg(self.system_time())
            self.send_msg(M.MAVLink_extended_sys_state_message(0, M.MAV_LANDED_STATE_ON_GROUND))
        if now >= self._next:
            self._next = max(self._next + self.period_s, now)
            self.send(b"".join(m.pack(self.codec) for m in self.telemetry()))
        return max(0.0, min(self._next, self._next_slow) - time.monotonic())

    def on_message(self, m) -> None:
        if m.get_srcSystem() != self.sysid or m.get_srcComponent() != COMP_ONBOARD:
            return
        t = m.get_type()
        if t == "PARAM_REQUEST_READ" and m.target_component == 1 and m.param_id in PARAMS:
            self.send_msg(M.MAVLink_param_value_message(m.param_id.encode(), PARAMS[m.param_id],
                                                        M.MAV_PARAM_TYPE_REAL32, len(PARAMS),
                                                        list(PARAMS).index(m.param_id)))
        elif t == "COMMAND_LONG" and m.target_component == 1:
            self.send_msg(M.MAVLink_command_ack_message(m.command, M.MAV_RESULT_ACCEPTED, 0, 0, self.sysid, COMP_ONBOARD))
            if m.command == M.MAV_CMD_REQUEST_MESSAGE and int(m.param1) == M.MAVLINK_MSG_ID_SYSTEM_TIME:
                self.send_msg(self.system_time())
            if m.command == M.MAV_CMD_SET_MESSAGE_INTERVAL and int(m.param1) == M.MAVLINK_MSG_ID_SYSTEM_TIME:
                self.set_up.set()
