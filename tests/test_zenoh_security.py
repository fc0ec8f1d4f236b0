"""Zenoh mTLS and access control with certificates made by gcs/pki.py, with real Zenoh sessions in
this process on loopback: agents reach each other through the mTLS router; a client without a
certificate, or with one from another CA, is refused; the router drops an agent's puts and
liveliness tokens on another agent's keys; the ground station reads all and writes nothing; two
routers link up and each enforces; the companion's Bus runs on a generated configuration.

"Refused" means: ``zenoh.open`` raises, or the session it returns reached no router and nothing
passes through it either way within REFUSED_WAIT_S (a put from it reaches no authorised subscriber,
and an authorised put does not reach it)."""

from __future__ import annotations

import asyncio
import json
import os
import stat
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from pathlib import Path

import numpy as np
import pytest
import typer
import zenoh
from typer.testing import CliRunner

from triswarm.companion.bus import Bus
from triswarm.companion.zenoh_session import tune
from triswarm.gcs import pki
from triswarm.gcs.pki_cmd import pki_app
from triswarm.gcs.stack import free_ports
from triswarm.protocol.codec import AgentStatus, alive_key, estimate_key

from .test_bus import PLAN, XI, until
from .poll import poll

DENIED_PUTS = 20        # denied puts sent before the allowed one that proves they would have arrived
REFUSED_WAIT_S = 2.0
OPEN_TIMEOUT_S = 15.0   # bound on zenoh.open itself (a refused one raises in milliseconds)
DEPLOY = Path(__file__).resolve().parents[1] / "deploy" / "zenoh"


class Swarm:
    def __init__(self, root: Path):
        self.name = f"sec-{uuid.uuid4().hex[:8]}"
        self.port = free_ports(1)[0]
        self.dir = root / "pki"
        self.report = pki.init(self.dir, self.name, 3, [f"127.0.0.1:{self.port}"], listen_host="127.0.0.1")
        # another CA, with the same names (the same issuer DN): only its signature differs
        self.other = root / "other-pki"
        pki.init(self.other, self.name, 3, [f"127.0.0.1:{self.port}"], listen_host="127.0.0.1")

    def config(self, name: str) -> zenoh.Config:
        return zenoh.Config.from_file(str(self.dir / "zenoh" / f"{name}.json5"))

    def est(self, agent: int) -> str:
        return estimate_key(self.name, agent)


@pytest.fixture(scope="module")
def swarm(tmp_path_factory):
    return Swarm(tmp_path_factory.mktemp("zenoh-security"))


@pytest.fixture(scope="module")
def router(swarm):
    session = open_bounded(swarm.config("router-127.0.0.1"))
    yield session
    session.close()


def open_bounded(config: zenoh.Config) -> zenoh.Session:
    """zenoh.open, failing the test instead of hanging if it does not return in OPEN_TIMEOUT_S."""
    pool = ThreadPoolExecutor(1)
    try:
        return pool.submit(zenoh.open, config).result(timeout=OPEN_TIMEOUT_S)
    except FutureTimeout:
        pytest.fail(f"zenoh.open did not return in {OPEN_TIMEOUT_S} s")
    finally:
        pool.shutdown(wait=False)


class Sessions:
    """Client sessions of one test and what they declared (kept alive: Zenoh undeclares a dropped
    subscriber), all closed at its end."""

    def __init__(self):
        self.sessions = []
        self.entities = []

    def open(self, config: zenoh.Config) -> zenoh.Session:
        s = open_bounded(config)
        self.sessions.append(s)
        return s

    def keep(self, entity):
        self.entities.append(entity)
        return entity

    def collect(self, session: zenoh.Session, key: str) -> list[bytes]:
        """Every payload a new subscriber of ``session`` on ``key`` receives."""
        got: list[bytes] = []
        self.keep(session.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes())))
        return got

    def close(self):
        self.entities.clear()
        for s in reversed(self.sessions):
            s.close()


@pytest.fixture
def clients():
    c = Sessions()
    yield c
    c.close()


# -- the files ---------------------------------------------------------------------------------

def openssl_text(*args: str) -> str:
    return pki._openssl(*args).decode()


def test_pki_files_and_configs(swarm):
    d = swarm.dir
    for name in ["ca", "router-127.0.0.1", "agent-1", "agent-2", "agent-3", "gcs"]:
        assert (d / f"{name}.pem").is_file()
        assert stat.S_IMODE(os.stat(d / f"{name}.key").st_mode) == 0o600, name
    for name in ["agent-1", "agent-3", "gcs"]:
        assert pki.common_name(d / f"{name}.pem") == name
        assert openssl_text("verify", "-CAfile", str(d / "ca.pem"), "-purpose", "sslclient", str(d / f"{name}.pem")).strip().endswith("OK")
    router_cert = d / "router-127.0.0.1.pem"
    assert pki.alt_names(router_cert) == {"IP:127.0.0.1"}
    assert openssl_text("verify", "-CAfile", str(d / "ca.pem"), "-purpose", "sslserver", str(router_cert)).strip().endswith("OK")
    # an agent's certificate is not a server's
    with pytest.raises(pki.PkiError):
        pki._openssl("verify", "-CAfile", str(d / "ca.pem"), "-purpose", "sslserver", str(d / "agent-1.pem"))

    cfg = swarm.config("agent-2")
    assert json.loads(cfg.get_json("mode")) == "client"
    assert json.loads(cfg.get_json("connect/endpoints")) == [f"tls/127.0.0.1:{swarm.port}"]
    tls = json.loads(cfg.get_json("transport/link/tls"))
    assert tls["enable_mtls"] is True and tls["connect_certificate"] == str((d / "agent-2.pem").resolve())
    acl = json.loads(swarm.config("router-127.0.0.1").get_json("access_control"))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    writes = {r["id"]: r["key_exprs"] for r in acl["rules"] if r["id"].endswith("-write")}
    assert writes == {f"agent-{i}-write": [f"triswarm/{swarm.name}/agent/{i}/**"] for i in (1, 2, 3)}
    # the shipped examples parse (their placeholder paths are only read when a link opens)
    for example in ("router-mtls.json5", "companion-mtls.json5"):
        zenoh.Config.from_file(str(DEPLOY / example))


def test_init_is_idempotent_and_cli(tmp_path):
    out = tmp_path / "pki"
    app = typer.Typer()
    app.add_typer(pki_app, name="pki")
    args = ["pki", "init", "--out", str(out), "--swarm", "s", "--drones", "2", "--router", "10.1.2.3:7500",
            "--router", "gs.example.org"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert stat.S_IMODE(os.stat(out).st_mode) == 0o700
    assert pki.alt_names(out / "router-gs.example.org.pem") == {"DNS:gs.example.org"}
    router = json.loads(zenoh.Config.from_file(str(out / "zenoh" / "router-10.1.2.3.json5")).get_json("connect/endpoints"))
    assert router == ["quic/gs.example.org:7447"]  # each pair of routers linked once, over QUIC
    last = zenoh.Config.from_file(str(out / "zenoh" / "router-gs.example.org.json5"))
    assert json.loads(last.get_json("connect/endpoints")) == []
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}

    report = pki.init(out, "s", 3, ["10.1.2.3:7500", "gs.example.org"])  # one more drone
    assert sorted(p.name for p in report.made) == ["agent-3.key", "agent-3.pem"]
    after = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert all(after[name] == data for name, data in before.items())
    assert (out / "zenoh" / "agent-3.json5").is_file()

    (out / "agent-1.pem").write_bytes((out / "agent-2.pem").read_bytes())  # a wrong name: remade
    assert {p.name for p in pki.init(out, "s", 3, ["10.1.2.3:7500", "gs.example.org"]).made} == {"agent-1.pem", "agent-1.key"}

    result = CliRunner().invoke(app, args + ["--force"])
    assert result.exit_code == 0, result.output
    assert (out / "ca.pem").read_bytes() != before["ca.pem"]

    result = CliRunner().invoke(app, ["pki", "init", "--out", str(out), "--swarm", "a/b", "--drones", "2", "--router", "h"])
    assert result.exit_code == 2 and "swarm name" in result.output
    with pytest.raises(pki.PkiError):
        pki.parse_router("host:70000")
    assert pki.parse_router("[fe80::1]:9000").endpoint == "tls/[fe80::1]:9000"


# -- (a) through the router --------------------------------------------------------------------

def test_agents_reach_each_other_through_the_mtls_router(swarm, router, clients):
    one = clients.open(swarm.config("agent-1"))
    two = clients.open(swarm.config("agent-2"))
    assert [str(z) for z in one.info.routers_zid()] == [str(router.info.zid())]
    # the router knows each client by its certificate's common name, the name its ACL keys on
    assert poll(lambda: {link.auth_identifier for link in router.info.links()} >= {"agent-1", "agent-2"}, 5.0)

    got = clients.collect(two, swarm.est(1))
    pub = one.declare_publisher(swarm.est(1))
    assert poll(lambda: got, 10.0, step=lambda: pub.put(b"estimate of 1")), "agent 2 got nothing from agent 1"
    assert set(got) == {b"estimate of 1"}

    # liveliness through the router: agent 1's token, seen by agent 2
    token = one.liveliness().declare_token(alive_key(swarm.name, 1))
    alive = []
    clients.keep(two.liveliness().declare_subscriber(alive_key(swarm.name, "*"), lambda s: alive.append(str(s.key_expr)),
                                                     history=True))
    assert poll(lambda: alive_key(swarm.name, 1) in alive, 5.0)
    # and a liveliness query (allowed as liveliness_query) from a fresh session
    three = clients.open(swarm.config("agent-3"))
    replies = [r.ok for r in three.liveliness().get(alive_key(swarm.name, "*"), timeout=2.0)]
    assert [str(r.key_expr) for r in replies if r is not None] == [alive_key(swarm.name, 1)]
    token.undeclare()


# -- (b) refused -------------------------------------------------------------------------------

def assert_refused(config: zenoh.Config, swarm: Swarm, clients: Sessions, what: str) -> str:
    """Assert the client ``config`` is refused (see the module's docstring); return how."""
    try:
        s = open_bounded(config)
    except zenoh.ZError:
        return "open raised"
    try:
        assert s.info.routers_zid() == [] and s.info.peers_zid() == [], f"{what}: connected"
        listener = clients.open(swarm.config("agent-2"))
        speaker = clients.open(swarm.config("agent-1"))
        heard, leaked = clients.collect(listener, swarm.est(1)), clients.collect(s, swarm.est(1))
        deadline = time.monotonic() + REFUSED_WAIT_S
        while time.monotonic() < deadline:
            s.put(swarm.est(1), b"from the refused")
            time.sleep(0.05)
        # (the authorised put, heard by the listener, is the delivery the refused ones would have had)
        assert poll(lambda: b"authorised" in heard, 10.0, step=lambda: speaker.put(swarm.est(1), b"authorised"))
        assert b"from the refused" not in heard, f"{what}: its put was delivered"
        assert leaked == [], f"{what}: it received data"
        return "isolated"
    finally:
        s.close()


def test_clients_without_a_valid_certificate_are_refused(swarm, router, clients):
    no_cert = swarm.config("agent-1")  # a plain TLS client: it knows the CA, presents no certificate
    no_cert.insert_json5("transport/link/tls", json.dumps({"root_ca_certificate": str(swarm.dir / "ca.pem")}))
    other_ca = swarm.config("agent-1")  # trusts the router, presents agent-1 signed by another CA
    other_ca.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(swarm.other / "agent-1.pem")))
    other_ca.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(swarm.other / "agent-1.key")))
    for what, config in [("no certificate", no_cert), ("another CA", other_ca)]:
        how = assert_refused(config, swarm, clients, what)
        # what Zenoh 1.10 does: the router ends the TLS handshake and open fails at once
        assert how == "open raised", f"{what}: {how}"
    # and the router still serves the authorised (control)
    one = clients.open(swarm.config("agent-1"))
    assert [str(z) for z in one.info.routers_zid()] == [str(router.info.zid())]


# -- (c) access control ------------------------------------------------------------------------

def test_an_agent_cannot_write_on_another_agents_keys(swarm, router, clients):
    one = clients.open(swarm.config("agent-1"))
    two = clients.open(swarm.config("agent-2"))
    own, forged = clients.collect(two, swarm.est(1)), clients.collect(two, swarm.est(2))
    alive = []
    clients.keep(two.liveliness().declare_subscriber(alive_key(swarm.name, "*"), lambda s: alive.append(str(s.key_expr)),
                                                     history=True))
    # agent 1 may declare a publisher on agent 2's key (a publisher is local to its session: Zenoh's
    # ACL has no such message), and it learns that agent 2 subscribes: its puts do go to the
    # router, which drops them.
    forger = one.declare_publisher(swarm.est(2))
    assert poll(lambda: forger.matching_status.matching, 5.0), "agent 1 never learnt of agent 2's subscriber"
    mine = one.declare_publisher(swarm.est(1))
    fake_token = one.liveliness().declare_token(alive_key(swarm.name, 2))
    token = one.liveliness().declare_token(alive_key(swarm.name, 1))
    for _ in range(DENIED_PUTS):
        forger.put(b"forged")
        one.put(swarm.est(2), b"forged too")
        one.delete(swarm.est(2))
    # agent 1's puts on its own key, after the forged ones, on the same link through the same router:
    # one heard proves the forged ones would have been heard before it; likewise its own token,
    # declared after the forged one
    assert poll(lambda: b"mine, after" in own, 5.0, step=lambda: mine.put(b"mine, after")), "agent 1's own key did not deliver"
    assert forged == [], "the router let agent 1 put on agent 2's key"
    assert poll(lambda: alive_key(swarm.name, 1) in alive, 5.0), alive
    assert alive_key(swarm.name, 2) not in alive, alive
    fake_token.undeclare()
    token.undeclare()


def test_the_ground_station_reads_everything_and_writes_nothing(swarm, router, clients):
    gcs = clients.open(swarm.config("gcs"))
    one = clients.open(swarm.config("agent-1"))
    everything = []
    clients.keep(gcs.declare_subscriber("**", lambda s: everything.append(str(s.key_expr))))
    heard = clients.collect(one, swarm.est(3))
    assert poll(lambda: swarm.est(1) in everything, 10.0, step=lambda: one.put(swarm.est(1), b"x"))
    for _ in range(DENIED_PUTS):
        gcs.put(swarm.est(3), b"from the gcs")
    # the ground station's query, after its puts on its link: once answered, the router has taken
    # the puts, and forwarded any it let through to agent 1's link, where agent 3's put then follows them
    assert list(gcs.get(swarm.est(3), timeout=5.0)) == []
    three = clients.open(swarm.config("agent-3"))
    assert poll(lambda: heard, 10.0, step=lambda: three.put(swarm.est(3), b"from agent 3"))
    assert set(heard) == {b"from agent 3"}, heard


def test_two_routers_forward_between_them_and_each_enforces(tmp_path, clients):
    """Agent 1 on router A, agent 2 on router B (127.0.0.2: the whole of 127/8 is loopback): the
    routers link up with their own certificates, and A drops agent 1's put on agent 2's key."""
    name = f"sec-{uuid.uuid4().hex[:8]}"
    pa, pb = free_ports(2)
    d = tmp_path / "pki"
    pki.init(d, name, 2, [f"127.0.0.1:{pa}", f"127.0.0.2:{pb}"], listen_host="127.0.0.1")
    config = lambda n: zenoh.Config.from_file(str(d / "zenoh" / f"{n}.json5"))  # noqa: E731
    b_config = config("router-127.0.0.2")
    b_config.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.2:{pb}", f"quic/127.0.0.2:{pb}"]))
    # A connects to B over QUIC. B is opened first so that A closes first: a router still trying
    # to reach one that is gone takes 10 s to close (its QUIC connection attempt runs to its timeout)
    b = clients.open(b_config)
    a = clients.open(config("router-127.0.0.1"))
    one, two = config("agent-1"), config("agent-2")
    one.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{pa}"]))
    two.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.2:{pb}"]))
    assert poll(lambda: len(a.info.routers_zid()) == 1 and len(b.info.routers_zid()) == 1, 10.0)
    one, two = clients.open(one), clients.open(two)
    own, forged = clients.collect(two, estimate_key(name, 1)), clients.collect(two, estimate_key(name, 2))
    assert poll(lambda: own, 10.0, step=lambda: one.put(estimate_key(name, 1), b"mine"))
    forger = one.declare_publisher(estimate_key(name, 2))
    assert poll(lambda: forger.matching_status.matching, 5.0)  # so its puts do leave agent 1
    for _ in range(DENIED_PUTS):
        forger.put(b"forged")
    mark = len(own)  # (a put on its own key after the forged ones arrives: they would have too)
    assert poll(lambda: len(own) > mark, 10.0, step=lambda: one.put(estimate_key(name, 1), b"mine"))
    assert forged == []


# -- (d) the companion's bus -------------------------------------------------------------------

def test_the_companion_bus_on_generated_configs(swarm, router):
    async def scenario():
        loop = asyncio.get_running_loop()
        one, two = Bus(swarm.name, 2), Bus(swarm.name, 2)
        try:
            # as triswarm-companion --zenoh-config agent-<i>.json5 does
            one.open(tune(swarm.config("agent-1")), loop)
            two.open(tune(swarm.config("agent-2")), loop)
            one.join(1, PLAN, frozenset({2}))
            two.join(2, PLAN, frozenset({1}))
            assert await until(lambda: 1 in two.alive and 2 in one.alive, 10.0, [one, two])
            assert await until(lambda: (one.publish_estimate(1, XI, 1.0, AgentStatus.FLYING) or True)
                               and two.estimates[1].heard, 10.0, [two])
            np.testing.assert_array_equal(two.estimates[1].xi, XI)
            assert await until(lambda: (two.publish_estimate(2, XI * 2, 1.0, AgentStatus.FLYING) or True)
                               and one.estimates[2].heard, 10.0, [one])
            np.testing.assert_array_equal(one.estimates[2].xi, XI * 2)
            assert two.counts().get("drop_unknown_agent", 0) == 0
        finally:
            one.close()
            two.close()

    asyncio.run(asyncio.wait_for(scenario(), 30.0))
