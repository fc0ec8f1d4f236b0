"""Run the whole stack on one machine: `triswarm sitl up` and one `triswarm-companion` per drone, as
real processes on loopback, and stop every one of them."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from triswarm.sitl.processes import signal_group, spawn

from .errors import GcsError


def _below_ephemeral() -> tuple[int, int]:
    """Ports to pick listening ports from: below the kernel's ephemeral range, which it hands to
    every outgoing connection (a port picked there may be taken by one before it is bound)."""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    return max(1024, low - 20000), low


class StackError(GcsError, RuntimeError):
    """The stack could not start (a process that died at start, no free ports): one sentence."""


def free_ports(count: int, contiguous: bool = False, tries: int = 200, exclude: frozenset[int] = frozenset()) -> list[int]:
    """Ports free for both TCP and UDP on loopback (contiguous: base+1..base+count), picked below the
    kernel's ephemeral range, none of them in ``exclude`` (ports picked earlier and not bound yet).
    (For the companions' listening ports, which their peers must know before they start;
    everything that can bind port 0 does.)"""
    import random

    def free(port: int) -> bool:
        for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
            s = socket.socket(socket.AF_INET, kind)
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return False
            finally:
                s.close()
        return True

    rng = random.Random()
    lo, hi = _below_ephemeral()
    if count > hi - lo - 2:
        raise StackError(f"no {count} free ports found below the ephemeral range ({lo}-{hi - 1}): it has fewer")
    if contiguous:
        for _ in range(tries):
            base = rng.randrange(lo, hi - count - 1)
            ports = list(range(base + 1, base + count + 1))
            if exclude.isdisjoint(ports) and all(free(p) for p in ports):
                return ports
    else:
        picked: dict[int, None] = {}
        for _ in range(tries * count):  # one port at a time: a taken one costs a pick, not the set
            port = rng.randrange(lo, hi)
            if port not in exclude and port not in picked and free(port):
                picked[port] = None
                if len(picked) == count:
                    return list(picked)
    raise StackError(f"no {count} free ports found below the ephemeral range ({lo}-{hi - 1})")



def fc_link(link: dict) -> str:
    """What a companion takes as --fc for a vehicle's companion link in a SITL manifest: its ``url``
    (PX4's Zenoh bridge), else its pymavlink connection string."""
    return link.get("url") or link["pymavlink"]

@dataclass
class Stack:
    """SITL and companions. Use as a context manager. With a plan file, the companions take it and
    start it by themselves at a common time (``--autostart``); without, they wait for the ground
    station. ``swarm.json`` in the work folder lists each companion's ground-station endpoint."""

    plan_path: Path | None
    workdir: Path
    n: int
    start_delay_s: float = 12.0
    rate_hz: float = 200.0
    sitl_args: list[str] = field(default_factory=list)
    companion_args: dict[int, list[str]] = field(default_factory=dict)
    """Extra arguments per agent (e.g. Zenoh endpoints)."""
    wrap: list[str] = field(default_factory=list)
    """Prefix for every command (e.g. tests/priority.py NICE), which then starts in a session of its
    own (the wrapper may set the session's priority). Every process ends with this one, however it
    ends (``sitl/processes.py``)."""
    companions: bool = True
    """Start the companions (False: the SITL alone, its ports and the Zenoh ports chosen)."""
    agents_per_process: int = 1
    """Companion processes fly this many agents each (0: all in one process, one Zenoh session)."""
    alone: tuple[int, ...] = ()
    """Agents that fly in a process of their own whatever ``agents_per_process`` says (a test that
    kills a companion kills one agent)."""
    sitl_base_port: int = 0
    """The SITL's first UDP port (0: any free ports). A fixed one lets a test kill the SITL and start
    it again on the same ports (``restart_sitl``), where the companions look for it."""
    fc_links: dict[int, str] = field(default_factory=dict)
    """The flight-controller link of agent i (e.g. a serial port) instead of its vehicle's companion
    link in the SITL's manifest (set before the companions start: ``companions=False``, then
    ``start_companion``)."""
    autopilot: str = "triswarm"
    """The flight controllers: triswarm's simulated ones, or ArduPilot's or PX4's SITL firmware (``sitl
    up --autopilot ardupilot|px4``, its binary or package ``firmware``), whose plant logs its truth to
    truth.csv."""
    firmware: Path | None = None
    lockstep: bool = False
    """The SITL steps when every companion has answered (``sitl up --lockstep``): the stack runs on
    simulated time, as fast as the machine allows. ``start_at`` is then on that clock, and
    ``start_delay_s`` counts simulated seconds from the moment every companion answers."""

    def __post_init__(self) -> None:
        self.workdir = Path(self.workdir)
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: list = []

    def _spawn(self, name: str, cmd: list[str]) -> subprocess.Popen:
        log = (self.workdir / "logs" / f"{name}.log").open("a")
        self._logs.append(log)
        proc = spawn(self.wrap + cmd, new_session=bool(self.wrap), stdout=log, stderr=subprocess.STDOUT)
        self.procs[name] = proc
        return proc

    def __enter__(self) -> "Stack":
        try:
            return self._start()
        except BaseException:  # (whatever stops the start stops what had started)
            self.__exit__(None, None, None)
            raise

    def _start(self) -> "Stack":
        for sub in ("logs", "state", "stats"):
            (self.workdir / sub).mkdir(parents=True, exist_ok=True)
        self.manifest = self._start_sitl()
        zenoh_ports = free_ports(self.n, contiguous=True)
        self.zenoh_base = zenoh_ports[0] - 1
        self.gcs_ports = free_ports(self.n, exclude=frozenset(zenoh_ports))  # (a companion binds both)
        clock = self.manifest["clock"]
        self.start_at = (clock["boot_unix_s"] if clock["lockstep"] else time.time()) + self.start_delay_s
        rest = [i for i in range(1, self.n + 1) if i not in self.alone]
        k = len(rest) if self.agents_per_process == 0 else self.agents_per_process
        groups = [[i] for i in self.alone] + [rest[a:a + k] for a in range(0, len(rest), max(k, 1))]
        self.process_of = {i: (f"companion-{g[0]}" if len(g) == 1 else f"companions-{g[0]}-{g[-1]}")
                           for g in groups for i in g}
        self.groups = {self.process_of[g[0]]: g for g in groups}
        for name in self.groups if self.companions else ():
            self._spawn(name, self.companion_cmd(self.groups[name]))
        from .link import write_manifest

        self.swarm_manifest = self.workdir / "swarm.json"
        write_manifest(self.swarm_manifest, Path(self.plan_path).stem if self.plan_path else "triswarm", self.endpoints(),
                       self.fc_endpoints())
        return self

    def _start_sitl(self) -> dict:
        """Start the SITL and wait for its manifest."""
        manifest_path = self.workdir / "manifest.json"
        if manifest_path.is_file():  # (a restart's old one; anything else there, the SITL says what)
            manifest_path.unlink()
        if self.autopilot in ("ardupilot", "px4"):
            own = ["--autopilot", self.autopilot, "--run-dir", str(self.workdir / "firmware"),
                   "--truth", str(self.workdir / "truth.csv"), "--quiet",
                   *(["--firmware", str(self.firmware)] if self.firmware is not None else [])]
        else:
            own = ["--base-port", str(self.sitl_base_port), *(["--lockstep"] if self.lockstep else ["--quiet"])]
        self._spawn("sitl", [sys.executable, "-m", "triswarm.gcs.cli", "sitl", "up", "-n", str(self.n), "--manifest",
                             str(manifest_path), "--stats", str(self.workdir / "stats" / "sitl.json"), *own,
                             *self.sitl_args])
        deadline = time.monotonic() + (120.0 if self.autopilot != "triswarm" else 60.0)
        while not manifest_path.is_file():
            if self.procs["sitl"].poll() is not None or time.monotonic() > deadline:
                self.__exit__(None, None, None)  # (first: the log is complete once the sitl is gone)
                raise StackError(f"sitl did not start{self._last_words('sitl')}")
            time.sleep(0.05)
        return json.loads(manifest_path.read_text())

    def kill_sitl(self, sig: int = signal.SIGKILL) -> None:
        """Signal the SITL (every flight controller goes with it) and wait for it to go."""
        proc = self.procs["sitl"]
        proc.send_signal(sig)
        proc.wait(timeout=10)

    def restart_sitl(self, sitl_args: list[str] | None = None) -> dict:
        """Start the SITL again (on the same ports if ``sitl_base_port`` is set): flight controllers
        that rebooted, on the ground, with a new clock; with ``sitl_args`` instead of the first
        ones if given. Returns its manifest."""
        assert self.procs["sitl"].poll() is not None, "the SITL still runs"
        if sitl_args is not None:
            self.sitl_args = list(sitl_args)
        self.manifest = self._start_sitl()
        return self.manifest

    def endpoints(self) -> dict[int, str]:
        """The ground station's URL of each companion."""
        return {i: f"udpout:127.0.0.1:{self.gcs_ports[i - 1]}" for i in range(1, self.n + 1)}

    def fc_endpoints(self) -> dict[int, str]:
        """The ground station's URL of each flight controller its companion does not route (PX4's
        own MAVLink port: its companion flies it over Zenoh); none for the others."""
        if self.autopilot != "px4":
            return {}
        return {i: self.manifest["vehicles"][i - 1]["links"]["gcs"]["pymavlink"] for i in range(1, self.n + 1)}

    def companion_cmd(self, agents: list[int]) -> list[str]:
        plan = [] if self.plan_path is None else [str(self.plan_path), "--autostart",
                                                  "--start-at", f"{self.start_at:.3f}"]
        links = []
        for i in agents:
            v = self.manifest["vehicles"][i - 1]
            links += ["--id", str(i), "--fc", self.fc_links.get(i, fc_link(v["links"]["companion"])),
                      "--gcs", f"udpin:127.0.0.1:{self.gcs_ports[i - 1]}"]
        extra = [arg for i in agents for arg in self.companion_args.get(i, [])]
        home = self.manifest["home"]
        return [sys.executable, "-m", "triswarm.companion.cli", *links,
                *plan, "--zenoh-base-port", str(self.zenoh_base), "--rate-hz", str(self.rate_hz),
                "--home", f"{home['lat_deg']!r},{home['lon_deg']!r},{home['alt_m']!r}",
                "--state-dir", str(self.workdir / "state" / "{id}"), "--stats", str(self.workdir / "stats" / "{id}.json"),
                *extra]

    def start_companion(self, i: int) -> None:
        """(Re)start the process that flies agent i."""
        name = self.process_of[i]
        self._spawn(name, self.companion_cmd(self.groups[name]))

    def kill_companion(self, i: int, sig: int = signal.SIGKILL) -> None:
        """Signal the process that flies agent i (every agent it flies goes with it)."""
        proc = self.procs[self.process_of[i]]
        proc.send_signal(sig)
        proc.wait(timeout=10)

    def alive(self) -> dict[str, bool]:
        return {name: p.poll() is None for name, p in self.procs.items()}

    def stopped(self) -> str | None:
        """One sentence on the first process of the stack that has stopped (None while all run): its
        name, its exit status and the last line of its log."""
        for name, p in self.procs.items():
            if p.poll() is not None:
                return f"{name} stopped (exit status {p.returncode}){self._last_words(name)}"
        return None

    def _last_words(self, name: str) -> str:
        """": <the last line of the log> (log: <path>)", or " (log: <path>)" for an empty log."""
        log = self.workdir / "logs" / f"{name}.log"
        try:
            lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
        except OSError:
            lines = []
        return f"{': ' + lines[-1].strip() if lines else ''} (log: {log})"

    def __exit__(self, *exc) -> None:
        companions = [p for name, p in self.procs.items() if name != "sitl"]
        stop_in_turn([companions, [p for p in [self.procs.get("sitl")] if p is not None]])
        for log in self._logs:
            log.close()

    def stats(self, name: str) -> dict:
        return json.loads((self.workdir / "stats" / f"{name}.json").read_text())

    def log(self, name: str) -> str:
        """A process's log: "sitl", or "companion-3" (the process that flies agent 3)."""
        if name.startswith("companion-"):
            name = self.process_of[int(name.removeprefix("companion-"))]
        return (self.workdir / "logs" / f"{name}.log").read_text()


def stop_in_turn(groups: list[list[subprocess.Popen]], timeout_s: float = 15.0, sig: int = signal.SIGTERM) -> None:
    """Stop each group of processes in turn: ``sig`` to all of it, then wait for each (SIGKILL after
    ``timeout_s``). Companions go before their flight controllers: they write their stats on SIGTERM."""
    for group in groups:
        for p in group:
            if p.poll() is None:
                signal_group(p, sig)
        for p in group:
            try:
                p.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                signal_group(p, signal.SIGKILL)
                p.wait(timeout=5)
