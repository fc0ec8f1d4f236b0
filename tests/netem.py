"""Network impairment for tests, with what this machine has (no netem qdisc): a network namespace
the test creates, iptables' ``statistic`` match in it for random drops, and a relay of our own that
delays every datagram and every TCP chunk by a fixed time in both directions."""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
import subprocess
import threading
from collections import Counter
from pathlib import Path


SHIPPED_PEER_CONFIG = Path(__file__).resolve().parents[1] / "deploy" / "zenoh" / "companion-peer.json5"


def at_loopback(endpoints: list[str], port: int) -> list[str]:
    """``endpoints`` (their protocols and options) moved to 127.0.0.1:port."""
    out = []
    for endpoint in endpoints:
        protocol, rest = endpoint.split("/", 1)
        options = rest.partition("?")[2]
        out.append(f"{protocol}/127.0.0.1:{port}" + (f"?{options}" if options else ""))
    return out


def shipped_peer_endpoints(port: int) -> list[str]:
    """The endpoints of the shipped peer configuration (deploy/zenoh/companion-peer.json5) at 127.0.0.1:port."""
    import json

    import zenoh

    return at_loopback(json.loads(zenoh.Config.from_file(str(SHIPPED_PEER_CONFIG)).get_json("listen/endpoints")), port)


def need_netns(tools: tuple[str, ...] = ("ip", "iptables"), problem: str | None = None) -> None:
    """Stop a test that needs network namespaces (and ``tools``) on a machine without them
    (``needs.missing``: a failure under CI, a skip elsewhere)."""
    from .needs import missing

    problem = problem or NetNamespace.problem(tools)
    if problem is not None:
        missing(f"{problem} (make test installs iproute2 and iptables when run as root)")


class NetNamespace:
    """``ip netns add NAME`` with loopback up; every process left in it is killed on exit."""

    def __init__(self, name: str) -> None:
        self.name = name

    @staticmethod
    def problem(tools: tuple[str, ...] = ("ip", "iptables")) -> str | None:
        """Why this machine cannot run the namespace tests that need ``tools`` (None if it can)."""
        if os.geteuid() != 0:
            return f"network namespaces{' and iptables' if 'iptables' in tools else ''} need root"
        for tool in tools:
            if shutil.which(tool) is None:
                return f"{tool} is not installed (Debian: apt-get install iproute2 iptables)"
        return None

    def __enter__(self) -> "NetNamespace":
        subprocess.run(["ip", "netns", "add", self.name], check=True, capture_output=True)
        try:
            self.ip("link", "set", "lo", "up")
        except Exception:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc) -> None:
        pids = subprocess.run(["ip", "netns", "pids", self.name], capture_output=True, text=True).stdout.split()
        for pid in pids:
            try:
                os.kill(int(pid), signal.SIGKILL)
            except (ProcessLookupError, ValueError):
                pass
        subprocess.run(["ip", "netns", "del", self.name], capture_output=True)

    def exec_prefix(self) -> list[str]:
        return ["ip", "netns", "exec", self.name]

    def ip(self, *args: str) -> str:
        return subprocess.run(["ip", "-n", self.name, *args], check=True, capture_output=True, text=True).stdout

    def iptables(self, *args: str) -> str:
        return subprocess.run(self.exec_prefix() + ["iptables", "-w", *args], check=True, capture_output=True,
                              text=True).stdout

    def iptables_restore(self, rules: str) -> None:
        """Load the filter table's ``rules`` (iptables-save format, without the table line and
        COMMIT) in one atomic step, on top of what is there."""
        subprocess.run(self.exec_prefix() + ["iptables-restore", "-w", "--noflush"], input=f"*filter\n{rules}COMMIT\n",
                       check=True, capture_output=True, text=True)

    def rule_packets(self, chain: str = "OUTPUT") -> list[int]:
        """Packets matched by each rule of a chain, in order."""
        out = self.iptables("-L", chain, "-v", "-x", "-n")
        return [int(line.split()[0]) for line in out.splitlines()[2:] if line.strip()]


class DelayRelay:
    """Relay ``listen port -> target port`` on 127.0.0.1 for UDP and TCP, every datagram and every
    chunk of a stream delivered ``delay_s`` late (order kept). Runs its own asyncio loop in a
    thread; counts what it relayed."""

    def __init__(self, routes: dict[int, int], delay_s: float) -> None:
        self.routes, self.delay_s = routes, delay_s
        self.counters: Counter[str] = Counter()
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> "DelayRelay":
        self._thread.start()
        if not self._ready.wait(10.0):
            raise RuntimeError("relay did not start")
        return self

    def __exit__(self, *exc) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5)

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        self._loop.run_until_complete(self._start())
        self._ready.set()
        self._loop.run_forever()

    async def _start(self) -> None:
        loop = self._loop
        for listen, target in self.routes.items():
            await loop.create_datagram_endpoint(lambda t=target: _UdpFront(self, t), local_addr=("127.0.0.1", listen))
            await asyncio.start_server(lambda r, w, t=target: self._tcp(r, w, t), "127.0.0.1", listen)

    def later(self, fn, *args) -> None:
        self._loop.call_later(self.delay_s, fn, *args)

    async def _tcp(self, reader, writer, target: int) -> None:
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", target)
        except OSError:
            writer.close()
            return
        await asyncio.gather(self._pump(reader, up_writer, "tcp_forward"), self._pump(up_reader, writer, "tcp_back"),
                             return_exceptions=True)

    async def _pump(self, reader, writer, name: str) -> None:
        try:
            while data := await reader.read(65536):
                self.counters[name] += 1
                self.later(_write, writer, data)
        finally:
            self.later(writer.close)


def _write(writer, data: bytes) -> None:
    if not writer.is_closing():
        writer.write(data)


class _UdpFront(asyncio.DatagramProtocol):
    """The relay's listening UDP socket: one upstream socket per client address."""

    def __init__(self, relay: DelayRelay, target: int) -> None:
        self.relay, self.target = relay, target
        self.upstream: dict[tuple, asyncio.DatagramTransport] = {}

    def connection_made(self, transport) -> None:
        self.transport = transport

    def datagram_received(self, data: bytes, client) -> None:
        self.relay.counters["udp_forward"] += 1
        self.relay.later(self._forward, data, client)

    def _forward(self, data: bytes, client) -> None:
        if client not in self.upstream:
            self.upstream[client] = None  # being opened: datagrams until then are lost, as on a link coming up
            asyncio.ensure_future(self._open(client, data))
        elif (up := self.upstream[client]) is not None:
            up.sendto(data)
        else:
            self.relay.counters["udp_lost_opening"] += 1

    async def _open(self, client, first: bytes) -> None:
        loop = asyncio.get_running_loop()
        front = self

        class Back(asyncio.DatagramProtocol):
            def datagram_received(self, data, _addr) -> None:
                front.relay.counters["udp_back"] += 1
                front.relay.later(front.transport.sendto, data, client)

        up, _ = await loop.create_datagram_endpoint(Back, remote_addr=("127.0.0.1", self.target))
        self.upstream[client] = up
        up.sendto(first)
