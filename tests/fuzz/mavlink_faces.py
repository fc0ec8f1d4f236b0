"""The companion's two MAVLink faces under fuzz: its ground-station link (unsigned, or signed with a
key) and its flight-controller link, each on real UDP on loopback to a real companion process.

Datagrams come from ``mav.Mutator`` (structure-aware: valid frames with fields, lengths, checksums
and signatures altered, truncations, random bytes), in batches of ``BATCH``: after each, a probe
(a parameter read the companion must answer) both paces the fuzz (no more than a batch waits in the
companion's socket, so the kernel drops nothing) and shows at once a companion that stopped
answering. Every datagram sent, the fuzz's and the peers' own, is also fed to ``mav.LinkModel``,
the oracle: at the end the link's drop and refusal counters must equal the model's.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from pathlib import Path

from triswarm.companion.ground_station import UNSIGNED_FROM_GCS
from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink as M

from .mav import LinkModel, Mutator
from .report import Clock, Report, crashes, drop_keys, kernel_drops
from .target import CompanionUnderFuzz
from .values import COMPANION_PARAMS

BATCH = 64
AGENT = 1
FUZZ_KEY = bytes(range(1, 33))
OUT_OF_ORDER_MS = 300
"""How far before the flight controller's clock the fuzz stamps some attitudes [ms] (the companion takes
a stamp up to 1 s back as out of order, further back as a rebooted clock)."""


def gcs_templates(codec) -> list:
    """What a ground station sends a companion (system 1): to component 191, and through it to the
    flight controller."""
    c = COMP_ONBOARD
    return [M.MAVLink_param_request_read_message(AGENT, c, b"NB_WAIT_MS", -1),
            M.MAVLink_param_request_read_message(AGENT, c, b"", 3),
            M.MAVLink_param_request_list_message(AGENT, c),
            M.MAVLink_param_set_message(AGENT, c, b"GCS_TLM_HZ", 20.0, M.MAV_PARAM_TYPE_REAL32),
            M.MAVLink_param_set_message(AGENT, c, b"NB_TIMEOUT_S", 0.2, M.MAV_PARAM_TYPE_REAL32),
            M.MAVLink_command_long_message(AGENT, c, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_HEARTBEAT,
                                           0, 0, 0, 0, 0, 0),
            M.MAVLink_command_int_message(AGENT, c, 0, M.MAV_CMD_TRISWARM_PLAN_START, 0, 0, 0x1234, 0x5678, 0, 0,
                                          1_900_000_000, 500, 0),
            M.MAVLink_command_long_message(AGENT, c, M.MAV_CMD_TRISWARM_LEADER_GOTO, 0, 1, 2, 3, 0, 10, 0, 0),
            M.MAVLink_command_long_message(AGENT, c, M.MAV_CMD_TRISWARM_LEADER_HOLD, 0, 0, 0, 0, 0, 0, 0, 0),
            M.MAVLink_mission_request_list_message(AGENT, c, M.MAV_MISSION_TYPE_MISSION),
            M.MAVLink_mission_request_int_message(AGENT, c, 0, M.MAV_MISSION_TYPE_MISSION),
            M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3),
            M.MAVLink_command_long_message(AGENT, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                                           0, 0, 0, 0, 0, 0)]


def fc_templates(codec, boot_ms: Callable[[], int] | None = None) -> list:
    """What a flight controller (system 1, component 1) sends its companion. With ``boot_ms`` (the
    flight controller's clock), attitudes stamped a little before its newest telemetry too: out of
    order, whenever the fuzz comes (a fixed stamp falls a second behind the clock during the set-up,
    where the companion takes it for the clock of a rebooted flight controller)."""
    q = [1.0, 0.0, 0.0, 0.0]
    late = [] if boot_ms is None else [
        lambda: M.MAVLink_attitude_message(max(0, boot_ms() - OUT_OF_ORDER_MS), 0.0, 0.0, 0.1, 0.0, 0.0, 0.0),
        lambda: M.MAVLink_attitude_quaternion_message(max(0, boot_ms() - OUT_OF_ORDER_MS), *q, 0.0, 0.0, 0.0, [0.0] * 4)]
    return late + [
            M.MAVLink_heartbeat_message(M.MAV_TYPE_GENERIC, M.MAV_AUTOPILOT_GENERIC,
                                        M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 2, M.MAV_STATE_STANDBY, 3),
            M.MAVLink_attitude_message(1000, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0),
            M.MAVLink_local_position_ned_message(1000, 1.0, -1.0, -2.0, 0.0, 0.0, 0.0),
            M.MAVLink_attitude_quaternion_message(1000, *q, 0.0, 0.0, 0.0, [0.0] * 4),
            M.MAVLink_odometry_message(1_000_000, M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD, 1.0, -1.0, -2.0, q,
                                       0.0, 0.0, 0.0, 0.0, 0.0, 0.0, [0.0] * 21, [0.0] * 21, 0, 0, 100),
            M.MAVLink_highres_imu_message(1_000_000, 0, 0, -9.8, 0, 0, 0, 0, 0, 0, 1013, 0, 0, 20, 0, 0),
            M.MAVLink_system_time_message(1_700_000_000_000_000, 1000),
            M.MAVLink_extended_sys_state_message(0, M.MAV_LANDED_STATE_ON_GROUND),
            M.MAVLink_command_ack_message(M.MAV_CMD_REQUEST_MESSAGE, M.MAV_RESULT_ACCEPTED, 0, 0, AGENT, COMP_ONBOARD),
            M.MAVLink_param_value_message(b"MOT_MAX_RPM", 8000.0, M.MAV_PARAM_TYPE_REAL32, 3, 0),
            M.MAVLink_statustext_message(M.MAV_SEVERITY_INFO, b"fuzz")]


def _fuzz(report: Report, peer, mutator: Mutator, n: int, probe) -> None:
    """``n`` datagrams from ``mutator`` through ``peer``, a probe after each batch."""
    with Clock() as clock:
        for k in range(n):
            kind, data = mutator()
            if peer.send(data):
                report.sent[kind] += 1
                report.inputs += 1
            if (k + 1) % BATCH == 0 or k == n - 1:
                if not probe():
                    report.problems.append(f"the companion stopped answering after {k + 1} inputs")
                    break
    report.seconds = clock.seconds


def _finish(report: Report, cuf: CompanionUnderFuzz, link: str, model: LinkModel, port: int) -> Report:
    """Stop the companion; its link's counters against the model's; the log for crashes."""
    dropped_by_kernel = kernel_drops(port)
    if dropped_by_kernel:
        report.problems.append(f"the kernel dropped {dropped_by_kernel} datagrams (the counts cannot add up)")
    stats = cuf.stop()
    counters = stats["links"][link]
    report.counters = counters
    report.expected = drop_keys(model.counters)
    for key in drop_keys(counters):
        report.expected.setdefault(key, 0)
    report.other = {"rx": counters.get("rx", 0), **{f"telemetry.{k}": n for k, n in stats["telemetry"].items()}}
    report.compare()
    report.problems += [f"crash: {c}" for c in crashes(cuf.log_tail(10**7))]
    if stats["phase"] == "lost":  # (a stamp out of place is dropped, not taken for a reboot: agent.clock_broke)
        said = [line for line in cuf.log_tail(10**6).splitlines() if "flight controller lost" in line]
        report.problems.append(f"the companion counts its flight controller lost after the fuzz: {said[-3:]}")
    return report


def fuzz_gcs(n: int, workdir: Path, seed: int = 1, signed: bool = False) -> Report:
    """The ground-station link: ``n`` datagrams from a ground station (signed ones too if ``signed``:
    the companion then has a signing key, and takes unsigned only what it documents)."""
    report = Report("gcs-signed" if signed else "gcs")
    key = FUZZ_KEY if signed else None
    with CompanionUnderFuzz(workdir, AGENT, signing_key=key) as cuf:
        station = cuf.station
        model = LinkModel(AGENT, COMP_ONBOARD, key, UNSIGNED_FROM_GCS.__contains__ if signed else None)
        station.tap = model.feed  # (from here on; what came before is in neither count)
        mutator = Mutator(random.Random(seed), gcs_templates(station.codec), station.codec, key=key,
                          target=(AGENT, COMP_ONBOARD), param_names=COMPANION_PARAMS)
        _fuzz(report, station, mutator, n, lambda: station.probe(AGENT))
        if not (cuf.alive() and station.probe(AGENT) and station.heartbeat_answered(AGENT)):
            report.problems.append("the companion does not answer a valid request after the fuzz")
        return _finish(report, cuf, "gcs", model, cuf.gcs_port)


def fuzz_fc(n: int, workdir: Path, seed: int = 2) -> Report:
    """The flight-controller link: ``n`` datagrams from the flight controller's own address, among
    its telemetry (which goes on at 100 Hz)."""
    report = Report("fc")
    with CompanionUnderFuzz(workdir, AGENT) as cuf:
        fc = cuf.fc
        model = LinkModel(AGENT, COMP_ONBOARD)
        fc.tap = model.feed  # (from here on: before it, the link took only valid telemetry)
        mutator = Mutator(random.Random(seed), fc_templates(fc.codec, fc.boot_ms), fc.codec, target=(AGENT, COMP_ONBOARD))
        _fuzz(report, fc, mutator, n, lambda: fc.probe(AGENT, source=(42, 1)))
        if not (cuf.alive() and fc.probe(AGENT, source=(42, 1)) and cuf.station.probe(AGENT)):
            report.problems.append("the companion does not answer a valid request after the fuzz")
        return _finish(report, cuf, "fc", model, fc.remote[1])
