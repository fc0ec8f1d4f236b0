"""Several "hosts" on one machine for tests: a Linux bridge in the root namespace and one network
namespace per host, joined to the bridge by a veth pair, each with an address of its own. Every
process a test starts in a host runs under ``ip netns exec``; on exit every process left in a
namespace is killed and every interface and namespace is deleted.

Run as a script it is a host's Zenoh router, until SIGTERM (what ``zenohd -c CONFIG`` would do,
without installing zenohd):

    python tests/multihost.py router CONFIG.json5
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path


def _run(*cmd: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(list(cmd), check=check, capture_output=True, text=True)


def subnet_in_use(prefix: str) -> bool:
    """Whether any interface of the root namespace has an address in ``prefix``.0/24."""
    return f" {prefix}." in _run("ip", "-4", "-o", "addr", "show", check=False).stdout


@dataclass
class Hosts:
    """``hosts`` names (short, e.g. "a", "b", "c"); host k gets ``prefix``.(11 + k), the bridge
    ``prefix``.1. Names carry ``tag`` so that two runs do not collide."""

    hosts: list[str]
    tag: str
    prefix: str = "10.77.0"
    netns: dict[str, str] = field(init=False)
    address: dict[str, str] = field(init=False)
    root_veth: dict[str, str] = field(init=False)

    def __post_init__(self) -> None:
        self.bridge = f"{self.tag}-br"  # hosts' veths are {tag}{host}r/n: no dash
        assert len(self.bridge) <= 15 and all(len(f"{self.tag}{h}r") <= 15 for h in self.hosts)
        self.bridge_address = f"{self.prefix}.1"
        self.netns = {h: f"{self.tag}-{h}" for h in self.hosts}
        self.address = {h: f"{self.prefix}.{11 + k}" for k, h in enumerate(self.hosts)}
        self.root_veth = {h: f"{self.tag}{h}r" for h in self.hosts}
        self._made: list[tuple[str, str]] = []  # ("netns"|"link", name), in the order made

    def __enter__(self) -> "Hosts":
        try:
            _run("ip", "link", "add", self.bridge, "type", "bridge")
            self._made.append(("link", self.bridge))
            _run("ip", "addr", "add", f"{self.bridge_address}/24", "dev", self.bridge)
            _run("ip", "link", "set", self.bridge, "up")
            for h in self.hosts:
                ns, root, inner = self.netns[h], self.root_veth[h], f"{self.tag}{h}n"
                _run("ip", "netns", "add", ns)
                self._made.append(("netns", ns))
                _run("ip", "link", "add", root, "type", "veth", "peer", "name", inner)
                self._made.append(("link", root))
                _run("ip", "link", "set", inner, "netns", ns)
                _run("ip", "link", "set", root, "master", self.bridge)
                _run("ip", "link", "set", root, "up")
                _run("ip", "-n", ns, "link", "set", "lo", "up")
                _run("ip", "-n", ns, "addr", "add", f"{self.address[h]}/24", "dev", inner)
                _run("ip", "-n", ns, "link", "set", inner, "up")
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc) -> None:
        # every process still in a namespace, then the namespaces (their veth ends go with them),
        # then the root ends and the bridge
        for kind, name in reversed(self._made):
            if kind == "netns":
                kill_namespace(name)
        for kind, name in reversed(self._made):
            if kind == "link":
                _run("ip", "link", "del", name, check=False)
        self._made.clear()

    def exec_prefix(self, host: str) -> list[str]:
        return ["ip", "netns", "exec", self.netns[host]]

    def link(self, host: str, up: bool) -> None:
        """Cut (or restore) a host's link: its veth end in the root namespace, down or up."""
        _run("ip", "link", "set", self.root_veth[host], "up" if up else "down")

    def leftovers(self) -> list[str]:
        """Interfaces and namespaces of ours still there (empty after exit)."""
        links = _run("ip", "-o", "link", "show", check=False).stdout
        netns = _run("ip", "netns", "list", check=False).stdout
        return [name for name in [self.bridge, *self.root_veth.values()] if f" {name}:" in links or f" {name}@" in links] + \
               [ns for ns in self.netns.values() if ns in netns.split()]


def kill_namespace(name: str) -> None:
    """SIGTERM every process in a namespace, SIGKILL what is left after 5 s, then delete it."""
    def pids() -> list[int]:
        out = _run("ip", "netns", "pids", name, check=False).stdout.split()
        return [int(p) for p in out if p.isdigit()]

    for sig, wait_s in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 2.0)):
        left = pids()
        for pid in left:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + wait_s
        while left and time.monotonic() < deadline:
            time.sleep(0.1)
            left = pids()
        if not left:
            break
    _run("ip", "netns", "del", name, check=False)


def _router_main(a: argparse.Namespace) -> None:
    import threading

    # Zenoh's default runtime, not the companion's single worker that a test's environment passes on
    # (triswarm.companion.bus sets it on import): a router with one worker stops whenever it blocks
    os.environ.pop("ZENOH_RUNTIME", None)
    import zenoh

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    zenoh.init_log_from_env_or("warn")
    session = zenoh.open(zenoh.Config.from_file(str(a.config)))
    print(f"router {session.zid()} up", flush=True)
    while not stop.wait(0.5):
        pass
    session.close()


def router_command(config: Path) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), "router", str(config)]


def main() -> None:
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="what", required=True)
    r = sub.add_parser("router")
    r.add_argument("config", type=Path)
    a = ap.parse_args()
    _router_main(a)


if __name__ == "__main__":
    main()
