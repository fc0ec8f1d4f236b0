"""A fault survived: a ground station (or a script gone wrong) floods a companion with commands,
parameters and missions mid-flight. Three drones, the whole stack on simulated time (lockstep);
the flood comes from a real pymavlink client on companion 1's ground-station port, FLOOD_FRAMES
frames at FLOOD_HZ of wall time, of every kind a ground station sends: commands for the companion
(a heartbeat asked for, leader moves as COMMAND_INT and COMMAND_LONG that each pass the airframe's
check), commands for the flight controller behind it, parameter reads, lists and sets, mission
downloads.

What must hold, each with its bound:

* the formation stays within the paper's bounds through the flood, judged from the flight
  controllers' own telemetry;
* the loop is never stalled: no companion is taken out of lockstep (its answer overdue by 10 s of
  wall time);
* the flooder is answered for what its bucket allows, no more: its answers heard by the end of the
  window number at most GCS_FRAMES_BURST + GCS_FRAMES_PER_S x the wall time since the flood began;
  leader moves checked (ACCEPTED or DENIED, not TEMPORARILY_REJECTED) at most CHECKED_CMDS_BURST +
  CHECKED_CMDS_PER_S x that time; frames reaching flight controller 1 likewise (bounds in count,
  each holding however fast or slow the machine);
* the real ground station, during the flood, has its parameter read, its command and its leader
  move answered (ACCEPTED);
* the drops are counted (``gcs_shed`` in the health report) and the flood is said once when it
  begins and once when it ends."""

import contextlib
import json
import math
import threading
import time

import pytest
import tomli_w
from pymavlink import mavutil

from triswarm.companion.ground_station import (CHECKED_CMDS_BURST, CHECKED_CMDS_PER_S, FC_FORWARD_BURST,
                                               FC_FORWARD_PER_S, GCS_FRAMES_BURST, GCS_FRAMES_PER_S)
from triswarm.gcs.recorder import Recorder
from triswarm.gcs.stack import Stack
from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink

from .stack_helpers import BusObserver, GroundStation, judge, small_plan, wait_sim
from .poll import poll

# (real time: the flood is paced on the wall clock, the answers during it are judged against its 10 s
# and the buckets' bounds against the wall time it took; the lockstep watchdog is on the wall too)
pytestmark = [pytest.mark.slow, pytest.mark.realtime]
N = 3
SWARM = "trio"
FLOOD_AT = 17.0  # plan time: the entry is over at 15 s
FLOOD_FRAMES = 30_000
FLOOD_HZ = 3_000.0  # frames a second of wall time (10 s of flood)
FLOODER = 250  # its system id
LEADER_NED_M = (5.0, 5.0, 0.0)  # the plan's leader, (5, -5, 0) in the plan's frame: a goto there moves nothing
AFTER_S = 3.0  # plan time judged after the flood


class Flooder:
    """A pymavlink client on a companion's ground-station port sending ``count`` frames at ``hz``,
    reading what comes back; each frame built by pymavlink's own encoder."""

    def __init__(self, port: int, count: int, hz: float, at_s: float) -> None:
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=FLOODER, source_component=190)
        self.count, self.hz, self.at_s = count, hz, at_s
        self.sent = 0
        self.heard: list = []
        self.started = self.ended = math.nan
        self._thread = threading.Thread(target=self._run, daemon=True)

    def frames(self, k: int):
        mav, t = self.conn.mav, mavlink
        at_s = self.at_s + 1e-4 * k  # (each move a new one, later than the one before)
        kind = k % 9
        if kind == 0:
            return mav.command_long_encode(1, COMP_ONBOARD, t.MAV_CMD_REQUEST_MESSAGE, 0, t.MAVLINK_MSG_ID_HEARTBEAT,
                                           0, 0, 0, 0, 0, 0)
        if kind == 1:
            return mav.command_int_encode(1, COMP_ONBOARD, t.MAV_FRAME_LOCAL_NED, t.MAV_CMD_TRISWARM_LEADER_GOTO, 0, 0,
                                          1.0, math.nan, at_s, 0, round(LEADER_NED_M[0] * 1000),
                                          round(LEADER_NED_M[1] * 1000), LEADER_NED_M[2])
        if kind == 2:
            return mav.command_long_encode(1, COMP_ONBOARD, t.MAV_CMD_TRISWARM_LEADER_GOTO, 0, 1.0, math.nan, at_s, 0,
                                           *LEADER_NED_M)
        if kind == 3:
            return mav.param_set_encode(1, COMP_ONBOARD, b"NB_WAIT_MS", 1.0, t.MAV_PARAM_TYPE_REAL32)
        if kind == 4:
            return mav.param_request_read_encode(1, COMP_ONBOARD, b"CTRL_RATE_HZ", -1)
        if kind == 5:
            return mav.param_request_list_encode(1, COMP_ONBOARD)
        if kind == 6:
            return mav.mission_request_list_encode(1, COMP_ONBOARD, t.MAV_MISSION_TYPE_MISSION)
        if kind == 7:  # for the flight controller behind the companion
            return mav.command_long_encode(1, 1, t.MAV_CMD_REQUEST_MESSAGE, 0, t.MAVLINK_MSG_ID_HEARTBEAT,
                                           0, 0, 0, 0, 0, 0)
        return mav.heartbeat_encode(t.MAV_TYPE_GCS, t.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def start(self) -> None:
        self._thread.start()

    def join(self, timeout_s: float) -> None:
        self._thread.join(timeout_s)
        assert not self._thread.is_alive(), f"the flood did not end within {timeout_s} s"

    def close(self) -> None:
        self.conn.close()

    def _run(self) -> None:
        self.started = time.monotonic()
        while self.sent < self.count:
            due = min(self.count, int((time.monotonic() - self.started) * self.hz) + 1)
            while self.sent < due:
                self.conn.mav.send(self.frames(self.sent))
                self.sent += 1
            self.read()
            time.sleep(0.002)
        self.ended = time.monotonic()

    def read(self) -> None:
        while (msg := self.conn.recv_match(blocking=False)) is not None:
            if msg.get_type() != "BAD_DATA":
                self.heard.append((time.monotonic(), msg))

    def last_answered(self, timeout_s: float) -> None:
        """Until the companion answers a parameter read sent now (again every 0.1 s while its bucket
        sheds it): it takes the link's frames in order, so the answers to the flood are in by then."""
        asked = lambda: self.conn.mav.param_request_read_send(1, COMP_ONBOARD, b"REJOIN_S", -1)  # noqa: E731
        answered = lambda: any(m.get_type() == "PARAM_VALUE" and m.param_id == "REJOIN_S" for _, m in self.heard)  # noqa: E731
        poll(lambda: (self.read(), answered())[1], timeout_s, "the answer to a read after the flood",
             every_s=0.1, step=asked)

    def acks(self, until: float, component: int = COMP_ONBOARD) -> list:
        """The COMMAND_ACKs to this client from ``component`` of system 1, heard until ``until``."""
        return [m for t, m in self.heard if t <= until and m.get_type() == "COMMAND_ACK" and m.target_system == FLOODER
                and m.get_srcSystem() == 1 and m.get_srcComponent() == component]


def test_a_ground_station_flood_is_shed_and_the_formation_holds(tmp_path, paper_spec):
    plan_file = tmp_path / "trio.toml"
    plan_file.write_text(tomli_w.dumps(small_plan(paper_spec, N, SWARM)))
    from triswarm.gcs.scenarios import load_plan

    plan = load_plan(str(plan_file))
    measured: dict = {}
    t_open = time.monotonic()
    with Stack(plan_file, tmp_path / "stack", N, start_delay_s=5.0, lockstep=True, agents_per_process=0) as stack, \
            Recorder(stack.manifest) as rec, BusObserver(SWARM, stack.zenoh_base, N) as bus, \
            GroundStation(stack.gcs_ports[0]) as gcs, contextlib.ExitStack() as cleanup:
        start = stack.start_at
        wait_sim(rec.now, start + FLOOD_AT, stack)
        flooder = Flooder(stack.gcs_ports[0], FLOOD_FRAMES, FLOOD_HZ, rec.now() - start + 1.0)
        flooder.start()
        cleanup.callback(flooder.close)
        poll(lambda: flooder.sent > FLOOD_FRAMES // 4, 30.0, "a quarter of the flood sent")
        flood_port = flooder.conn.port.getsockname()[1]  # (bound by its first send; read before it closes)

        # the real ground station, in the flood: a parameter read, a command, a leader move
        t_plan = rec.now() - start
        gcs.send(gcs.conn.mav.param_request_read_encode(1, COMP_ONBOARD, b"REJOIN_S", -1))
        gcs.send(gcs.conn.mav.command_long_encode(1, COMP_ONBOARD, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                                  mavlink.MAVLINK_MSG_ID_HEARTBEAT, 0, 0, 0, 0, 0, 0))
        gcs.send(gcs.conn.mav.command_long_encode(1, COMP_ONBOARD, mavlink.MAV_CMD_TRISWARM_LEADER_GOTO, 0, 1.0,
                                                  math.nan, t_plan + 30.0, 0, *LEADER_NED_M))
        assert gcs.wait_for("PARAM_VALUE", 10.0, param_id="REJOIN_S", srcComponent=COMP_ONBOARD), "no answer in the flood"
        for command in (mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_CMD_TRISWARM_LEADER_GOTO):
            acks = gcs.wait_for("COMMAND_ACK", 10.0, target_system=255, command=command)
            assert acks and acks[-1].result == mavlink.MAV_RESULT_ACCEPTED, (command, acks)
        answered_during = flooder.sent < FLOOD_FRAMES  # (the flood still on when they were answered)

        flooder.join(FLOOD_FRAMES / FLOOD_HZ + 60.0)
        t_end_plan = rec.now() - start
        flooder.last_answered(10.0)  # (the last answers on their way)
        window_end = time.monotonic()
        wall_s = window_end - flooder.started
        wait_sim(rec.now, start + t_end_plan + AFTER_S, stack)
        poll(lambda: "flood over" in stack.log("companion-1"), 10.0, "the end of the flood said")
        health = bus.health[1][-1]
        gcs_sent = 3 + math.ceil(time.monotonic() - t_open)  # (its heartbeat once a second, and the three above)
    wall_total_s = time.monotonic() - flooder.started  # (until the companions stopped)

    ok, worst = judge(plan, rec, start, FLOOD_AT, t_end_plan + AFTER_S)
    acks, fc_acks = flooder.acks(window_end), flooder.acks(window_end, component=1)
    checked = [m for m in acks if m.command == mavlink.MAV_CMD_TRISWARM_LEADER_GOTO
               and m.result != mavlink.MAV_RESULT_TEMPORARILY_REJECTED]
    link = stack.stats("1")["links"]["gcs"]
    fc_commands = [v["counters"].get("commands", 0) for v in stack.stats("sitl")["vehicles"]]
    measured = dict(flood_wall_s=round(flooder.ended - flooder.started, 2), window_wall_s=round(wall_s, 2),
                    flood_plan_s=(FLOOD_AT, round(t_end_plan, 2)), gcs_shed=health["gcs_shed"], link=link,
                    acks=len(acks), fc_acks=len(fc_acks), leader_moves_checked=len(checked), fc_commands=fc_commands,
                    worst=worst)
    print("MEASURED " + json.dumps(measured))
    assert answered_during, measured
    assert ok, f"through the flood [{FLOOD_AT}, {t_end_plan + AFTER_S:.1f}] s: {worst}"
    sitl = stack.stats("sitl")
    assert sitl["lockstep"]["left"] == [], sitl["lockstep"]  # no companion stalled out of lockstep

    # answered what its buckets allow, and no more (counts, on any machine)
    assert 0 < len(acks) <= GCS_FRAMES_BURST + GCS_FRAMES_PER_S * wall_s, measured
    assert 0 < len(checked) <= CHECKED_CMDS_BURST + CHECKED_CMDS_PER_S * wall_s, measured
    assert 0 < len(fc_acks), measured  # (what it forwards still reaches the flight controller)
    assert fc_commands[0] - fc_commands[1] <= min(GCS_FRAMES_BURST + GCS_FRAMES_PER_S * wall_total_s,
                                                  FC_FORWARD_BURST + FC_FORWARD_PER_S * wall_total_s), measured
    # every frame of the flood read or counted as dropped by the kernel; what was read and not shed
    # is within the two senders' buckets
    assert link["rx"] + link.get("drop_kernel", 0) >= FLOOD_FRAMES, measured
    assert link["rx"] - link["shed_frames"] <= GCS_FRAMES_BURST + GCS_FRAMES_PER_S * wall_total_s + gcs_sent, measured
    assert health["gcs_shed"]["shed_frames"] > 0 and health["gcs_shed"]["shed_commands"] > 0, measured

    log = stack.log("companion-1")
    port = flood_port
    assert log.count(f"ground station at 127.0.0.1:{port} floods") == 1, log[-3000:]  # said once
    assert log.count(f"ground station at 127.0.0.1:{port}: flood over") == 1, log[-3000:]
    for i in range(1, N + 1):
        assert stack.stats(str(i))["tick_errors"] == 0
