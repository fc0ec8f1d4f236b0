"""A swarm across three hosts, on this machine: three network namespaces on a Linux bridge, each
with its own `sitl up -n 2 --first-id K`, two companions and a Zenoh router, secured as a field
swarm is: `triswarm pki init` makes the certificates and configurations, the companions are mTLS
clients of their host's router (access control: agent i writes only under its own keys), and the
routers mesh over QUIC with their router certificates. The ground station sits in the root
namespace: `triswarm monitor` reaches every companion over MAVLink, and a Zenoh client with the
gcs certificate follows every agent's status through router A. The six fly the paper's hexagon;
host C's link is cut for 10 s once the formation has settled, then restored.

Timeline (plan time; the plan switches topology every 5 s):

    25-34 s   all six, judged                        (reverse-two-chain, then two-chain)
    34 s      host C's link down (its root-side veth)
    34-40 s   agents 1-4 keep a path from the leader (two-chain, triangles): judged;
              agents 5, 6 have none: they hold
    40-44 s   reverse-two-chain: the leader pins only 5 and 6, so 1-4 hold; 5, 6 have a path again
              and rejoin (on host C, alone)
    44 s      the link back up: the routers reconnect, 1-4 get their path (through 5, 6) back
    44-64 s   all six back within the bounds within 15 s of the restore; final window judged

The formation is judged from the flight controllers' own telemetry (a Recorder in the root namespace
on every SITL's gcs link, over the bridge), within the paper's bounds (0.10 m, 0.02 rad). Holding
(no path to the leader: brake, hold position, say so) is the companion's failsafe for a lost swarm
link; the cut drones' flight controllers stay in their companions' hands throughout."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
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
from .netem import NetNamespace
from .stack_helpers import judge
from .test_monitor import table_rows, triswarm

pytestmark = pytest.mark.slow
SWARM = "paper-hexagon"
HOSTS = {"a": [1, 2], "b": [3, 4], "c": [5, 6]}
CUT_AT, RESTORE_AT, END = 34.0, 44.0, 64.0
REJOIN_WITHIN_S = 15.0
START_DELAY_S = 40.0
"""From the SITLs' manifests to the plan's start. Six companions importing numpy, scipy, numba, zenoh
and pymavlink at once, beside three SITLs and three routers, take about 10 s to be ready when this
test runs alone (8 s from the command line to ready, 4 s of it loading and designing the plan), but
26-29 s at the end of a full `make test` on a fresh clone (twice 0.4-0.8 s too late for 30 s); a
companion ready late starts late and is still settling at 25 s."""
RATE_HZ = 100.0
"""The companions' control rate here. Three hosts' processes share this machine's two cores: at the
plan's 200 Hz, six companions, three SITLs and three routers need more than two cores (measured
~170 CPU-seconds in an 85 s run), 40-50 % of the ticks miss their deadline, and the worst attitude
error reaches the 0.02 rad bound. At 100 Hz the same bounds hold with margin (0.015 m, 0.005 rad)."""
POS_BOUND, ATT_BOUND = 0.10, 0.02


def client_config(generated: Path, router: pki.Router, out: Path) -> Path:
    """A client configuration of ``pki init``, connecting to one router only (its host's)."""
    cfg = pki.read_config(generated)
    cfg["connect"]["endpoints"] = [router.endpoint]
    out.write_text(json.dumps(cfg, indent=2))
    return out


class MonitorTables:
    """`triswarm monitor` running (plain tables, one a second): each table and when it came."""

    def __init__(self, cmd: list[str]) -> None:
        import threading

        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        self.tables: list[tuple[float, list[str]]] = []
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            if "triswarm monitor" in line:
                self.tables.append((time.time(), []))
            if self.tables:
                self.tables[-1][1].append(line.rstrip("\n"))

    def close(self) -> None:
        stop_in_turn([[self.proc]], timeout_s=10, sig=signal.SIGINT)  # the monitor stops on Ctrl-C
        self._thread.join(timeout=5)
        self.proc.stdout.close()

    def last_before(self, t_unix: float) -> dict[str, dict[str, str]]:
        """The rows of the last whole table printed before ``t_unix``."""
        done = [lines for at, lines in self.tables[:-1] if at < t_unix]  # the last one may be cut short
        assert done, f"no monitor table before {t_unix}: {self.tables[:2]}"
        return table_rows("\n".join(done[-1]))


class BusWatch:
    """The ground station's Zenoh client (certificate CN gcs), through host A's router: every
    agent's status."""

    def __init__(self, config: Path) -> None:
        import threading

        import zenoh

        self.session = zenoh.open(zenoh.Config.from_file(str(config)))
        self.statuses: list[tuple[float, int, str, str]] = []  # (since [unix time], agent, status, reason)
        self._lock = threading.Lock()
        self._sub = self.session.declare_subscriber(f"triswarm/{SWARM}/agent/*/status", self._on_status)

    def _on_status(self, sample) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
            with self._lock:
                # when the agent's status began, by its own word: a status put lost on the way is
                # repeated, whole, within a second
                self.statuses.append((float(msg["since"]), int(msg["agent"]), msg["status"], msg.get("reason", "")))
        except (ValueError, KeyError, TypeError):
            pass

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


def changes(statuses, agent: int, start: float) -> list[tuple[float, str, str]]:
    """An agent's status changes (plan time they began, status, reason); the 1 Hz repeats dropped."""
    out: list[tuple[float, str, str]] = []
    for t, a, status, reason in statuses:
        if a == agent and (not out or out[-1][1] != status):
            out.append((round(t - start, 2), status, reason))
    return out


def log_events(text: str, what: str) -> list[float]:
    """Plan times of a companion's "hold at t_plan X" / "rejoin at t_plan X" log lines."""
    out = []
    for line in text.splitlines():
        if f"{what} at t_plan " in line:
            out.append(float(line.split(f"{what} at t_plan ")[1].split(":")[0]))
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
    why = NetNamespace.problem(tools=("ip",))
    if why:
        pytest.skip(why)
    prefix = next((f"10.77.{k}" for k in range(0, 250) if not subnet_in_use(f"10.77.{k}")), None)
    if prefix is None:
        pytest.skip("no free 10.77.x.0/24 subnet")
    plan = load_plan(str(PAPER_PLAN_FILE))
    t_wall = time.monotonic()
    procs: dict[str, subprocess.Popen] = {}
    logs = []
    for sub in ("logs", "state", "stats", "zenoh"):
        (tmp_path / sub).mkdir()
    monitor = None

    def spawn(net: Hosts, host: str, name: str, cmd: list[str]) -> None:
        log = (tmp_path / "logs" / f"{name}.log").open("w")
        logs.append(log)
        procs[name] = subprocess.Popen(net.exec_prefix(host) + cmd, stdout=log, stderr=subprocess.STDOUT,
                                       cwd=str(Path(__file__).resolve().parents[1]))

    def check_alive() -> None:
        dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
        assert not dead, f"exited early: {dead}: " + "; ".join(
            f"{n}: {(tmp_path / 'logs' / f'{n}.log').read_text()[-1500:]}" for n in dead)

    def sleep_until(t_unix: float) -> None:
        while (left := t_unix - time.time()) > 0:
            time.sleep(min(left, 0.5))
            check_alive()

    rec = watch = None
    net = Hosts(list(HOSTS), f"tsw{os.getpid() % 100000}", prefix)
    with net:
        try:
            # the swarm's PKI: a router per host (reached at the host's address), agents 1-6, the gcs
            routers = {h: pki.Router(net.address[h]) for h in HOSTS}
            pki.init(tmp_path / "pki", SWARM, 6, list(routers.values()))
            generated = tmp_path / "pki" / "zenoh"
            # each host: its router (QUIC to the routers of the hosts after it), its SITL on its own address
            for h in HOSTS:
                spawn(net, h, f"router-{h}", zenoh_router.command(generated / f"{routers[h].name}.json5"))
                spawn(net, h, f"sitl-{h}", [sys.executable, "-m", "triswarm.gcs.cli", "sitl", "up", "-n", str(len(HOSTS[h])),
                                            "--first-id", str(HOSTS[h][0]), "--bind", net.address[h], "--base-port", "0",
                                            "--manifest", str(tmp_path / f"manifest-{h}.json"),
                                            "--stats", str(tmp_path / "stats" / f"sitl-{h}.json"), "--quiet"])
            deadline = time.monotonic() + 60.0
            while not all((tmp_path / f"manifest-{h}.json").exists() for h in HOSTS):
                check_alive()
                assert time.monotonic() < deadline, "the SITLs did not write their manifests within 60 s"
                time.sleep(0.1)
            manifests = {h: json.loads((tmp_path / f"manifest-{h}.json").read_text()) for h in HOSTS}
            # each host's SITL flies its own system ids, bound on the host's address
            for h, ids in HOSTS.items():
                assert [v["sysid"] for v in manifests[h]["vehicles"]] == ids
                assert {v["links"]["gcs"]["host"] for v in manifests[h]["vehicles"]} == {net.address[h]}
            start = time.time() + START_DELAY_S
            gcs_urls = []
            for h, ids in HOSTS.items():
                for v in manifests[h]["vehicles"]:
                    i = v["sysid"]
                    agent_cfg = client_config(generated / f"agent-{i}.json5", routers[h], tmp_path / "zenoh" / f"agent-{i}.json5")
                    gcs_urls.append(f"{i}=udpout:{net.address[h]}:{14550 + i}")
                    spawn(net, h, f"companion-{i}", [
                        sys.executable, "-m", "triswarm.companion.cli", "--id", str(i),
                        "--fc", v["links"]["companion"]["pymavlink"], "--gcs", f"udpin:{net.address[h]}:{14550 + i}",
                        "--plan", str(PAPER_PLAN_FILE), "--autostart", "--start-at", f"{start:.3f}",
                        "--zenoh-config", str(agent_cfg),
                        "--rate-hz", str(RATE_HZ), "--state-dir", str(tmp_path / "state" / str(i)), "--stats", str(tmp_path / "stats" / f"{i}.json")])
            # the root namespace: the flight controllers' own telemetry over the bridge, the bus via router A
            rec = Recorder({"vehicles": [v for h in HOSTS for v in manifests[h]["vehicles"]]}).__enter__()
            watch = BusWatch(client_config(generated / "gcs.json5", routers["a"], tmp_path / "zenoh" / "gcs.json5"))

            # the operator's monitor, from the root namespace to every companion's MAVLink link, all along
            monitor = MonitorTables(triswarm("monitor", *[a for url in gcs_urls for a in ("--drone", url)],
                                             "--rate-hz", "1", "--tlog", str(tmp_path / "gcs.tlog")))
            sleep_until(start + CUT_AT)
            net.link("c", up=False)
            t_cut = time.time() - start
            sleep_until(start + RESTORE_AT)
            net.link("c", up=True)
            t_restore = time.time() - start
            sleep_until(start + END)
            check_alive()  # every process alive to the end
        finally:
            if monitor is not None:
                monitor.close()
            if watch is not None:
                watch.close()
            if rec is not None:
                rec.__exit__(None, None, None)
            # companions first, then the SITLs, then the routers one by one in the order they connect
            # (A to B and C, B to C): a router still trying to reach one that is gone takes 10 s to close
            stop_in_turn([[p for n, p in procs.items() if n.startswith("companion")],
                          [p for n, p in procs.items() if n.startswith("sitl")],
                          *[[procs[f"router-{h}"]] for h in HOSTS if f"router-{h}" in procs]])
            for log in logs:
                log.close()
    assert not net.leftovers(), net.leftovers()
    wall_s = time.monotonic() - t_wall

    def log(name: str) -> str:
        return (tmp_path / "logs" / f"{name}.log").read_text()

    measured: dict = {"cut_s": round(t_cut, 2), "restore_s": round(t_restore, 2), "wall_s": round(wall_s, 1)}
    try:
        late = [line for i in range(1, 7) for line in log(f"companion-{i}").splitlines() if "late for the start" in line]
        assert not late, f"companions not ready {START_DELAY_S:.0f} s after the SITLs: {late}"
        # settled, before the cut: all six
        ok, worst = judge(plan, rec, start, 25.0, CUT_AT)
        measured["all_25_34"] = worst
        assert ok, f"before the cut [25, {CUT_AT}] s: {worst}"
        # the ground station reaches every drone (its companion, and the autopilot behind it); during
        # the cut, C's two are lost to it while the others fly on; after the restore, all six again
        tables = {"before the cut": monitor.last_before(start + CUT_AT),
                  "cut": monitor.last_before(start + 40.0),  # C cut off, 1-4 flying (triangles)
                  "end": monitor.last_before(start + END)}
        measured["monitor"] = {name: {d: (r["link"], r["phase"]) for d, r in t.items()} for name, t in tables.items()}
        for name in ("before the cut", "end"):
            assert sorted(tables[name]) == [str(i) for i in range(1, 7)], (name, tables[name])
            for d, row in tables[name].items():
                assert (row["armed"], row["mode"], row["phase"]) == ("yes", "EXTERNAL", "flying"), (name, d, row)
                assert not row["link"].startswith("lost"), (name, d, row)
        for d, row in tables["cut"].items():
            lost = row["link"].startswith("lost")
            assert lost if d in ("5", "6") else (not lost and row["phase"] == "flying"), (d, row)
        # during the cut, while 1-4 keep a path from the leader (two-chain, triangles)
        assert {plan.schedule.at(t).name for t in np.arange(CUT_AT, 40.0, 0.5)} == {"two-chain", "triangles"}
        ok, worst = judge(plan, rec, start, CUT_AT, 40.0, drones=[1, 2, 3, 4])
        measured["1-4_34_40"] = worst
        assert ok, f"agents 1-4 with a path, [{CUT_AT}, 40] s, host C cut off: {worst}"

        # reverse-two-chain (40-44 s): without 5 and 6, 1-4 have no path; they hold, and say so on Zenoh
        assert plan.schedule.at(42.0).name == "reverse-two-chain"
        status = {i: changes(watch.statuses, i, start) for i in range(1, 7)}
        measured["status_changes"] = status
        for i in (1, 2, 3, 4):
            holds = [(t, reason) for t, s, reason in status[i] if s == "HOLDING" and t > 25.0]
            assert holds and 39.9 < holds[0][0] < 40.6, (i, status[i])
            assert "reverse-two-chain" in holds[0][1], (i, holds)
            back = [t for t, s, _ in status[i] if s == "FLYING" and t > holds[0][0]]
            assert back and RESTORE_AT < back[0] < RESTORE_AT + 5.0, (i, status[i])
            measured.setdefault("1-4_hold_s", {})[i] = round(back[0] - holds[0][0], 2)
            # braking: slower at the end of the hold than at its start (the recorder sees hosts A, B)
            v0, v1 = speed(rec, start, i, 39.5, 40.0), speed(rec, start, i, RESTORE_AT - 0.5, RESTORE_AT)
            measured.setdefault("1-4_speed_40_44", {})[i] = (round(v0, 2), round(v1, 2))
            assert v0 > 5.0 and v1 < 0.75 * v0, (i, v0, v1)

        # 5 and 6, cut off: they hold from the cut (no path in two-chain / triangles without 3 and 4) and
        # fly again when reverse-two-chain pins them to the leader (their logs; nobody outside sees them)
        for i in (5, 6):
            holds, rejoins = log_events(log(f"companion-{i}"), "hold"), log_events(log(f"companion-{i}"), "rejoin")
            measured.setdefault("5-6_holds", {})[i] = holds
            measured.setdefault("5-6_rejoins", {})[i] = rejoins
            during = [t for t in holds if CUT_AT < t < CUT_AT + 2.0]
            assert during, (i, holds)
            # (a tick acts on the graph in force at its end: the switch at 40 s is seen one tick early)
            assert any(40.0 - 1.5 / RATE_HZ <= t < 40.6 for t in rejoins), (i, rejoins)
            assert not [t for t in holds if during[0] < t < 40.0], (i, holds)  # held throughout until 40 s

        # after the restore: all six back within the bounds, within 15 s, and they stay
        t, pe, ae = worst_over_time(plan, rec, start, RESTORE_AT, END)
        out = (pe > POS_BOUND).any(axis=1) | (ae > ATT_BOUND).any(axis=1)
        back_at = float(t[np.nonzero(out)[0][-1] + 1]) if out.any() else RESTORE_AT
        measured["rejoin_s_after_restore"] = round(back_at - RESTORE_AT, 2)
        measured["worst_during_rejoin_m"] = round(float(pe.max()), 2)
        assert back_at - RESTORE_AT <= REJOIN_WITHIN_S, f"back within the bounds {back_at - RESTORE_AT:.1f} s after the restore"
        ok, worst = judge(plan, rec, start, RESTORE_AT + REJOIN_WITHIN_S, END)
        measured["all_59_64"] = worst
        assert ok, f"final window [{RESTORE_AT + REJOIN_WITHIN_S}, {END}] s: {worst}"

        # every companion stopped cleanly and never failed a tick
        for i in range(1, 7):
            assert procs[f"companion-{i}"].returncode == 0, log(f"companion-{i}")[-3000:]
            stats = json.loads((tmp_path / "stats" / f"{i}.json").read_text())
            assert stats["tick_errors"] == 0, (i, stats)
            measured.setdefault("misses", {})[i] = stats["loop"].get("deadline_misses")
    finally:
        print("MEASURED " + json.dumps(measured, default=str))
