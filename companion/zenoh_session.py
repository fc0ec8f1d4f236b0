"""The companion's Zenoh sessions: how one is configured (peers on one machine, named endpoints,
the settings triswarm needs whatever the deployment), opened and closed, and whether its links back
the best-effort estimates up with reliable copies (``copies_backup``; the layouts are in ``bus``'s
opening comment)."""

from __future__ import annotations

import json
import logging
import os

import zenoh

from .options import DEFAULT_ZENOH_BASE_PORT

ONE_WORKER_RUNTIME = ("(app: (worker_threads: 1), acc: (handover: app), tx: (handover: app), rx: (handover: app), "
                      "net: (handover: app))")
"""One Zenoh worker thread for everything (accept, rx, tx, network): at a few hundred samples per
second, a multi-threaded runtime only spends the CPU on waking its own threads."""


def open_session(config: zenoh.Config) -> zenoh.Session:
    """A Zenoh session of the companion's. Zenoh reads ZENOH_RUNTIME when a process opens its first
    session: unless the deployment set its own, the companion's is ``ONE_WORKER_RUNTIME``."""
    os.environ.setdefault("ZENOH_RUNTIME", ONE_WORKER_RUNTIME)
    return zenoh.open(config)


def close_session(session: zenoh.Session) -> None:
    """Close a session at the end. Zenoh gives up a close that its peers do not answer in time
    (one behind a lossy link, or gone) with an error; the session is closed all the same and the
    process goes on to end as it would (its stats written), saying so."""
    try:
        session.close()
    except zenoh.ZError as exc:
        logging.getLogger("triswarm.companion").warning(
            f"zenoh: the session's close timed out ({str(exc).split(' at ')[0]}); closed without its peers' answer")


def default_config(agents: int | frozenset[int], n_agents: int, base_port: int = DEFAULT_ZENOH_BASE_PORT,
                   host: str = "127.0.0.1", protocols: tuple[str, ...] = ("tcp",)) -> zenoh.Config:
    """Peers on one machine, no router, no multicast: agent i listens on port base + i (a link of
    each of ``protocols``) and connects to every other agent's. A process of several agents listens
    on each of theirs and connects to the others'.

    TCP alone by default. On one machine nothing is lost on the way but what a starved receiver's
    full UDP buffer drops, and a peer that loses a declaration sent over UDP (Zenoh sends them on
    any link while no reliable one is up) stays deaf to that key for the whole session (measured:
    in the case study on a machine starved by busier processes, "Route data with unknown scope" in
    a companion's log, and two drones 37 m off). TCP loses nothing; a starved receiver only slows
    its senders, which then drop best-effort estimates rather than queue them."""
    mine = frozenset({agents}) if isinstance(agents, int) else agents
    listen = [f"{proto}/{host}:{base_port + i}" for i in sorted(mine) for proto in protocols]
    connect = [f"{proto}/{host}:{base_port + j}" for j in range(1, n_agents + 1) if j not in mine
               for proto in protocols]
    return peer_config(listen, connect)


def peer_config(listen: list[str], connect: list[str], mode: str = "peer") -> zenoh.Config:
    """A session that listens and connects where it is told, and nowhere else: no multicast
    scouting, and no gossip (peers telling each other where else they listen). The companions'
    peers are a full mesh of named endpoints, so gossip adds no path; what it adds are links around
    the named ones (measured: behind a relay, peers reached each other directly)."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("listen/endpoints", json.dumps(listen))
    cfg.insert_json5("connect/endpoints", json.dumps(connect))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "false")
    tune(cfg)
    return cfg


def copies_backup(config: zenoh.Config) -> bool:
    """Whether a session with ``config`` sends reliable copies of its estimates (``Bus``): when its
    endpoints give the estimates a link of their own (plain UDP) beside a reliable one (TCP, TLS, a
    reliable UDP link...). On one reliable UDP link (QUIC: ``rel=1``, the estimates as its
    datagrams) the copies share the connection's congestion window with the estimates: measured
    with 20 % loss and 20 ms each way, six peers, the estimates then came up to 0.3-2.2 s apart;
    without the copies at most 0.09 s apart, and 0.17 s beside two busy loops
    (tests/bench/bench_zenoh_loss.py)."""
    endpoints = [e for key in ("listen/endpoints", "connect/endpoints") for e in _endpoints(config, key)]
    plain_udp = [e for e in endpoints if _is_plain_udp(e)]
    return bool(plain_udp) and len(plain_udp) < len(endpoints)


def _endpoints(config: zenoh.Config, key: str) -> list[str]:
    """The endpoints under ``key``, of every mode when the file gives them by mode."""
    got = json.loads(config.get_json(key) or "null")
    if isinstance(got, dict):
        return [e for v in got.values() for e in (v if isinstance(v, list) else [v])]
    return list(got or [])


def _is_plain_udp(endpoint: str) -> bool:
    locator, _, rest = endpoint.partition("?")
    metadata = dict(kv.partition("=")[::2] for kv in rest.partition("#")[0].split(";") if kv)
    return locator.startswith("udp/") and metadata.get("rel") != "1"


LEASE_MS = 1000
KEEP_ALIVES_PER_LEASE = 10


def tune(cfg: zenoh.Config) -> zenoh.Config:
    """Settings triswarm needs whatever the deployment: two links per peer (reliable + best
    effort); a lease short enough that a dead peer's liveliness goes within a second; and a
    keep-alive every tenth of it on a link that sends nothing else, so that a live link is not
    closed for losses alone. Zenoh applies the lease to each link, and every link but the one the
    estimates ride carries keep-alives only: at 20 % loss, 4 per lease (Zenoh's default) are all
    lost with p = 0.2^4, and 30 UDP links expired in a minute's flight of six (each then opened
    again, with a handshake that loses a message half the time); with 10, 3 did (measured with
    RUST_LOG=zenoh_transport=debug, in tests/test_stack_lossy.py's set-up with TCP dropped too)."""
    cfg.insert_json5("transport/unicast/max_links", "2")
    cfg.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    cfg.insert_json5("transport/link/tx/keep_alive", str(KEEP_ALIVES_PER_LEASE))
    return cfg
