"""`triswarm monitor`: the rows from fabricated MAVLink messages, the table they render to, the
command against a fake drone (refresh, --duration-s, Ctrl-C), and the whole stack flying two drones."""

from __future__ import annotations

import io
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
import tomli_w
from pymavlink import mavutil
from rich.console import Console

from triswarm.gcs.link import GroundLink, Seen
from triswarm.gcs.monitor import _heard_a_second, rows, table
from triswarm.gcs.stack import Stack
from triswarm.protocol.mavlink import COMP_AUTOPILOT, COMP_ONBOARD, CustomMode, mavlink, new_codec

from .stack_helpers import flying, small_plan
from .poll import poll

NOW = 1_700_000_000.0
ARMED = mavlink.MAV_MODE_FLAG_SAFETY_ARMED


def received(msg, sysid: int, compid: int):
    """The message as a ground station gets it: packed by its sender, parsed from the bytes."""
    return new_codec(255, 190).parse_buffer(msg.pack(new_codec(sysid, compid)))[0]


def fc_heartbeat(sysid: int, mode: int, armed: bool, status: int):
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (ARMED if armed else 0)
    return received(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_TRICOPTER, mavlink.MAV_AUTOPILOT_GENERIC, base,
                                                      mode, status, 3), sysid, COMP_AUTOPILOT)


def companion_heartbeat(sysid: int, phase: int):
    return received(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0,
                                                      phase, mavlink.MAV_STATE_ACTIVE, 3), sysid, COMP_ONBOARD)


def statustext(sysid: int, compid: int, text: str):
    return received(mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_CRITICAL, text.encode()), sysid, compid)


def named(sysid: int, name: str, value: float):
    return received(mavlink.MAVLink_named_value_float_message(0, name.encode(), value), sysid, COMP_ONBOARD)


def heard(*timed) -> Seen:
    """What GroundLink keeps of these (age [s] before NOW, message) pairs."""
    seen = Seen()
    for age, msg in timed:
        at, kind = NOW - age, msg.get_type()
        if kind == "HEARTBEAT":
            seen.heartbeat, seen.heartbeat_at = msg, at
            seen.heartbeats += 1
        elif kind == "NAMED_VALUE_FLOAT":
            seen.named[msg.name] = (msg.value, at)
        else:
            seen.texts.append((at, msg.severity, msg.text))
    return seen


def one(seen: dict, positions: dict | None = None, drone: int = 1) -> dict:
    return rows(seen, positions or {}, [drone], NOW)[0]


def test_failsafe_is_a_critical_heartbeat_while_armed():
    for status, armed, failsafe in ((mavlink.MAV_STATE_CRITICAL, True, True), (mavlink.MAV_STATE_CRITICAL, False, False),
                                    (mavlink.MAV_STATE_ACTIVE, True, False)):
        r = one({(1, COMP_AUTOPILOT): heard((0.1, fc_heartbeat(1, CustomMode.HOLD, armed, status)))})
        assert (r["armed"], r["mode"], r["failsafe"]) == (armed, "HOLD", failsafe)


def test_failsafe_is_a_recent_flight_controller_statustext_not_cleared():
    hb = (0.1, fc_heartbeat(1, CustomMode.EXTERNAL, True, mavlink.MAV_STATE_ACTIVE))
    said = (1.0, statustext(1, COMP_AUTOPILOT, "failsafe: no actuator command for 0.5 s, holding"))
    cleared = (0.5, statustext(1, COMP_AUTOPILOT, "actuator commands back, failsafe cleared"))
    assert one({(1, COMP_AUTOPILOT): heard(hb, said)})["failsafe"]
    assert not one({(1, COMP_AUTOPILOT): heard(hb, said, cleared)})["failsafe"]
    assert not one({(1, COMP_AUTOPILOT): heard(hb, (60.0, said[1]))})["failsafe"]  # long ago
    assert not one({(1, COMP_AUTOPILOT): heard(hb), (1, COMP_ONBOARD): heard(said)})["failsafe"]  # not the FC's


def test_mode_and_phase_names():
    for mode in CustomMode:
        for phase, name in enumerate(("idle", "scheduled", "flying", "holding")):
            r = one({(1, COMP_AUTOPILOT): heard((0.0, fc_heartbeat(1, mode, True, mavlink.MAV_STATE_ACTIVE))),
                     (1, COMP_ONBOARD): heard((0.0, companion_heartbeat(1, phase)))})
            assert (r["mode"], r["phase"]) == (mode.name, name)
    assert one({})["mode"] is None and one({})["phase"] is None
    ardupilot = fc_heartbeat(1, 4, True, mavlink.MAV_STATE_ACTIVE)  # ArduCopter names its modes its own way
    ardupilot.autopilot = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert one({(1, COMP_AUTOPILOT): heard((0.0, ardupilot))})["mode"] == "GUIDED"


def test_ages_values_position_and_last_text():
    position = received(mavlink.MAVLink_local_position_ned_message(0, 1.5, -2.0, -20.0, 0, 0, 0), 1, COMP_AUTOPILOT)
    seen = {
        (1, COMP_AUTOPILOT): heard((0.9, fc_heartbeat(1, CustomMode.EXTERNAL, True, mavlink.MAV_STATE_ACTIVE)),
                                   (4.0, statustext(1, COMP_AUTOPILOT, "takeoff complete, holding"))),
        (1, COMP_ONBOARD): heard((0.7, companion_heartbeat(1, 2)), (0.4, named(1, "FORM_ERRM", 0.031)),
                                 (0.4, named(1, "LOOP_HZ", 200.0)), (0.4, named(1, "JIT_P99MS", 0.75)),
                                 (0.4, named(1, "MISSES", 2.0)), (0.4, named(1, "NB3_AGEMS", 0.9)),
                                 (0.4, named(1, "NB2_AGEMS", 1.2)), (5.0, named(1, "NB4_AGEMS", 1.0)),
                                 (2.5, statustext(1, COMP_ONBOARD, "rejoining the formation"))),
        (2, COMP_ONBOARD): heard((3.3, companion_heartbeat(2, 3))),
    }
    r1, r2, r3 = rows(seen, {1: (NOW - 0.2, position)}, [1, 2, 3], NOW)
    assert r1["age_s"] == pytest.approx(0.2) and r2["age_s"] == pytest.approx(3.3) and r3["age_s"] is None
    assert (r1["form_err_m"], r1["loop_hz"], r1["jitter_p99_ms"], r1["misses"]) == pytest.approx((0.031, 200.0, 0.75, 2.0))
    assert r1["neighbours_ms"] == pytest.approx({2: 1.2, 3: 0.9, 4: None})  # 4 went quiet 5 s ago
    assert r1["position_ned_m"] == (1.5, -2.0, -20.0)
    assert r1["text"] == "rejoining the formation"  # newer than the flight controller's
    assert (r2["phase"], r2["armed"], r2["form_err_m"], r2["position_ned_m"]) == ("holding", None, None, None)

    text = rendered(rows(seen, {1: (NOW - 0.2, position)}, [1, 2, 3], NOW))
    line1, line2, line3 = (line for line in text.splitlines() if line.startswith("│"))
    assert cells(line1)[:8] == ["1", "0.2 s", "yes", "EXTERNAL", "no", "flying", "0.031", "2:1.2 3:0.9 4:- ms"]
    assert cells(line1)[8:] == ["200 Hz p99 0.75 ms 2 missed", "1.5, -2.0, -20.0", "rejoining the formation"]
    assert cells(line2)[:7] == ["2", "lost 3.3 s", "-", "-", "no", "holding", "-"]
    assert cells(line3)[1] == "lost"


def test_once_waits_for_two_heartbeats_of_every_flight_controller_and_companion():
    def beats(fc: int, companion: int, drone: int = 1) -> dict:
        return {(drone, COMP_AUTOPILOT): heard(*[(1.0, fc_heartbeat(drone, CustomMode.EXTERNAL, True, mavlink.MAV_STATE_ACTIVE))] * fc),
                (drone, COMP_ONBOARD): heard(*[(1.0, companion_heartbeat(drone, 2))] * companion)}

    assert _heard_a_second(beats(2, 2), [1]) and _heard_a_second(beats(3, 5), [1])
    assert not _heard_a_second(beats(1, 2), [1]) and not _heard_a_second(beats(2, 1), [1])
    assert not _heard_a_second(beats(2, 0), [1]) and not _heard_a_second({}, [1])
    assert _heard_a_second(beats(2, 2) | beats(2, 2, drone=2), [1, 2])
    assert not _heard_a_second(beats(2, 2) | beats(2, 1, drone=2), [1, 2])
    assert not _heard_a_second(beats(2, 2), [1, 2])  # drone 2 silent


def test_long_statustext_is_truncated():
    long = "x" * 50
    text = rendered(rows({(1, COMP_AUTOPILOT): heard((0.0, statustext(1, COMP_AUTOPILOT, long)))}, {}, [1], NOW))
    last = cells(next(line for line in text.splitlines() if line.startswith("│")))[-1]
    assert last == "x" * 39 + "…"


def rendered(rs: list[dict]) -> str:
    out = Console(width=200, record=True, file=io.StringIO())
    out.print(table(rs))
    return out.export_text()


def cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("│┃").split("│" if "│" in line else "┃")]


def table_rows(output: str) -> dict[str, dict[str, str]]:
    """The last table printed: drone -> column -> cell."""
    lines = output.splitlines()
    start = max(k for k, line in enumerate(lines) if line.startswith("┃"))
    header = cells(lines[start])
    body = [cells(line) for line in lines[start + 1:] if line.startswith("│")]
    return {row[0]: dict(zip(header, row)) for row in body}


def triswarm(*args: str) -> list[str]:
    return [sys.executable, "-m", "triswarm.gcs.cli", *args]


class FakeDrone:
    """A companion and flight controller that only talk: heartbeats and a formation error at 5 Hz to
    whoever spoke last, as a companion does."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.url = f"udpout:127.0.0.1:{self.sock.getsockname()[1]}"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> "FakeDrone":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()

    def _run(self) -> None:
        peer, fc, companion = None, new_codec(1, COMP_AUTOPILOT), new_codec(1, COMP_ONBOARD)
        while not self._stop.is_set():
            try:
                peer = self.sock.recvfrom(65536)[1]
            except socket.timeout:
                pass
            if peer is not None:
                for msg, codec in ((mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_TRICOPTER, mavlink.MAV_AUTOPILOT_GENERIC,
                                                                      ARMED, CustomMode.EXTERNAL, mavlink.MAV_STATE_ACTIVE, 3), fc),
                                   (mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                                                                      mavlink.MAV_AUTOPILOT_INVALID, 0, 2,
                                                                      mavlink.MAV_STATE_ACTIVE, 3), companion),
                                   (mavlink.MAVLink_named_value_float_message(0, b"FORM_ERRM", 0.05), companion)):
                    self.sock.sendto(msg.pack(codec), peer)


def test_plain_tables_for_a_duration_and_ctrl_c_exits_cleanly(tmp_path):
    with FakeDrone() as drone:
        args = triswarm("monitor", "--endpoint", f"1={drone.url}", "--tlog", str(tmp_path / "gcs.tlog"))
        done = subprocess.run([*args, "--duration-s", "1"], capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        assert "\x1b[" not in done.stdout  # plain text, no terminal codes
        assert done.stdout.count("triswarm monitor") >= 5  # one table per 0.2 s, and one at the end
        assert table_rows(done.stdout)["1"]["form err [m]"] == "0.050"

        proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            while "triswarm monitor" not in proc.stdout.readline():
                assert proc.poll() is None, proc.stderr.read()
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=10)
        finally:
            proc.kill()
        assert proc.returncode == 0 and "Traceback" not in err, err


def test_once_prints_the_silent_drones_when_the_wait_is_up(tmp_path):
    with FakeDrone() as drone, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
        silent.bind(("127.0.0.1", 0))
        args = triswarm("monitor", "--endpoint", f"1={drone.url}", "--endpoint", f"2=udpout:127.0.0.1:{silent.getsockname()[1]}",
                        "--tlog", str(tmp_path / "gcs.tlog"), "--once")
        done = subprocess.run([*args, "--wait-s", "1"], capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        drones = table_rows(done.stdout)
        assert (drones["1"]["phase"], drones["1"]["form err [m]"]) == ("flying", "0.050"), done.stdout
        assert (drones["2"]["link"], drones["2"]["phase"]) == ("lost", "-"), done.stdout
        refused = subprocess.run([*args, "--wait-s", "0"], capture_output=True, text=True, timeout=60)
        assert refused.returncode == 2 and "--wait-s must be a positive number, got 0.0" in refused.stderr, refused.stderr


@pytest.mark.slow
def test_once_against_the_stack_flying_two_drones(tmp_path, paper_spec):
    plan_file = tmp_path / "pair.toml"
    plan_file.write_text(tomli_w.dumps(small_plan(paper_spec, 2, "pair")))
    with Stack(plan_file, tmp_path / "stack", 2, start_delay_s=5.0, lockstep=True, agents_per_process=0) as stack:
        with GroundLink(stack.endpoints()) as link:
            poll(lambda: flying(link, 1) and flying(link, 2), 60.0, "both drones in formation")
            # Two ground stations on the same links at once (the monitor, and this link): each
            # gets all of the forwarded telemetry (GCS_TLM_HZ), not a share of it.
            with link.subscribe(None, COMP_AUTOPILOT, "ATTITUDE") as attitudes, \
                    link.subscribe(None, COMP_ONBOARD, "NAMED_VALUE_FLOAT") as named:
                # (--once waits for a second of every drone, however slowly a loaded machine runs
                # the stack; --wait-s only bounds the test)
                started = time.monotonic()
                done = subprocess.run(triswarm("monitor", "--manifest", str(stack.swarm_manifest), "--once",
                                               "--wait-s", "120", "--tlog", str(tmp_path / "monitor.tlog")),
                                      capture_output=True, text=True, timeout=150)
                listened_s = time.monotonic() - started
                tlog = mavutil.mavlink_connection(str(tmp_path / "monitor.tlog"))
                there = [(m.get_srcSystem(), m.time_boot_ms) for m in iter(lambda: tlog.recv_match(type="ATTITUDE"), None)]
                tlog.close()
                assert there, done.stdout + done.stderr
                # this station takes in what came up to the monitor's last frame (its reader may lag
                # behind on a busy machine; the frames of each drone come in order on its link)
                here = []

                def caught_up() -> bool:
                    here.extend((m.get_srcSystem(), m.time_boot_ms) for m in iter(lambda: attitudes.get(0.0), None))
                    return all(max((t for d, t in here if d == drone), default=-1) >= t_last
                               for drone, t_last in dict(sorted(there, key=lambda dt: dt[1])).items())

                poll(caught_up, 60.0, "this station's frames past the monitor's last")
                reported = {}  # drone -> the formation errors its companion reported meanwhile [m]
                for m in iter(lambda: named.get(0.0), None):
                    if m.name == "FORM_ERRM":
                        reported.setdefault(m.get_srcSystem(), set()).add(f"{m.value:.3f}")
    for drone in (1, 2):
        # every frame the monitor got, this station got too; and while the monitor listened, it got
        # every frame this station got. Shared, the stream would go to one station or the other: in
        # turns (the first check fails) or alternately, k frames of 2k - 1, which fails the second
        # from k = 2 on. (Frames are told apart by their time: the simulator sends a state again when
        # its answer is late. How many come while the monitor listens depends on the machine's speed.)
        mine, its = {t for d, t in here if d == drone}, {t for d, t in there if d == drone}
        assert len(its) >= 2 and its <= mine, (drone, sorted(its), sorted(mine))
        during = {t for t in mine if min(its) <= t <= max(its)}
        assert len(its) >= 0.95 * len(during), (drone, len(its), len(during))
    assert done.returncode == 0, done.stdout + done.stderr
    drones = table_rows(done.stdout)
    assert sorted(drones) == ["1", "2"], done.stdout
    for drone, row in drones.items():
        assert (row["armed"], row["mode"], row["failsafe"], row["phase"]) == ("yes", "EXTERNAL", "no", "flying"), done.stdout
        # the formation error shown is one its companion sent (FORM_ERRM) while the monitor listened
        assert row["form err [m]"] in reported.get(int(drone), set()), (drone, row["form err [m]"], reported)
        assert float(row["link"].removesuffix(" s")) < listened_s  # heard while it listened
        assert len(row["position NED [m]"].split(", ")) == 3
