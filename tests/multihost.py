"""Several "hosts" on one machine for tests: a Linux bridge in the root namespace and one network
namespace per host, joined to the bridge by a veth pair, each with an address of its own. Every
process a test starts in a host runs under ``ip netns exec``; on exit every process left in a
namespace is killed and every interface and namespace is deleted (``tests/netem.py``'s
NetNamespace, one per host).

A host's Zenoh router runs as ``tests/zenoh_router.py CONFIG.json5``.
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass, field

from .netem import NetNamespace


def _run(*cmd: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(list(cmd), check=check, capture_output=True, text=True)


def subnet_in_use(prefix: str) -> bool:
    """Whether any interface of the root namespace has an address in ``prefix``.0/24."""
    return f" {prefix}." in _run("ip", "-4", "-o", "addr", "show", check=False).stdout


@dataclass
class Hosts:
    """``hosts`` names (short, e.g. "a", "b", "c"); host k gets ``prefix``.(11 + k), the bridge
    ``prefix``.1. Names carry ``tag`` so that two runs do not collide. Each host is a
    :class:`NetNamespace` (loopback up, what is left in it killed on exit)."""

    hosts: list[str]
    tag: str
    prefix: str = "10.77.0"
    netns: dict[str, NetNamespace] = field(init=False)
    address: dict[str, str] = field(init=False)
    root_veth: dict[str, str] = field(init=False)

    def __post_init__(self) -> None:
        self.bridge = f"{self.tag}-br"  # hosts' veths are {tag}{host}r/n: no dash
        assert len(self.bridge) <= 15 and all(len(f"{self.tag}{h}r") <= 15 for h in self.hosts)
        self.bridge_address = f"{self.prefix}.1"
        self.netns = {h: NetNamespace(f"{self.tag}-{h}") for h in self.hosts}
        self.address = {h: f"{self.prefix}.{11 + k}" for k, h in enumerate(self.hosts)}
        self.root_veth = {h: f"{self.tag}{h}r" for h in self.hosts}
        self._entered: list[NetNamespace] = []
        self._links: list[str] = []  # root-namespace interfaces made, in order

    def __enter__(self) -> "Hosts":
        try:
            _run("ip", "link", "add", self.bridge, "type", "bridge")
            self._links.append(self.bridge)
            _run("ip", "addr", "add", f"{self.bridge_address}/24", "dev", self.bridge)
            _run("ip", "link", "set", self.bridge, "up")
            for h in self.hosts:
                ns, root, inner = self.netns[h], self.root_veth[h], f"{self.tag}{h}n"
                self._entered.append(ns.__enter__())
                _run("ip", "link", "add", root, "type", "veth", "peer", "name", inner)
                self._links.append(root)
                _run("ip", "link", "set", inner, "netns", ns.name)
                _run("ip", "link", "set", root, "master", self.bridge)
                _run("ip", "link", "set", root, "up")
                ns.ip("addr", "add", f"{self.address[h]}/24", "dev", inner)
                ns.ip("link", "set", inner, "up")
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc) -> None:
        # the namespaces (what runs in them killed; their veth ends go with them), then the root
        # ends and the bridge
        while self._entered:
            self._entered.pop().__exit__(None, None, None)
        while self._links:
            _run("ip", "link", "del", self._links.pop(), check=False)

    def exec_prefix(self, host: str) -> list[str]:
        return self.netns[host].exec_prefix()

    def cut(self, host: str, keep: list[tuple[str, int]]) -> None:
        """Cut a host off the network but for loopback and the UDP peers ``keep`` ((address, port):
        e.g. its companions' flight-controller links, a serial line on a drone): iptables in its
        namespace drops every other packet in and out, from one atomic iptables-restore."""
        rules = ""
        for chain, interface, peer, port in (("INPUT", "-i", "-s", "--sport"), ("OUTPUT", "-o", "-d", "--dport")):
            rules += f"-A {chain} {interface} lo -j ACCEPT\n"
            rules += "".join(f"-A {chain} -p udp {peer} {address} {port} {p} -j ACCEPT\n" for address, p in keep)
            rules += f"-A {chain} -j DROP\n"
        self.netns[host].iptables_restore(rules)

    def restore(self, host: str) -> None:
        """Undo ``cut``: the host's rules flushed at once, every packet passes again."""
        self.netns[host].iptables_restore("-F INPUT\n-F OUTPUT\n")

    def leftovers(self) -> list[str]:
        """Interfaces and namespaces of ours still there (empty after exit)."""
        links = _run("ip", "-o", "link", "show", check=False).stdout
        netns = _run("ip", "netns", "list", check=False).stdout.split()
        return [name for name in [self.bridge, *self.root_veth.values()] if f" {name}:" in links or f" {name}@" in links] + \
               [ns.name for ns in self.netns.values() if ns.name in netns]
