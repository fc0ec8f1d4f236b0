"""The ground station's plans and leader commands over MAVLink, against the real stack: two drones
flying (sitl up in lockstep, their companions in one process, Zenoh), the ground station on UDP,
MAVProxy as a third-party client, and a relay of the test's own that cuts an upload in the middle.
Times of plan starts and leader moves are on the flight controllers' clock (the Recorder's)."""

from __future__ import annotations

import copy
import math
import socket
import threading
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from triswarm.gcs import missions
from triswarm.gcs.link import GroundLink
from triswarm.gcs.recorder import Recorder
from triswarm.gcs.stack import Stack
from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink
from triswarm.protocol.plan_transfer import PlanItem, decode_plan, encode_plan, field_value


from .mavproxy_run import mavproxy_until_saved
from .stack_helpers import flying, small_plan, wait_sim
from .poll import poll

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[1]


class CuttableRelay:
    """UDP between the ground station and a companion; ``cut`` drops everything from then on."""

    def __init__(self, target_port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.up = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.up.connect(("127.0.0.1", target_port))
        self.up.settimeout(0.05)
        self.cut = threading.Event()
        self.forwarded = 0
        self._client = None
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._down, daemon=True), threading.Thread(target=self._back, daemon=True)]

    def __enter__(self) -> "CuttableRelay":
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        self.sock.close()
        self.up.close()

    def _down(self) -> None:
        while not self._stop.is_set():
            try:
                data, self._client = self.sock.recvfrom(65536)
            except socket.timeout:
                continue
            if not self.cut.is_set():
                self.forwarded += 1
                self.up.send(data)

    def _back(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.up.recv(65536)
            except (socket.timeout, ConnectionRefusedError):
                continue
            if self._client is not None and not self.cut.is_set():
                self.sock.sendto(data, self._client)


def start(link: GroundLink, drone: int, pid: int, at_unix_s: float):
    return link.command(drone, COMP_ONBOARD, mavlink.MAV_CMD_TRISWARM_PLAN_START, [pid >> 16, pid & 0xFFFF],
                        use_int=True, x=int(at_unix_s), y=int(at_unix_s % 1.0 * 1000.0))


def held_plan_id(link: GroundLink, drone: int) -> int:
    return decode_plan(missions.download(link, drone))[1]


def test_plans_and_leader_over_mavlink(tmp_path, paper_spec):
    import tomllib

    spec = small_plan(paper_spec, 2, "pair")
    plan_file = tmp_path / "pair.toml"
    plan_file.write_text(tomli_w.dumps(spec))
    flying_id = decode_plan(encode_plan(tomllib.loads(plan_file.read_text())))[1]
    with Stack(plan_file, tmp_path / "stack", 2, start_delay_s=5.0, lockstep=True, agents_per_process=0) as stack, \
            Recorder(stack.manifest) as rec:
        with CuttableRelay(stack.gcs_ports[1]) as relay, \
                GroundLink({1: stack.endpoints()[1], 2: f"udpout:127.0.0.1:{relay.port}"}, tlog=tmp_path / "gcs.tlog") as link:
            poll(lambda: flying(link, 1) and flying(link, 2), 90, "both drones in formation")
            wait_sim(rec.now, stack.start_at + 15.0, stack)  # the entry is over at 15 s of plan time

            # an infeasible plan sent by a raw client: refused with the code and the reason
            bad = copy.deepcopy(spec)  # a velocity offset with a constant position: fails (76)
            bad["formation"] = {"type": "constant", "offsets": [[1.0] + [0.0] * 8 + [0.0, 0.0, 10.0],
                                                                [0.0] * 9 + [1.0, 0.0, 10.0]]}
            out = missions.upload(link, 1, encode_plan(bad))
            assert not out.ok and out.code == mavlink.MAV_MISSION_INVALID, out
            assert "plan refused" in out.detail

            # an upload cut in the middle: the companion gives up, the plan in force flies on
            new = copy.deepcopy(spec)
            new["formation"]["radius_m"] = 8.0
            items = encode_plan(new)
            sent = []

            def cut_after_five(k: int) -> None:
                sent.append(k)
                if k == 5:
                    relay.cut.set()

            out = missions.upload(link, 2, items, progress=cut_after_five, timeout_s=0.3, retries=3)
            assert not out.ok and 5 <= max(sent) < len(items)  # (a request may be in flight at the cut)
            relay.cut.clear()  # the ground station has given up; the companion asks on, then gives up too
            poll(lambda: any(f"upload timed out at item {k}/{len(items)}" in text for _, _, text in link.companion(2).texts
                                 for k in range(4, max(sent) + 1)), 10,
                     "the companion's timeout (1 s, 5 retries)")
            assert held_plan_id(link, 2) == flying_id
            assert flying(link, 2)
            out = missions.upload(link, 2, items)  # the retry
            assert out.ok, out
            assert held_plan_id(link, 2) == flying_id  # staged, not in force: it waits for its start

            # in flight, a new plan may change the formation, not the design
            other = copy.deepcopy(spec)
            other["design"]["coupling_margin"] = 2.0
            assert missions.upload(link, 1, encode_plan(other)).ok
            result, why = start(link, 1, decode_plan(encode_plan(other))[1], rec.now() + 2.0)
            assert result == mavlink.MAV_RESULT_DENIED and "not design; land first" in why

            # the new formation (radius 8 m instead of 10) takes over on both at one time: the two
            # drones, opposite on the circle, end up 16 m apart instead of 20. Its t = 0 is its start,
            # chosen at a whole turn of the old one (1 rad/s), so only the radius changes
            assert missions.upload(link, 1, items).ok
            pid = decode_plan(items)[1]
            at = stack.start_at + 2 * math.pi * math.ceil((rec.now() + 2.0 - stack.start_at) / (2 * math.pi))
            result, why = start(link, 1, pid, at + math.pi)  # half a turn off: 18 m from the old formation
            assert result == mavlink.MAV_RESULT_DENIED and "start it where the two meet" in why
            for i in (1, 2):
                result, why = start(link, i, pid, at)
                assert result == mavlink.MAV_RESULT_ACCEPTED, why
            wait_sim(rec.now, at + 8.0, stack)
            t_now = rec.now() - stack.start_at
            _, pos, _ = rec.arrays(stack.start_at, t_from=t_now - 1.5, t_to=t_now - 0.5)
            np.testing.assert_allclose(np.linalg.norm(pos[:, 0] - pos[:, 1], axis=1), 16.0, atol=0.1)
            assert held_plan_id(link, 1) == held_plan_id(link, 2) == pid
            assert flying(link, 1) and flying(link, 2)

            # a leader move past the airframe's limits (40 m in 1 s: about 230 m/s^2) is refused
            # with the reason, and changes nothing
            t_plan = link.param(1, COMP_ONBOARD, "PLAN_T_S")
            result, why = link.command(1, COMP_ONBOARD, mavlink.MAV_CMD_TRISWARM_LEADER_GOTO,
                                       [100.0, float("nan"), t_plan + 1.0, 0.0, 45.0, 5.0, 0.0])
            assert result == mavlink.MAV_RESULT_DENIED and "the move cannot be flown" in why, why
            assert "past the motor limit (12000 RPM)" in why, why

            # the leader moves 6 m north at 2 m/s on both drones at once, to 11 m north and 5 m east
            # of home, given in NED as MAVLink has it (the plan's frame has y west: y = -5 m): the pair's midpoint (the centre of a
            # two-drone polygon) follows it
            t_plan = link.param(1, COMP_ONBOARD, "PLAN_T_S")
            at = t_plan + 1.0
            for i in (1, 2):
                result, why = link.command(i, COMP_ONBOARD, mavlink.MAV_CMD_TRISWARM_LEADER_GOTO,
                                           [2.0, float("nan"), at, 0.0, 11.0, 5.0, 0.0])
                assert result == mavlink.MAV_RESULT_ACCEPTED, why
            move_s = 1.875 * 6.0 / 2.0
            wait_sim(rec.now, stack.start_at + at + move_s + 4.0, stack)
            t_now = rec.now() - stack.start_at  # the last second, from the flight controllers' own telemetry
            _, pos, _ = rec.arrays(stack.start_at, t_from=t_now - 1.5, t_to=t_now - 0.5)
            np.testing.assert_allclose(pos.mean(axis=1), np.tile([11.0, -5.0, 20.0], (len(pos), 1)), atol=0.1)
            assert flying(link, 1) and flying(link, 2)

        # MAVProxy, a third-party client, downloads the plan drone 1 holds from component 191
        saved = tmp_path / "plan.txt"
        args = [f"--master={stack.endpoints()[1]}", "--target-system=1", "--target-component=191", "--source-system=254"]
        count, path = mavproxy_until_saved(args, f"wp save {saved}", tmp_path)
        assert path == saved and count == len(items)
        rows = [line.split("\t") for line in saved.read_text().splitlines()[1:] if line.strip()]
        items = [PlanItem(int(r[3]), tuple(field_value(round(float(v), 6), "wpl") for v in r[4:11])) for r in rows]
        spec_back, pid_back = decode_plan(items)
        assert pid_back == pid and spec_back["formation"]["radius_m"] == 8.0
