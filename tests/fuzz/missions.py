"""The mission protocol of component 191 under fuzz: random and out-of-order mission messages from
two ground stations, on real UDP to a real companion process.

Each input is one well-formed mission message (byte-level damage is the ground-station face's):
counts (zero, small, too many), items (in order, out of order, duplicates, from the other
station, with fields that are not integers in [0, 2^24): NaN, infinities, fractions, negatives),
downloads of items that do not exist, clears, acks, other mission types, other targets. ``Model``
restates the upload state machine of the mission protocol as documented (companion/plan_server.py's
module text) and counts what the companion should: at the end its counters must equal the
model's. After the fuzz, a whole plan goes up with the ground station's own client
(``gcs.missions.upload``), must be accepted, and must come back down unchanged.
"""

from __future__ import annotations

import math
import random
from collections import Counter
from pathlib import Path

from triswarm.gcs.link import GroundLink
from triswarm.gcs.missions import download, upload
from triswarm.gcs.scenarios import read_plan_spec
from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink as M, new_codec
from triswarm.protocol.plan_transfer import MAX_ITEMS, encode_plan

from .report import Clock, Report, crashes, kernel_drops
from .target import CompanionUnderFuzz

BATCH = 64
AGENT = 1
MISSION = M.MAV_MISSION_TYPE_MISSION
STATIONS = ((255, 190), (254, 190))
PLAN = Path(__file__).resolve().parents[2] / "examples" / "still-hexagon.toml"
BAD_FIELDS = (math.nan, math.inf, -math.inf, 0.5, -1.0, float(1 << 24), 3.4e38)
JUDGED = ("uploads_started", "uploads_restarted", "items_unexpected", "items_out_of_order", "uploads_refused",
          "uploads_cancelled", "uploads_accepted", "upload_timeouts")


class Model:
    """The companion's upload state as the mission protocol documents it, and its counters."""

    def __init__(self) -> None:
        self.upload: tuple[tuple[int, int], int, int] | None = None  # partner, count, next seq
        self.counters: Counter[str] = Counter()

    def take(self, src: tuple[int, int], msg) -> None:
        ts, tc = getattr(msg, "target_system", 0), getattr(msg, "target_component", 0)
        if ts not in (0, AGENT) or tc not in (0, COMP_ONBOARD) or msg.mission_type != MISSION:
            return  # not for component 191, or another mission type (answered UNSUPPORTED)
        t = msg.get_type()
        c = self.counters
        if t == "MISSION_COUNT" and 0 < msg.count <= MAX_ITEMS:
            c["uploads_restarted"] += self.upload is not None
            c["uploads_started"] += 1
            self.upload = (src, msg.count, 0)
        elif t in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            if self.upload is None or self.upload[0] != src:
                c["items_unexpected"] += 1
                return
            partner, count, seq = self.upload
            if msg.seq != seq:
                c["items_out_of_order"] += 1
                return
            fields = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z)
            if seq + 1 == count or not all(0 <= v < 1 << 24 and v == int(v) for v in fields):
                c["uploads_refused"] += 1  # (random items never make a plan: its header and checksum)
                self.upload = None
            else:
                self.upload = (partner, count, seq + 1)
        elif t == "MISSION_ACK" and self.upload is not None and self.upload[0] == src:
            c["uploads_cancelled"] += 1
            self.upload = None


class Inputs:
    """Random mission messages; ``next()`` -> (kind, station index, message)."""

    def __init__(self, rng: random.Random) -> None:
        self.rng = rng
        self.count = {0: 0, 1: 0}
        self.seq = {0: 0, 1: 0}

    def field(self, good: bool) -> float:
        return float(self.rng.randrange(1 << 24)) if good else self.rng.choice(BAD_FIELDS)

    def next(self):
        rng = self.rng
        s = 0 if rng.random() < 0.8 else 1
        ts, tc = (AGENT, COMP_ONBOARD) if rng.random() < 0.95 else rng.choice(((0, 0), (AGENT, 1), (7, COMP_ONBOARD)))
        mt = MISSION if rng.random() < 0.97 else rng.choice((M.MAV_MISSION_TYPE_FENCE, M.MAV_MISSION_TYPE_RALLY, 255))
        kind = rng.choices(("count", "item", "item_float", "request_list", "request", "clear", "ack"),
                           (3, 10, 4, 1, 1, 1, 1))[0]
        if kind == "count":
            n = rng.choice((0, 1, 2, 3, 4, rng.randint(1, 40), MAX_ITEMS, MAX_ITEMS + 1, 65535))
            self.count[s], self.seq[s] = n, 0
            return kind, s, M.MAVLink_mission_count_message(ts, tc, n, mt)
        if kind in ("item", "item_float"):
            seq = self.seq[s] if rng.random() < 0.7 else rng.choice((0, self.seq[s] + 1, max(0, self.seq[s] - 1),
                                                                     rng.randrange(65536)))
            good = rng.random() < 0.9
            f = [self.field(True) for _ in range(7)]
            if not good:
                f[rng.randrange(7)] = self.field(False)
            if seq == self.seq[s]:
                self.seq[s] += 1
            command = rng.choice((31900, 31901, 16, rng.randrange(65536)))
            if kind == "item_float":
                return kind, s, M.MAVLink_mission_item_message(ts, tc, seq, M.MAV_FRAME_MISSION, command, 0, 0, *f, mt)
            x, y = (int(v) if math.isfinite(v) and v == int(v) and abs(v) < 2**31 else -1 for v in f[4:6])
            return kind, s, M.MAVLink_mission_item_int_message(ts, tc, seq, M.MAV_FRAME_MISSION, command, 0, 0, *f[:4],
                                                               x, y, f[6], mt)
        if kind == "request_list":
            return kind, s, M.MAVLink_mission_request_list_message(ts, tc, mt)
        if kind == "request":
            make = rng.choice((M.MAVLink_mission_request_int_message, M.MAVLink_mission_request_message))
            return kind, s, make(ts, tc, rng.choice((0, 1, rng.randrange(65536))), mt)
        if kind == "clear":
            return kind, s, M.MAVLink_mission_clear_all_message(ts, tc, mt)
        return kind, s, M.MAVLink_mission_ack_message(ts, tc, rng.choice((0, 1, 15)), mt)


def fuzz_missions(n: int, workdir: Path, seed: int = 3) -> Report:
    report = Report("missions")
    rng = random.Random(seed)
    model, inputs = Model(), Inputs(rng)
    codecs = [new_codec(*src) for src in STATIONS]
    with CompanionUnderFuzz(workdir, AGENT) as cuf:
        station = cuf.station
        with Clock() as clock:
            for k in range(n):
                kind, s, msg = inputs.next()
                if station.send(msg.pack(codecs[s])):
                    model.take(STATIONS[s], msg)
                    report.sent[kind] += 1
                    report.inputs += 1
                if ((k + 1) % BATCH == 0 or k == n - 1) and not station.probe(AGENT):
                    report.problems.append(f"the companion stopped answering after {k + 1} inputs")
                    break
        report.seconds = clock.seconds
        station.close()
        _valid_upload(report, cuf)
        if kernel_drops(cuf.gcs_port):
            report.problems.append("the kernel dropped datagrams (the counts cannot add up)")
        stats = cuf.stop()
    counters = stats["missions"]
    report.counters = counters
    report.expected = {k: model.counters[k] for k in JUDGED}
    report.expected["uploads_accepted"] = 1  # (the plan sent after the fuzz)
    report.expected["uploads_started"] += 1
    report.expected["uploads_restarted"] += model.upload is not None  # (the fuzz's last upload, if one was open)
    report.other = {k: n for k, n in counters.items() if k not in JUDGED}
    report.compare()
    report.problems += [f"crash: {c}" for c in crashes(cuf.log_tail(10**7))]
    return report


def _valid_upload(report: Report, cuf: CompanionUnderFuzz) -> None:
    """A whole plan up with the ground station's own client, accepted, and the same back down."""
    spec, _ = read_plan_spec(str(PLAN))
    items = encode_plan(spec)
    with GroundLink({AGENT: f"udpout:127.0.0.1:{cuf.gcs_port}"}) as link:
        outcome = upload(link, AGENT, items)
        if not outcome.ok:
            report.problems.append(f"a valid plan was not accepted after the fuzz: {outcome.detail}")
            return
        if download(link, AGENT) != items:
            report.problems.append("the plan downloaded after the fuzz is not the one uploaded")
