"""Valid messages with hostile values (``values.HostileValues``) at a whole stack: ``sitl up`` in
lockstep with two vehicles, a companion for each, Zenoh. One face of vehicle 1 is fuzzed:

- ``sitl-gcs``: the SITL's ground-station link, as a ground station (system 255);
- ``sitl-companion``: the SITL's companion link, as a second companion would (system 1, 191);
- ``routed``: the companion's ground-station link, addressed to the flight controller behind it
  (what the routing forwards, or keeps back), to the companion, and to everyone.

After each batch of ``BATCH`` inputs, vehicle 1 is asked a parameter on the face (through the
companion too, for ``routed``) and vehicle 2 one on its own ground-station link: the fuzz waits for
both answers, so it never floods a socket, and a vehicle that stopped answering, or that another's
input touched, is seen at once. After the fuzz both drones fly a short plan from the ground, as an
operator flies one (uploaded, armed, taken off and started over MAVLink): they must keep its
bounds. No process may have raised: the SITL counts ``handler_exceptions`` (its tracebacks in its
log), the companions' logs are read for tracebacks.
"""

from __future__ import annotations

import random
import socket
import time
import tomllib
from pathlib import Path

from triswarm.gcs import missions
from triswarm.gcs.link import GroundLink
from triswarm.gcs.recorder import Recorder
from triswarm.gcs.stack import Stack
from triswarm.gcs.swarm import start_all, take_off_all
from triswarm.protocol.autopilots import launch_mode_command
from triswarm.protocol.mavlink import COMP_AUTOPILOT, COMP_ONBOARD, mavlink as M, new_codec
from triswarm.protocol.plan_transfer import decode_plan, encode_plan
from triswarm.protocol.plan import plan_from_dict

from .report import Clock, Report, crashes
from .values import COMPANION_PARAMS, HostileValues

BATCH = 64
PROBE_TIMEOUT_S = 20.0
ROOT = Path(__file__).resolve().parents[2]
SITL_PARAMS = ("MOT_MAX_RPM", "MASS_KG", "SC_ATT_HZ", "SG_LPOS_HZ", "TKO_ALT_M", "NOISE_POS_M")
FLY_FROM_S, FLY_TO_S = 20.0, 30.0
"""The window of plan time the flight after the fuzz is judged over (its entry is flown by 15 s)."""
POSITION_BOUND_M, ATTITUDE_BOUND_RAD = 0.10, 0.02
FACES = ("sitl-gcs", "sitl-companion", "routed")


class Asker:
    """A UDP socket that sends to one MAVLink port and reads its answers (pymavlink's parser)."""

    def __init__(self, host: str, port: int, sysid: int = 255, compid: int = 190) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.connect((host, port))
        self.codec = new_codec(sysid, compid)
        self.reader = new_codec(sysid, compid)

    def send(self, data: bytes) -> None:
        for _ in range(100):
            try:
                self.sock.send(data)
                return
            except BlockingIOError:
                time.sleep(0.001)
            except ConnectionRefusedError:  # (an ICMP from a moment the port was not there)
                return

    def ask(self, target: tuple[int, int], name: str, timeout_s: float = PROBE_TIMEOUT_S) -> bool:
        """PARAM_REQUEST_READ of ``name`` from ``target``, again every second, until its PARAM_VALUE."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.send(M.MAVLink_param_request_read_message(*target, name.encode(), -1).pack(self.codec))
            until = min(deadline, time.monotonic() + 1.0)
            while (left := until - time.monotonic()) > 0:
                self.sock.settimeout(left)
                try:
                    data = self.sock.recv(65535)
                except (socket.timeout, ConnectionRefusedError):
                    continue
                for m in self.reader.parse_buffer(data) or []:
                    if (m.get_type() == "PARAM_VALUE" and (m.get_srcSystem(), m.get_srcComponent()) == target
                            and m.param_id == name):
                        return True
        return False

    def close(self) -> None:
        self.sock.close()


def _fly(stack: Stack, plan_spec: dict, report: Report) -> None:
    """Both drones from the ground through a short plan, as an operator flies it; a problem if they
    do not keep its bounds over [FLY_FROM_S, FLY_TO_S] s of plan time."""
    from tests.stack_helpers import judge, wait_sim

    ids = [1, 2]
    items = encode_plan(plan_spec)
    pid = decode_plan(items)[1]
    plan = plan_from_dict(plan_spec, "fuzz-flight")
    with Recorder(stack.manifest) as rec, GroundLink(stack.endpoints()) as link:
        deadline = time.monotonic() + 120.0
        while not all(link.companion(i).heartbeat and link.autopilot(i).heartbeat for i in ids):
            if time.monotonic() > deadline:
                report.problems.append("after the fuzz: a drone or companion was not heard within 120 s")
                return
            time.sleep(0.1)
        for i in ids:
            out = missions.upload(link, i, items)
            if not out.ok:
                report.problems.append(f"after the fuzz: drone {i} refused the plan: {out.detail}")
                return
        for i in ids:
            launch = launch_mode_command(link.autopilot(i).heartbeat.autopilot)
            for command, params in [launch] * (launch is not None) + [(M.MAV_CMD_COMPONENT_ARM_DISARM, (1.0,))]:
                result, texts = link.command(i, COMP_AUTOPILOT, command, list(params))
                if result != M.MAV_RESULT_ACCEPTED:
                    report.problems.append(f"after the fuzz: drone {i} refused command {command}: {result} {texts}")
                    return
        if not all(ok for ok, _ in take_off_all(link, ids).values()):
            report.problems.append("after the fuzz: a drone refused to take off")
            return
        while any(link.autopilot(i).landed_state != M.MAV_LANDED_STATE_IN_AIR for i in ids) or link.fc_now() != link.fc_now():
            if time.monotonic() > deadline + 60.0:
                report.problems.append("after the fuzz: the drones did not take off")
                return
            time.sleep(0.1)
        start = link.fc_now() + 3.0
        if not all(ok for ok, _ in start_all(link, ids, pid, start).values()):
            report.problems.append("after the fuzz: a drone refused the plan's start")
            return
        wait_sim(rec.now, start + FLY_TO_S + 0.5, stack)
        ok, worst = judge(plan, rec, start, FLY_FROM_S, FLY_TO_S, position_bound_m=POSITION_BOUND_M,
                          attitude_bound_rad=ATTITUDE_BOUND_RAD)
    report.other["flight_after_worst_m_rad"] = worst
    if not ok:
        report.problems.append(f"after the fuzz the formation missed its bounds over [{FLY_FROM_S:g}, {FLY_TO_S:g}] s: "
                               f"{worst}")


def small_pair() -> dict:
    """The paper's plan for two drones over the two-chain graph (as the whole-stack tests fly it)."""
    from tests.stack_helpers import small_plan

    return small_plan(tomllib.loads((ROOT / "examples" / "paper-hexagon.toml").read_text()), 2, "pair")


def fuzz_stack(face: str, n: int, workdir: Path, seed: int = 3) -> Report:
    """``n`` hostile valid inputs at ``face`` of vehicle 1, then a flight; the Report's problems."""
    report = Report(face)
    workdir.mkdir(parents=True, exist_ok=True)
    with Stack(None, workdir / "stack", 2, lockstep=True, agents_per_process=0,
               companion_args={1: ["--gcs-frames-per-s", "0"]}) as stack:  # (the handlers under fuzz, not the flood limit)
        v1, v2 = stack.manifest["vehicles"][0]["links"], stack.manifest["vehicles"][1]["links"]
        if face == "routed":
            fuzz = Asker("127.0.0.1", stack.gcs_ports[0])
            makers = [HostileValues(random.Random(seed), fuzz.codec, (1, COMP_AUTOPILOT), SITL_PARAMS),
                      HostileValues(random.Random(seed + 1), fuzz.codec, (1, COMP_ONBOARD), COMPANION_PARAMS)]
            probes = [(fuzz, (1, COMP_ONBOARD), "NB_WAIT_MS"), (fuzz, (1, COMP_AUTOPILOT), "MOT_MAX_RPM")]
        else:
            link = v1["gcs" if face == "sitl-gcs" else "companion"]
            fuzz = Asker(link["host"], link["port"], *((255, 190) if face == "sitl-gcs" else (1, COMP_ONBOARD)))
            makers = [HostileValues(random.Random(seed), fuzz.codec, (1, COMP_AUTOPILOT), SITL_PARAMS)]
            probes = [(fuzz, (1, COMP_AUTOPILOT), "MOT_MAX_RPM")]
        other = Asker(v2["gcs"]["host"], v2["gcs"]["port"])
        probes.append((other, (2, COMP_AUTOPILOT), "MOT_MAX_RPM"))
        try:
            silent = [f"{t} on {'vehicle 2' if asker is other else face}" for asker, t, name in probes
                      if not asker.ask(t, name, timeout_s=120.0)]  # (every face up before the first input)
            if silent:
                report.problems.append(f"before the fuzz no answer from {silent}")
                n = 0
            with Clock() as clock:
                for k in range(n):
                    kind, data = makers[k % len(makers)]()
                    fuzz.send(data)
                    report.sent[kind] += 1
                    report.inputs += 1
                    if (k + 1) % BATCH == 0 or k == n - 1:
                        silent = [f"{t} on {'vehicle 2' if asker is other else face}" for asker, t, name in probes
                                  if not asker.ask(t, name)]
                        if silent:
                            report.problems.append(f"after {k + 1} inputs no answer from {silent}")
                            break
            report.seconds = clock.seconds
        finally:
            fuzz.close()
            other.close()
        if not report.problems:
            _fly(stack, small_pair(), report)
    sitl = stack.stats("sitl")
    counters = [v["counters"] for v in sitl["vehicles"]]
    report.counters = {"handler_exceptions": sitl["handler_exceptions"],
                       **{f"vehicle1.{k}": n for k, n in counters[0].items() if k.startswith(("drop_", "refused_"))},
                       **{f"vehicle2.{k}": n for k, n in counters[1].items() if k.startswith(("drop_", "refused_"))}}
    report.expected = {"handler_exceptions": 0, "vehicle1.drop_handler_error": 0, "vehicle1.drop_unpackable": 0,
                       "vehicle2.drop_handler_error": 0, "vehicle2.drop_unpackable": 0}
    report.compare()
    if any(k.startswith("vehicle2.") and n for k, n in report.counters.items()):
        report.problems.append("vehicle 2 dropped something: vehicle 1's input reached it")
    if face == "routed":
        gcs = stack.stats("1").get("links", {}).get("gcs", {})
        report.other.update({f"companion.{k}": n for k, n in gcs.items() if k in ("kept_from_fc", "refused_own_system")})
    report.problems += [f"crash in the SITL: {c}" for c in crashes(stack.log("sitl"))]
    report.problems += [f"crash in a companion: {c}" for c in crashes(stack.log("companion-1"))]
    return report
