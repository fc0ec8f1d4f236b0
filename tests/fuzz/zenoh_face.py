"""The companion's Zenoh keys under fuzz: a real Zenoh session of the fuzzer's, peered with a real
companion process flying nothing yet but holding a plan (so it is on its swarm's bus, listening to
its in-neighbours' estimates), publishes garbage and wrong-typed payloads on the swarm's keys:

- estimates (``triswarm/<swarm>/agent/<j>/estimate`` of each in-neighbour j): random bytes, sizes
  off by a few bytes, a wrong version, status, agent (0, the companion's own, another's), plan
  id, non-finite numbers in the header or in xi, old plan times, a status's JSON;
- statuses (``.../<k>/status``): random bytes, an estimate's bytes, JSON that is not an object,
  wrong types (Infinity, 1e400, lists, null), keys missing, nesting 50,000 deep, an agent that is
  not its key's, out of the swarm, or on a key whose chunk is not a number ("x", "²", "١", 5,000
  digits);
- liveliness tokens on such keys, declared and undeclared.

The oracle: what each input must come to, by the bus's documented checks (companion/bus.py). The
outcome of an estimate whose header is valid (taken, older than one taken with it, or a
non-finite xi) depends on which others the companion read in the same turn; the rest is exact.
The listened-to agents and the plan id come from the companion itself (its health and status).
"""

from __future__ import annotations

import json
import random
import struct
import time
from collections import Counter
from pathlib import Path

import zenoh

from triswarm.companion.zenoh_session import peer_config
from triswarm.gcs.scenarios import read_plan_spec
from triswarm.gcs.stack import free_ports
from triswarm.protocol.codec import (ESTIMATE_SIZE, AgentStatus, Estimate, alive_key, encode_estimate, estimate_key,
                                     health_key, status_key)

from .report import Clock, Report, crashes
from .target import CompanionUnderFuzz

BATCH = 64
PACE_S = 0.01  # after each batch has arrived, and a probe: the companion empties its inboxes (256 each) at every
# tick (100 Hz); under load it may fall behind, and counts what its inboxes push out
AGENT = 1
PLAN = Path(__file__).resolve().parents[2] / "examples" / "paper-hexagon.toml"
BAD_CHUNKS = ("x", "0", "99", "²", "١", "1" * 5000, "-1", "1e3", "01x")
ESTIMATE_KINDS = {"garbage": 2, "resized": 1, "bad_version": 1, "bad_status": 1, "agent_zero": 1, "nonfinite_header": 1,
                  "wrong_agent": 2, "other_plan": 2, "status_json": 1, "valid": 4, "nonfinite_xi": 1, "stale": 1}
PLAUSIBLE = ("valid", "nonfinite_xi", "stale")
"""Estimates with a valid header for a listened-to agent and the plan: their outcome is one of
taken, drop_old or drop_undecodable (a non-finite xi), depending on what came with them."""
STATUS_KINDS = {"valid": 3, "garbage": 1, "estimate_bytes": 1, "not_object": 1, "wrong_types": 2, "missing": 1,
                "deep": 1, "wrong_key_agent": 1, "out_of_swarm": 1, "bad_chunk": 1}
ESTIMATE_OUTCOMES = ("estimates", "drop_undecodable", "drop_unknown_agent", "drop_other_plan", "drop_old",
                     "drop_inbox_full")


class Inputs:
    def __init__(self, rng: random.Random, swarm: str, plan_id: int, listened: list[int], n_agents: int) -> None:
        self.rng, self.swarm, self.plan_id, self.listened, self.n = rng, swarm, plan_id, listened, n_agents
        self.t_plan = 0.0
        self.seq = 0

    def estimate(self, agent: int, plan_id: int | None = None, t_plan: float | None = None, xi=None, **raw) -> bytes:
        self.seq += 1
        if t_plan is None:
            self.t_plan += 0.01
            t_plan = self.t_plan
        xi = [self.rng.uniform(-10, 10) for _ in range(12)] if xi is None else xi
        data = bytearray(encode_estimate(Estimate(agent, self.plan_id if plan_id is None else plan_id, self.seq,
                                                  time.time(), t_plan, AgentStatus.FLYING, xi)))
        for offset, value in raw.items():
            data[int(offset[1:])] = value
        return bytes(data)

    def next_estimate(self) -> tuple[str, str, bytes]:
        rng = self.rng
        kind = rng.choices(list(ESTIMATE_KINDS), list(ESTIMATE_KINDS.values()))[0]
        j = rng.choice(self.listened)
        key = estimate_key(self.swarm, j)
        if kind == "garbage":
            n = rng.choice([rng.randint(0, 300), ESTIMATE_SIZE + rng.choice((-1, 1))])
            return kind, key, rng.randbytes(n if n != ESTIMATE_SIZE else n + 1)
        if kind == "resized":
            good = self.estimate(j)
            return kind, key, good[:rng.randint(0, ESTIMATE_SIZE - 1)] if rng.random() < 0.5 else good + rng.randbytes(rng.randint(1, 64))
        if kind == "bad_version":
            return kind, key, self.estimate(j, o0=rng.choice([0] + list(range(2, 256))))
        if kind == "bad_status":
            return kind, key, self.estimate(j, o1=rng.randint(max(AgentStatus) + 1, 255))
        if kind == "agent_zero":
            return kind, key, self.estimate(0)
        if kind == "nonfinite_header":
            data = bytearray(self.estimate(j))
            struct.pack_into("<d", data, rng.choice((12, 20)), rng.choice((float("nan"), float("inf"), -float("inf"))))
            return kind, key, bytes(data)
        if kind == "wrong_agent":
            other = rng.choice((AGENT, rng.choice(self.listened), rng.randint(2, 65535)))
            return kind, key, self.estimate(other if other != j else AGENT)
        if kind == "other_plan":
            pid = rng.randrange(1 << 32)
            return kind, key, self.estimate(j, plan_id=pid if pid != self.plan_id else pid ^ 1)
        if kind == "status_json":
            return kind, key, json.dumps({"agent": j, "plan": self.plan_id, "status": "FLYING"}).encode()
        if kind == "nonfinite_xi":
            xi = [0.0] * 12
            xi[rng.randrange(12)] = rng.choice((float("nan"), float("inf"), -float("inf")))
            return kind, key, self.estimate(j, xi=xi)
        if kind == "stale":
            return kind, key, self.estimate(j, t_plan=-1e6 - rng.random())
        return kind, key, self.estimate(j)

    def next_status(self) -> tuple[str, str, bytes]:
        """(kind, key, payload): the bus must take the "valid" kind only (``_expected``)."""
        rng = self.rng
        kind = rng.choices(list(STATUS_KINDS), list(STATUS_KINDS.values()))[0]
        k = rng.randint(2, self.n)
        key = status_key(self.swarm, k)
        good = {"agent": k, "plan": self.plan_id, "status": rng.choice([s.name for s in AgentStatus]),
                "reason": "", "since": time.time(), "t": time.time()}
        if kind == "valid":
            return kind, key, json.dumps(good).encode()
        if kind == "garbage":
            return kind, key, rng.randbytes(rng.randint(0, 200))
        if kind == "estimate_bytes":
            return kind, key, self.estimate(k)
        if kind == "not_object":
            return kind, key, rng.choice((b"[1, 2]", b"2", b'"FLYING"', b"null", b"true", b"Infinity"))
        if kind == "wrong_types":
            field = rng.choice(("agent", "status"))
            bad = (rng.choice(("null", "[2]", '{"a": 1}', '"two"', "Infinity", "-Infinity", "NaN", "1e400"))
                   if field == "agent" else rng.choice(('"flying"', "0", "null", "[]", '""', "1e400")))
            text = json.dumps(good).replace(f'"{field}": {json.dumps(good[field])}', f'"{field}": {bad}')
            return kind, key, text.encode()
        if kind == "missing":
            del good[rng.choice(("agent", "status"))]
            return kind, key, json.dumps(good).encode()
        if kind == "deep":
            return kind, key, b"[" * 50000 + b"]" * rng.choice((0, 50000))
        if kind == "wrong_key_agent":
            other = rng.choice([x for x in range(1, self.n + 1) if x != k])
            return kind, status_key(self.swarm, other), json.dumps(good).encode()
        if kind == "out_of_swarm":
            agent = rng.choice((0, self.n + 1, 99, 65536))
            good["agent"] = agent
            return kind, status_key(self.swarm, agent), json.dumps(good).encode()
        return kind, status_key(self.swarm, rng.choice(BAD_CHUNKS)), json.dumps(good).encode()


def fuzz_zenoh(n: int, workdir: Path, seed: int = 4) -> Report:
    report = Report("zenoh")
    rng = random.Random(seed)
    swarm = f"fuzz{rng.randrange(1 << 30)}"
    port = free_ports(1)[0]
    with CompanionUnderFuzz(workdir, AGENT, plan=PLAN, zenoh_base=port - AGENT, swarm=swarm,
                            exclude_ports=frozenset({port})) as cuf:
        session = zenoh.open(peer_config([], [f"tcp/127.0.0.1:{port}"]))
        try:
            health, status = _first_reports(session, swarm)
            listened = sorted(int(j) for j in health["neighbour_age_ms"])
            inputs = Inputs(rng, swarm, status["plan"], listened, read_plan_spec(str(PLAN))[0]["drones"])
            _until_subscribed(session, [estimate_key(swarm, j) for j in listened] + [status_key(swarm, AGENT + 1)])
            lost = _fuzz(report, session, cuf, inputs, n, swarm)
            final = _settle(session, swarm, report, lost)
        finally:
            session.close()
        if not (cuf.alive() and cuf.station.probe(AGENT)):
            report.problems.append("the companion does not answer a valid request after the fuzz")
        if final is None:
            report.problems.append("the companion's counters never accounted for every input")
        stats = cuf.stop()
    counters = stats["zenoh"]
    sent, at_least = report.sent, _expected(report.sent - lost)
    expected = _expected(sent)
    if sum(lost.values()) > n // 4:
        report.problems.append(f"{sum(lost.values())} inputs sent on a link that closed: too few were judged")
    report.counters = dict(counters, estimate_outcomes=sum(counters.get(k, 0) for k in ESTIMATE_OUTCOMES))
    judged = ("estimate_outcomes", "drop_bad_liveliness")
    if not counters.get("drop_inbox_full") and not counters.get("drop_status_inbox_full"):
        judged += ("drop_unknown_agent", "drop_other_plan", "drop_bad_status")
        undecodable = counters.get("drop_undecodable", 0)
        least, most = at_least["header_bad"], expected["header_bad"] + sent["estimate.nonfinite_xi"]
        if not least <= undecodable <= most:
            report.problems.append(f"drop_undecodable {undecodable}: expected {least} to {most}")
        if counters.get("statuses", 0) < at_least["statuses"]:
            report.problems.append(f"statuses {counters.get('statuses', 0)}: expected at least {at_least['statuses']}")
    report.expected = {k: expected[k] for k in judged}
    report.slack = {k: expected[k] - at_least[k] for k in judged if expected[k] != at_least[k]}
    report.other = {"plausible_estimates_sent": sum(sent[f"estimate.{k}"] for k in PLAUSIBLE),
                    "statuses_taken": counters.get("statuses", 0),
                    **{k: counters.get(k, 0) for k in ("drop_inbox_full", "drop_status_inbox_full")}}
    if lost:
        report.other["inputs_on_a_link_that_closed"] = sum(lost.values())
    report.compare()
    report.problems += [f"crash: {c}" for c in crashes(cuf.log_tail(10**7))]
    return report


def _expected(sent: Counter) -> dict[str, int]:
    """What the companion's counters must come to for the inputs ``sent`` (by kind), by the bus's
    documented checks: every estimate has one outcome; the header-invalid ones are undecodable; a
    status is taken only if valid; a token on a bad key is counted at its declaration and again at
    its undeclaration."""
    estimates = {k[9:]: n for k, n in sent.items() if k.startswith("estimate.")}
    statuses = {k[7:]: n for k, n in sent.items() if k.startswith("status.")}
    return {"estimate_outcomes": sum(estimates.values()),
            "drop_unknown_agent": estimates.get("wrong_agent", 0),
            "drop_other_plan": estimates.get("other_plan", 0),
            "header_bad": sum(n for k, n in estimates.items() if k not in PLAUSIBLE + ("wrong_agent", "other_plan")),
            "statuses": statuses.get("valid", 0),
            "drop_bad_status": sum(statuses.values()) - statuses.get("valid", 0),
            "drop_bad_liveliness": 2 * sent.get("liveliness.bad_chunk", 0)}


def _until_subscribed(session, keys: list[str], timeout_s: float = 30.0) -> None:
    """Until this session knows the companion subscribes to each of ``keys``: a put before that is
    dropped here, with no one to route it to (seen: the first batch of a fuzz lost on a busy machine,
    the companion's reports heard before its subscriptions)."""
    pubs = [session.declare_publisher(key) for key in keys]
    try:
        deadline = time.monotonic() + timeout_s
        while not all(pub.matching_status.matching for pub in pubs):
            assert time.monotonic() < deadline, f"the companion's subscriptions to {keys} within {timeout_s:g} s"
            time.sleep(0.05)
    finally:
        for pub in pubs:
            pub.undeclare()


def _first_reports(session, swarm: str, timeout_s: float = 30.0) -> tuple[dict, dict]:
    """The companion's first health report and status (what it listens to, the plan it holds)."""
    with session.declare_subscriber(health_key(swarm, AGENT)) as health_sub, \
            session.declare_subscriber(status_key(swarm, AGENT)) as status_sub:
        health = status = None
        deadline = time.monotonic() + timeout_s
        while (health is None or status is None) and time.monotonic() < deadline:
            for sub, name in ((health_sub, "health"), (status_sub, "status")):
                sample = sub.try_recv()
                if sample is not None:
                    value = json.loads(sample.payload.to_bytes())
                    health, status = (value, status) if name == "health" else (health, value)
            time.sleep(0.05)
    if health is None or status is None:
        raise RuntimeError("the companion published no health report or status on Zenoh")
    return health, status


def _fuzz(report: Report, session, cuf, inputs: Inputs, n: int, swarm: str) -> Counter:
    """n inputs: 60 % estimates, 39 % statuses, the rest liveliness tokens (declared, undeclared).
    Returns what was sent in batches the transport may have dropped: a batch counts as delivered
    once the companion answered a query sent after it on the same link, with no loss of that link
    seen since. (A companion stalled past its Zenoh lease, 1 s, loses its link with everything in
    flight on it; the fuzz then waits for the link and the subscriptions back.)"""
    rng = inputs.rng
    publishers: dict[str, object] = {}
    lost: Counter = Counter()
    batch: Counter = Counter()
    watch = session.liveliness().declare_subscriber(alive_key(swarm, AGENT), zenoh.handlers.FifoChannel(1024))
    keys = [estimate_key(swarm, j) for j in inputs.listened] + [status_key(swarm, AGENT + 1)]

    def put(key: str, data: bytes) -> None:
        pub = publishers.get(key)
        if pub is None:
            pub = publishers[key] = session.declare_publisher(key, reliability=zenoh.Reliability.RELIABLE,
                                                               congestion_control=zenoh.CongestionControl.BLOCK)
        pub.put(data)

    def delivered() -> None:
        """Books the batch just sent as lost unless it reached the companion (and, on a lost link,
        waits for the link and the subscriptions back)."""
        answered = any(reply.ok is not None for reply in session.liveliness().get(alive_key(swarm, AGENT), timeout=10.0))
        went = False
        while (sample := watch.try_recv()) is not None:
            went |= sample.kind == zenoh.SampleKind.DELETE
        if not answered or went:
            lost.update(batch)
            _until_subscribed(session, keys)

    tokens = max(8, n // 200)
    with Clock() as clock:
        for k in range(n - 2 * tokens):
            if rng.random() < 0.6:
                kind, key, data = inputs.next_estimate()
                name = f"estimate.{kind}"
            else:
                kind, key, data = inputs.next_status()
                name = f"status.{kind}"
            put(key, data)
            report.sent[name] += 1
            batch[name] += 1
            report.inputs += 1
            if (k + 1) % BATCH == 0:
                delivered()
                batch.clear()
                time.sleep(PACE_S)
                if not cuf.station.probe(AGENT):  # (the loop turns: it empties the inboxes as it reads)
                    report.problems.append(f"the companion stopped answering after {k + 1} inputs")
                    break
                if len(publishers) > 256:  # (status keys of random chunks: do not keep them all)
                    for pub in publishers.values():
                        pub.undeclare()
                    publishers.clear()
        for pub in publishers.values():
            pub.undeclare()
        if batch:
            delivered()
            batch.clear()
        for _ in range(tokens):
            kind = "bad_chunk" if rng.random() < 0.8 else "agent"
            chunk = rng.choice(BAD_CHUNKS) if kind == "bad_chunk" else str(rng.randint(2, inputs.n))
            token = session.liveliness().declare_token(alive_key(swarm, chunk))
            time.sleep(PACE_S / 4)
            token.undeclare()
            report.sent[f"liveliness.{kind}"] += 1
            batch[f"liveliness.{kind}"] += 1
            report.inputs += 2
        delivered()
    report.seconds = clock.seconds
    watch.undeclare()
    return lost


def _settle(session, swarm: str, report: Report, lost: Counter, timeout_s: float = 30.0) -> dict | None:
    """Wait (bounded) for a health report whose counters account for every input sent (but for
    those sent on a link that closed)."""
    want = _expected(report.sent - lost)
    deadline = time.monotonic() + timeout_s
    with session.declare_subscriber(health_key(swarm, AGENT)) as sub:
        while time.monotonic() < deadline:
            sample = sub.try_recv()
            if sample is None:
                time.sleep(0.1)
                continue
            c = Counter(json.loads(sample.payload.to_bytes())["counters"])
            statuses = c["statuses"] + c["drop_bad_status"] + c["drop_status_inbox_full"]
            if (sum(c[k] for k in ESTIMATE_OUTCOMES) >= want["estimate_outcomes"]
                    and statuses >= want["statuses"] + want["drop_bad_status"]
                    and c["drop_bad_liveliness"] >= want["drop_bad_liveliness"]):
                return dict(c)
    return None
