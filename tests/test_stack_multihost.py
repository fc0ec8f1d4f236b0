"""A swarm across three hosts, on this machine, on simulated time. Three network namespaces on a
Linux bridge are the drones' hosts: each runs a Zenoh router and the companions of its two drones,
secured as a field swarm is (`triswarm pki init` makes the certificates and configurations; the
companions are mTLS clients of their host's router, access control lets agent i write only under
its own keys, and the routers mesh over QUIC with their router certificates). The six flight
controllers are ONE `sitl up -n 6 --lockstep` in the root namespace, bound on the bridge's address:
its clock steps only when every companion has answered its state, so control and protocol are
judged on the flight controllers' clock however slow or busy the machine is (separate SITL
processes would have separate clocks). The ground station sits in the root namespace too:
`triswarm monitor` reaches every companion over MAVLink, and a Zenoh client with the gcs
certificate follows every agent's status and liveliness through router A.

Host C is cut off the swarm's network once the formation has settled, then restored: iptables in
its namespace drops every packet in and out but loopback (its companions to its router) and its
companions' flight-controller links (on a drone, a serial line that no network fault cuts). The
routers, the companions' Zenoh sessions and the ground station's MAVLink links to 5 and 6 all lose
host C; the drones 5 and 6 stay in their companions' hands. While C is cut off, its router is
killed (SIGKILL: a crash) and started again ROUTER_DEAD_S of wall time later: 5 and 6 lose their
sessions and each other, and must find the new router; at the restore, routers A and B must mesh
with it. Only through it do the ground station's clients of A and B see 5 and 6 alive again, and
the swarm become whole.

Timeline, plan time on the flight controllers' clock (the plan switches topology every 5 s):

    16-19 s   all six, judged (the entry ends at 15 s)              (two-chain)
    19 s      host C cut off; then its router killed, and started again ROUTER_DEAD_S (wall) later
    19-25 s   agents 1-4 keep a path from the leader (two-chain, triangles): judged;
              agents 5, 6 have none: they hold
    25-30 s   reverse-two-chain: the leader pins only 5 and 6, so 1-4 hold and say so on Zenoh;
              5, 6 have a path again and rejoin (on host C, alone)
    27 s      host C restored
    then      the routers reconnect. That takes wall time while simulated time runs on, so how
              much plan time it takes depends on the machine: the test measures when the ground
              station's clients of routers A and B both see 5 and 6 alive again (t_reconnected)
              and judges from there. 1-4 fly again once they have a path: as soon as the swarm is
              reconnected, or at 30 s at the latest (two-chain pins 1 and 2); t_joined is the later
              of that and t_reconnected
    t_joined + 15 s   all six within the bounds, and they stay there for 5 s more: judged

The formation is judged from the flight controllers' own telemetry (a Recorder in the root
namespace on the SITL's ground-station links), within the paper's bounds (0.10 m, 0.02 rad). Holding
(no path to the leader: brake, hold position, say so) is the companion's failsafe for a lost swarm
link. What only wall time can show is judged on wall time, with margin: the monitor calls a drone
lost after 2 s of silence, so the cut lasts at least MIN_CUT_WALL_S of wall time. (That the monitor
shows 1-4 holding is not judged: their hold lasts 2.5-4.5 s of wall time here, too short to be sure
of a table with it, and a longer one would push the restore past the graph switch at 30 s.) Every
wait is bounded in wall time."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from triswarm.gcs import pki
from triswarm.gcs.recorder import Recorder
from triswarm.gcs.scenarios import load_plan
from triswarm.gcs.stack import stop_in_turn
from triswarm.protocol import metrics

from .conftest import PAPER_PLAN_FILE
from . import zenoh_router
from .multihost import Hosts, subnet_in_use
from .netem import need_netns
from .stack_helpers import judge, log_events
from .test_monitor import table_rows, triswarm

pytestmark = [pytest.mark.slow, pytest.mark.realtime]  # (the monitor's view and the cut are judged on wall time)
SWARM = "paper-hexagon"
HOSTS = {"a": [1, 2], "b": [3, 4], "c": [5, 6]}
SETTLED_AT, CUT_AT, HOLD_AT, RESTORE_AT, TWO_CHAIN_AT = 16.0, 19.0, 25.0, 27.0, 30.0
"""The entry ends at 15 s (3 s climb, 12 s blend): the six are judged from 16 s, host C is cut at
19 s (two-chain, then triangles), reverse-two-chain from 25 s leaves 1-4 without a path, C is restored
at 27 s, and two-chain from 30 s pins 1 and 2 again. (The graphs repeat every 15 s; the case study's
window [25, 50] s is test_stack's.)"""
REJOIN_WITHIN_S = 15.0
"""From t_joined to all six within the bounds. A companion's way back is a quintic of
``rejoin_duration``: at REJOIN_ACCEL = 4 m/s^2, 3.94 |dv| / 4 s for a velocity error dv. A drone
braking from 10 m/s (over 5 s) while its place turns at 1 rad/s and 10 m/s is at most 14.5 m/s off
(2.3 s into the hold): 14.3 s, the longest (a 9.8 s rejoin from rest, 13.9 s measured from 2.7 s)."""
FINAL_S = 5.0
RATE_HZ = 100.0
"""The companions' control rate. In lockstep the rate costs wall time, not accuracy: at the plan's
200 Hz this test took 171 CPU-seconds for 50 simulated seconds (six companions, the SITL, three
routers, start-up included: 2 minutes of wall time on two cores), at 100 Hz 90, and the formation
stays within 0.005 m (0.002 m at 200 Hz)."""
START_DELAY_S = 3.0
"""Simulated seconds from the flight controllers' boot to the plan's start. The clock stands until
every companion has answered (however long they take to import and design the plan), so nobody
can be late; the companions arm 2 s before the start."""
ROUTER_DEAD_S = 2.0
"""Wall time router C stays dead: past Zenoh's 1 s lease, its clients lose their sessions."""
MIN_CUT_WALL_S = 4.0
"""The restore waits, beside plan time RESTORE_AT, for this much wall time after the cut: the
monitor calls a drone lost after 2 s of silence and prints a table a second, so it shows the cut
whatever the speed of the simulated clock. (The clock runs at most MAX_RTF times as fast as the
wall: the wait does not delay the restore.)"""
MAX_RTF = 1.0
"""The simulated clock never runs faster than the wall here (``sitl up --max-rtf``): what happens on
the wall clock (the routers reconnecting, the monitor's 2 s to call a drone lost, the restore's
wall-time wait, statuses and liveliness, which are not lockstepped) then takes at most as many
simulated seconds as wall seconds, and the timeline above holds however fast the machine is."""
TICK_S = 1.0 / 100.0 + 1e-6
"""A control period (RATE_HZ): a tick acts on the graph in force at the time its estimate refers
to, one period ahead."""
STATUS_SLACK_S = 0.1
"""1-4 fly again once a path is back: 1 and 2 at once (pinned in two-chain), 3 and 4 when the
others' FLYING status has reached them. A status travels on Zenoh outside lockstep (through the
routers, on the wall clock): some ticks of simulated time, at most (MAX_RTF) that much wall time."""
CUT_TOLERANCE_S = 0.5
"""5 and 6 hold, and the routers lose them, within this much plan time of the cut (measured once the
rules are in: the clock then stands while 5 and 6 wait for the estimates the cut lost)."""
WALL_TIMEOUT_S = 120.0
"""Bound on each wait for the simulated clock."""
POS_BOUND, ATT_BOUND = 0.10, 0.02


def client_config(generated: Path, router: pki.Router, out: Path) -> Path:
    """A client configuration of ``pki init``, connecting to one router only (its host's)."""
    cfg = pki.read_config(generated)
    cfg["connect"]["endpoints"] = [router.endpoint]
    out.write_text(json.dumps(cfg, indent=2))
    return out


class MonitorTables:
    """`triswarm monitor` running (plain tables, one a second of wall time): each table, stamped
    with the flight controllers' clock (``clock``) when it came."""

    def __init__(self, cmd: list[str], clock, copy: Path) -> None:
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        self.clock = clock
        self.copy = copy.open("w")
        self.tables: list[tuple[float, list[str]]] = []
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.copy.write(line)
            if "triswarm monitor" in line:
                self.tables.append((self.clock(), []))
                self.copy.write(f"(plan clock {self.clock():.3f})\n")
            if self.tables:
                self.tables[-1][1].append(line.rstrip("\n"))

    def close(self) -> None:
        stop_in_turn([[self.proc]], timeout_s=10, sig=signal.SIGINT)  # the monitor stops on Ctrl-C
        self._thread.join(timeout=5)
        self.proc.stdout.close()
        self.copy.close()

    def last_before(self, t_unix: float) -> dict[str, dict[str, str]]:
        """The rows of the last whole table printed before the flight controllers' clock reached ``t_unix``."""
        done = [lines for at, lines in self.tables[:-1] if at < t_unix]  # the last may be cut short
        assert done, f"no monitor table before {t_unix}: {self.tables[:2]}"
        return table_rows("\n".join(done[-1]))


class BusWatch:
    """The ground station's Zenoh client (certificate CN gcs), through host A's router: every
    agent's status, and when (on the flight controllers' clock) each agent's liveliness came and went."""

    def __init__(self, config: Path, clock) -> None:
        import zenoh

        self.clock = clock
        self.session = zenoh.open(zenoh.Config.from_file(str(config)))
        self.statuses: list[tuple[float, int, str, str]] = []  # (since [the agent's fc clock, Unix s], agent, status, reason)
        self.liveliness: list[tuple[float, int, bool]] = []  # (the fc clock when heard, agent, alive)
        self._lock = threading.Lock()
        self._sub = self.session.declare_subscriber(f"triswarm/{SWARM}/agent/*/status", self._on_status)
        self._alive = self.session.liveliness().declare_subscriber(f"triswarm/{SWARM}/agent/*/alive", self._on_alive,
                                                                   history=True)

    def _on_status(self, sample) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
            with self._lock:
                # when the agent's status began, by its own word: a status put lost on the way is
                # repeated, whole, within a second
                self.statuses.append((float(msg["since"]), int(msg["agent"]), msg["status"], msg.get("reason", "")))
        except (ValueError, KeyError, TypeError):
            pass

    def _on_alive(self, sample) -> None:
        import zenoh

        try:
            agent = int(str(sample.key_expr).split("/")[-2])
        except ValueError:
            return
        with self._lock:
            self.liveliness.append((self.clock(), agent, sample.kind == zenoh.SampleKind.PUT))

    def alive_since(self, agent: int, after: float) -> float | None:
        """When the agent's liveliness came back after Unix time ``after`` (the fc clock), if it did."""
        with self._lock:
            events = [(t, alive) for t, a, alive in self.liveliness if a == agent and t > after]
        lost = [t for t, alive in events if not alive]
        back = [t for t, alive in events if alive and (not lost or t > lost[0])]
        return back[0] if back else None

    def close(self) -> None:
        self._alive.undeclare()
        self._sub.undeclare()
        self.session.close()


def changes(statuses, agent: int, start: float) -> list[tuple[float, str, str]]:
    """An agent's status changes (plan time they began, status, reason); the 1 Hz repeats dropped."""
    out: list[tuple[float, str, str]] = []
    for t, a, status, reason in statuses:  # (in the order they came)
        if a == agent and (not out or out[-1][1] != status):
            out.append((round(t - start, 3), status, reason))
    return out


def worst_over_time(plan, rec, start: float, t_from: float, t_to: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per time step, every drone's position and attitude error (the worst of the three angles)."""
    t, pos, eta = rec.arrays(start, t_from=t_from, t_to=t_to)
    pe, ae = metrics.formation_errors(plan, t, pos, eta)
    return t, pe, ae.max(axis=2)


def speed(rec, start: float, drone: int, t_from: float, t_to: float) -> float:
    t, pos, _ = rec.arrays(start, t_from=t_from, t_to=t_to)
    v = np.linalg.norm(np.diff(pos[:, drone - 1], axis=0), axis=1) / np.diff(t)
    return float(v.mean())


def test_three_hosts_link_cut_and_rejoin(tmp_path):
    need_netns(tools=("ip", "iptables"))
    prefix = next((f"10.77.{k}" for k in range(0, 250) if not subnet_in_use(f"10.77.{k}")), None)
    if prefix is None:
        need_netns(problem="no free 10.77.x.0/24 subnet")
    plan = load_plan(str(PAPER_PLAN_FILE))
    assert [plan.schedule.at(t).name for t in (SETTLED_AT, CUT_AT + 0.5, HOLD_AT - 1, HOLD_AT + 0.1, TWO_CHAIN_AT + 0.1)] == \
        ["two-chain", "two-chain", "triangles", "reverse-two-chain", "two-chain"]
    t_wall = time.monotonic()
    procs: dict[str, subprocess.Popen] = {}
    logs = []
    for sub in ("logs", "state", "stats", "zenoh"):
        (tmp_path / sub).mkdir()
    monitor = rec = watch = watch_b = None
    measured: dict = {}
    router_of = {h: f"router-{h}" for h in HOSTS}  # (their process names: router C's changes when it restarts)

    def spawn(prefix_cmd: list[str], name: str, cmd: list[str]) -> None:
        log = (tmp_path / "logs" / f"{name}.log").open("w")
        logs.append(log)
        procs[name] = subprocess.Popen(prefix_cmd + cmd, stdout=log, stderr=subprocess.STDOUT,
                                       cwd=str(Path(__file__).resolve().parents[1]))

    def check_alive() -> None:
        dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
        assert not dead, f"exited early: {dead}: " + "; ".join(
            f"{n}: {(tmp_path / 'logs' / f'{n}.log').read_text()[-1500:]}" for n in dead)

    def wait(cond, what: str, timeout_s: float = WALL_TIMEOUT_S) -> None:
        deadline = time.monotonic() + timeout_s
        while not cond():
            check_alive()
            assert time.monotonic() < deadline, f"{what}: not within {timeout_s:.0f} s of wall time"
            time.sleep(0.05)

    def plan_time() -> float:
        return rec.now() - start

    def wait_plan(t: float) -> None:
        """Until the flight controllers' clock reaches plan time t."""
        wait(lambda: plan_time() >= t, f"plan time {t:.1f} s (now {plan_time():.2f} s)")

    net = Hosts(list(HOSTS), f"tsw{os.getpid() % 100000}", prefix)
    with net:
        try:
            # the swarm's PKI: a router per host (reached at the host's address), agents 1-6, the gcs
            routers = {h: pki.Router(net.address[h]) for h in HOSTS}
            pki.init(tmp_path / "pki", SWARM, 6, list(routers.values()))
            generated = tmp_path / "pki" / "zenoh"
            for h in HOSTS:  # each host's router: QUIC to the routers of the hosts after it
                spawn(net.exec_prefix(h), f"router-{h}", zenoh_router.command(generated / f"{routers[h].name}.json5"))
            # the six flight controllers: one simulator, one clock, on the bridge's address
            manifest_path = tmp_path / "manifest.json"
            spawn([], "sitl", [sys.executable, "-m", "triswarm.gcs.cli", "sitl", "up", "-n", "6", "--lockstep",
                               "--max-rtf", str(MAX_RTF), "--bind", net.bridge_address, "--base-port", "0",
                               "--manifest", str(manifest_path),
                               "--stats", str(tmp_path / "stats" / "sitl.json")])
            wait(manifest_path.exists, "the SITL's manifest", 60.0)
            manifest = json.loads(manifest_path.read_text())
            assert manifest["clock"]["lockstep"] and [v["sysid"] for v in manifest["vehicles"]] == list(range(1, 7))
            vehicle = {v["sysid"]: v for v in manifest["vehicles"]}
            start = manifest["clock"]["boot_unix_s"] + START_DELAY_S
            gcs_urls = []
            for h, ids in HOSTS.items():
                for i in ids:
                    agent_cfg = client_config(generated / f"agent-{i}.json5", routers[h], tmp_path / "zenoh" / f"agent-{i}.json5")
                    gcs_urls.append(f"{i}=udpout:{net.address[h]}:{14550 + i}")
                    spawn(net.exec_prefix(h), f"companion-{i}", [
                        sys.executable, "-m", "triswarm.companion.cli", "--id", str(i),
                        "--fc", vehicle[i]["links"]["companion"]["pymavlink"], "--gcs", f"udpin:{net.address[h]}:{14550 + i}",
                        str(PAPER_PLAN_FILE), "--autostart", "--start-at", f"{start:.3f}",
                        "--zenoh-config", str(agent_cfg),
                        "--rate-hz", str(RATE_HZ), "--state-dir", str(tmp_path / "state" / str(i)), "--stats", str(tmp_path / "stats" / f"{i}.json")])
            # the root namespace: the flight controllers' own telemetry, the bus via router A
            rec = Recorder(manifest).__enter__()
            watch = BusWatch(client_config(generated / "gcs.json5", routers["a"], tmp_path / "zenoh" / "gcs.json5"), rec.now)
            # (and through host B's router, whose agents 3 and 4 need 5 and 6 for a path in reverse-two-chain)
            watch_b = BusWatch(client_config(generated / "gcs.json5", routers["b"], tmp_path / "zenoh" / "gcs-b.json5"), rec.now)
            # the operator's monitor, from the root namespace to every companion's MAVLink link, all along
            monitor = MonitorTables(triswarm("monitor", *[a for url in gcs_urls for a in ("--endpoint", url)],
                                             "--rate-hz", "1", "--tlog", str(tmp_path / "gcs.tlog")), rec.now,
                                   tmp_path / "logs" / "monitor.txt")
            wait_plan(CUT_AT)
            # host C off the network but for its flight-controller links
            t_cut_begin = plan_time()
            net.cut("c", keep=[(net.bridge_address, vehicle[i]["links"]["companion"]["port"]) for i in HOSTS["c"]])
            t_cut, t_cut_wall = plan_time(), time.monotonic()  # (the clock stands at once: 5 and 6 wait for 3 and 4)
            # once routers A and B have lost 5 and 6 (judged below), host C's router crashes, and is
            # started again
            wait(lambda: all(any(a == i and not alive and t >= start + t_cut_begin for t, a, alive in w.liveliness)
                             for w in (watch, watch_b) for i in HOSTS["c"]), "A and B lose 5 and 6", 60.0)
            dead = procs.pop(router_of["c"])
            dead.kill()
            dead.wait(timeout=10)
            t_router_dead_wall = time.monotonic()
            time.sleep(ROUTER_DEAD_S)
            router_of["c"] = "router-c-again"
            spawn(net.exec_prefix("c"), router_of["c"], zenoh_router.command(generated / f"{routers['c'].name}.json5"))
            wait(lambda: " up" in (tmp_path / "logs" / f"{router_of['c']}.log").read_text(), "router C up again", 60.0)
            measured["router_c_dead_wall_s"] = round(time.monotonic() - t_router_dead_wall, 2)
            measured["router_c_up_again_s"] = round(plan_time(), 2)
            wait_plan(RESTORE_AT)
            wait(lambda: time.monotonic() >= t_cut_wall + MIN_CUT_WALL_S, "the cut's least wall time")
            t_restore, t_restore_wall = plan_time(), time.monotonic()
            net.restore("c")
            # the swarm reconnected: routers A and B both see 5 and 6 again
            wait(lambda: all(w.alive_since(i, start + t_cut) for w in (watch, watch_b) for i in HOSTS["c"]),
                 "5 and 6 alive again", 60.0)
            t_reconnected = max(w.alive_since(i, start + t_cut) for w in (watch, watch_b) for i in HOSTS["c"]) - start
            measured["reconnected_wall_s"] = round(time.monotonic() - t_restore_wall, 2)
            wait_plan(TWO_CHAIN_AT + 0.5)  # past the graph switch that gives 1-4 a path without 5 and 6
            held = {i: [t for t, s, _ in changes(watch.statuses, i, start) if s == "HOLDING" and t > HOLD_AT - 1]
                    for i in (1, 2, 3, 4)}
            assert all(held.values()), f"agents 1-4 never held in reverse-two-chain: {held}"
            wait(lambda: all(any(s == "FLYING" and t > held[i][0] for t, s, _ in changes(watch.statuses, i, start))
                             for i in (1, 2, 3, 4)), "agents 1-4 flying again")
            back = {i: min(t for t, s, _ in changes(watch.statuses, i, start) if s == "FLYING" and t > held[i][0])
                    for i in (1, 2, 3, 4)}
            t_joined = max(max(back.values()), t_reconnected)
            end = t_joined + REJOIN_WITHIN_S + FINAL_S
            wait_plan(end)
            check_alive()  # every process alive to the end
        finally:
            if monitor is not None:
                monitor.close()
            for w in (watch, watch_b):
                if w is not None:
                    w.close()
            if rec is not None:
                rec.__exit__(None, None, None)
            # companions first, then the SITL, then the routers one by one in the order they connect
            # (A to B and C, B to C): a router still trying to reach one that is gone takes 10 s to close
            stop_in_turn([[p for n, p in procs.items() if n.startswith("companion")], [procs["sitl"]] if "sitl" in procs else [],
                          *[[procs[router_of[h]]] for h in HOSTS if router_of[h] in procs]])
            for log in logs:
                log.close()
    assert not net.leftovers(), net.leftovers()
    wall_s = time.monotonic() - t_wall

    def log(name: str) -> str:
        return (tmp_path / "logs" / f"{name}.log").read_text()

    sitl = json.loads((tmp_path / "stats" / "sitl.json").read_text())
    measured.update({"cut_s": round(t_cut, 2), "restore_s": round(t_restore, 2), "reconnected_s": round(t_reconnected, 2),
                     "joined_s": round(t_joined, 2), "end_s": round(end, 2), "wall_s": round(wall_s, 1),
                     "cut_wall_s": round(t_restore_wall - t_cut_wall, 1),
                     "real_time_factor": sitl["lockstep"]["real_time_factor"], "left": sitl["lockstep"]["left"]})
    try:
        late = [line for i in range(1, 7) for line in log(f"companion-{i}").splitlines() if "late for the start" in line]
        assert not late, f"companions late for the start: {late}"
        assert sitl["lockstep"]["left"] == [], "a companion left lockstep (the watchdog took it out)"
        # settled, before the cut: all six
        ok, worst = judge(plan, rec, start, SETTLED_AT, CUT_AT)
        measured["all_before_cut"] = worst
        assert ok, f"before the cut [{SETTLED_AT}, {CUT_AT}] s: {worst}"

        # routers A and B lost 5 and 6 at the cut, and saw them again only after the restore. (A
        # loss before the cut, back before it too, is a process starved past Zenoh's 1 s lease on
        # a loaded machine, as Zenoh means it: counted in the measurements, not judged)
        for w in (watch, watch_b):
            for i in HOSTS["c"]:
                events = [(t - start, alive) for t, a, alive in w.liveliness if a == i]
                k = next((n for n, (t, _) in enumerate(events) if t >= t_cut_begin), len(events))
                measured.setdefault("liveliness_lost_before_cut", []).extend(t for t, alive in events[:k] if not alive)
                assert k == 0 or events[k - 1][1], (i, events, t_cut_begin)  # alive when the cut began
                gone = [t for t, alive in events[k:] if not alive]
                assert gone and gone[0] < t_cut + CUT_TOLERANCE_S, (i, events, t_cut)
        assert t_reconnected >= t_restore, (t_reconnected, t_restore)  # (the same recorder sample: a quick retry)

        # the operator's view (wall time: a table a second, "lost" after 2 s): every drone before the
        # cut; during it 5 and 6 lost while 1-4 are reached; all six at the end
        tables = {"before the cut": monitor.last_before(start + CUT_AT),
                  "cut, triangles": monitor.last_before(start + HOLD_AT),
                  "cut, restore": monitor.last_before(start + t_restore),
                  "end": monitor.last_before(start + end)}
        measured["monitor"] = {name: {d: (cell(r, "link"), cell(r, "phase")) for d, r in t.items()}
                               for name, t in tables.items()}
        for name in ("before the cut", "end"):
            assert sorted(tables[name]) == [str(i) for i in range(1, 7)], (name, tables[name])
            for d, row in tables[name].items():
                assert [shown(cell(row, c), v) for c, v in (("armed", "yes"), ("mode", "EXTERNAL"), ("phase", "flying"))] \
                    == [True] * 3, (name, d, row)
                assert not cell(row, "link").startswith("lost"), (name, d, row)
        for d, row in tables["cut, triangles"].items():
            assert d in ("5", "6") or (not cell(row, "link").startswith("lost") and shown(cell(row, "phase"), "flying")), (d, row)
        for d, row in tables["cut, restore"].items():
            lost = cell(row, "link").startswith("lost")
            assert lost if d in ("5", "6") else not lost, (d, row)

        # during the cut, while 1-4 keep a path from the leader (two-chain, triangles)
        ok, worst = judge(plan, rec, start, CUT_AT, HOLD_AT, drones=[1, 2, 3, 4])
        measured["1-4_with_a_path"] = worst
        assert ok, f"agents 1-4 with a path, [{CUT_AT}, {HOLD_AT}] s, host C cut off: {worst}"

        # reverse-two-chain: without 5 and 6, 1-4 have no path; they hold, and say so on Zenoh; they fly
        # again once the swarm is reconnected, or when two-chain pins 1 and 2 if it is not yet
        status = {i: changes(watch.statuses, i, start) for i in range(1, 7)}
        measured["status_changes"] = status
        measured["1-4_back_s"] = back
        for i in (1, 2, 3, 4):
            holds = [(t, reason) for t, s, reason in status[i] if s == "HOLDING" and t > SETTLED_AT]
            # (a tick acts on the graph in force at the time its estimate refers to: a tick early)
            assert holds and HOLD_AT - 0.02 <= holds[0][0] < HOLD_AT + 0.05, (i, status[i])
            assert "no path to the leader in reverse-two-chain" in holds[0][1], (i, holds)
            assert min(t_restore, TWO_CHAIN_AT) - TICK_S <= back[i] <= TWO_CHAIN_AT + STATUS_SLACK_S, (i, status[i], t_restore)
            if t_reconnected < TWO_CHAIN_AT - 0.5:  # reconnected in reverse-two-chain: they fly again then
                assert back[i] < t_reconnected + 0.5, (i, back[i], t_reconnected)
            # braking: slower at the end of the hold than at its start (from 10 m/s)
            v0, v1 = speed(rec, start, i, HOLD_AT - 0.5, HOLD_AT), speed(rec, start, i, back[i] - 0.5, back[i])
            measured.setdefault("1-4_speed_at_hold_and_back", {})[i] = (round(v0, 2), round(v1, 2))
            assert v0 > 5.0 and v1 < 0.75 * v0, (i, v0, v1)

        # 5 and 6, cut off: they hold from the cut (no path in two-chain / triangles without 3 and 4)
        # and fly again when reverse-two-chain pins them to the leader (their logs: nobody outside
        # hears them). Plan time stands while they wait for their lost neighbours, so this is exact.
        for i in HOSTS["c"]:
            holds, rejoins = log_events(log(f"companion-{i}"), "hold"), log_events(log(f"companion-{i}"), "rejoin")
            measured.setdefault("5-6_holds", {})[i] = holds
            measured.setdefault("5-6_rejoins", {})[i] = rejoins
            during = [t for t in holds if t_cut_begin <= t < t_cut + CUT_TOLERANCE_S]
            assert during, (i, holds, t_cut)
            assert any(HOLD_AT - 0.02 <= t < HOLD_AT + 0.05 for t in rejoins), (i, rejoins)
            assert not [t for t in holds if during[0] < t < HOLD_AT], (i, holds)  # held throughout until then

        # the swarm whole again: all six back within the bounds within REJOIN_WITHIN_S, and they stay
        t, pe, ae = worst_over_time(plan, rec, start, t_joined, end)
        out = (pe > POS_BOUND).any(axis=1) | (ae > ATT_BOUND).any(axis=1)
        back_at = float(t[np.nonzero(out)[0][-1] + 1]) if out.any() else t_joined
        measured["within_bounds_s_after_joined"] = round(back_at - t_joined, 2)
        measured["worst_during_rejoin_m"] = round(float(pe.max()), 2)
        assert back_at - t_joined <= REJOIN_WITHIN_S, f"back within the bounds {back_at - t_joined:.1f} s after t_joined"
        ok, worst = judge(plan, rec, start, t_joined + REJOIN_WITHIN_S, end)
        measured["all_final"] = worst
        assert ok, f"final window [{t_joined + REJOIN_WITHIN_S:.1f}, {end:.1f}] s: {worst}"

        # every companion stopped cleanly and never failed a tick
        for i in range(1, 7):
            assert procs[f"companion-{i}"].returncode == 0, log(f"companion-{i}")[-3000:]
            stats = json.loads((tmp_path / "stats" / f"{i}.json").read_text())
            assert stats["tick_errors"] == 0, (i, stats)
    finally:
        print("MEASURED " + json.dumps(measured, default=str))


def cell(row: dict[str, str], column: str) -> str:
    """A monitor cell by its column's name. The plain table is 200 characters wide: when a row is
    wider (the neighbour ages of an agent cut off for seconds run to 8 digits), rich squeezes the
    columns and ends a cut header or cell with an ellipsis."""
    for header, value in row.items():
        if header == column or (header.endswith("…") and column.startswith(header[:-1])):
            return value
    raise KeyError(f"no column {column} in {list(row)}")


def shown(value: str, word: str) -> bool:
    """Whether a (maybe squeezed) monitor cell shows ``word``."""
    return value == word or (value.endswith("…") and len(value) > 1 and word.startswith(value[:-1]))
