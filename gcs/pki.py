"""The swarm's certificates and the Zenoh configurations that use them (mTLS and access control).

Run where the operator is (``triswarm pki init``). With the ``openssl`` command line it makes:

- a swarm CA (``ca.pem``; its key ``ca.key`` signs everything and stays with the operator);
- per router, a certificate for the names it is reached by (subjectAltName: a DNS name or an IP
  address), good for TLS server and client (routers connect to each other with it), CN
  ``router-<host>``;
- per agent i, a client certificate with CN ``agent-<i>``, and one for the ground station, CN ``gcs``.
  The router's access control keys on these common names.

Keys are EC P-256, written 0600. Then the Zenoh configurations (JSON5): one per router (mTLS on
``tls/`` for clients and ``quic/`` for the other routers, access control) and one per client
(``tls/`` to every router, its own certificate).

Routers mesh over QUIC, not TLS over TCP: Zenoh sets SO_LINGER 10 s on its TCP sockets (a
compile-time constant) and closes a dead link's socket from a worker thread of its runtime, so a
router that loses another (a host out of radio range: nothing acknowledges what is queued) has that
thread blocked in close() for 10 s. Two such links block both of the default receive workers, and
the router stops forwarding altogether, even between its own clients. QUIC runs over UDP and closes
without lingering.

Re-running keeps the CA and every certificate that is still valid (signed by the CA, not expired,
same name, matching key); it makes what is missing and rewrites the configurations. ``force``
starts again from a new CA.
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import os
import re
import secrets
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from .errors import GcsError

DEFAULT_ROUTER_PORT = 7447
DEFAULT_DAYS = 825      # leaf certificates (the CA/Browser Forum's old ceiling)
CA_DAYS = 3650          # the CA outlives its certificates
OPENSSL_TIMEOUT_S = 30.0

ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"]
"""Every message kind Zenoh 1.x access control filters (its own schema lists exactly these)."""

_SWARM = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
_DNS = re.compile(r"(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*")


class PkiError(GcsError, ValueError):
    """Something the operator asked for cannot be made (one sentence)."""


@dataclass(frozen=True)
class Router:
    """A router as the clients reach it: ``HOST[:PORT]`` (``[v6]:PORT`` for an IPv6 address)."""

    host: str
    port: int = DEFAULT_ROUTER_PORT

    @property
    def ip(self) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
        try:
            return ipaddress.ip_address(self.host)
        except ValueError:
            return None

    @property
    def name(self) -> str:
        """``router-<host>``: its certificate's CN and its files' names."""
        return "router-" + re.sub(r"[^A-Za-z0-9.-]", "_", self.host)

    @property
    def endpoint(self) -> str:
        """Where clients connect (TLS over TCP)."""
        return f"tls/{self._address}"

    @property
    def mesh_endpoint(self) -> str:
        """Where the other routers connect (QUIC, the same port number on UDP)."""
        return f"quic/{self._address}"

    @property
    def _address(self) -> str:
        host = f"[{self.host}]" if isinstance(self.ip, ipaddress.IPv6Address) else self.host
        return f"{host}:{self.port}"

    @property
    def san(self) -> str:
        return f"IP:{self.ip.compressed}" if self.ip is not None else f"DNS:{self.host}"


def parse_router(text: str) -> Router:
    text = text.strip()
    if text.startswith("tls/"):
        text = text[4:]
    port = DEFAULT_ROUTER_PORT
    if text.startswith("["):  # [v6] or [v6]:port
        host, _, rest = text[1:].partition("]")
        if rest:
            if not rest.startswith(":"):
                raise PkiError(f"router {text!r}: expected [IPV6]:PORT")
            port = _port(rest[1:], text)
    elif text.count(":") == 1:
        host, _, p = text.partition(":")
        port = _port(p, text)
    else:
        host = text  # a name, an IPv4 address, or a bare IPv6 address
    if not host:
        raise PkiError(f"router {text!r}: no host")
    try:
        ipaddress.ip_address(host)
    except ValueError:
        if not _DNS.fullmatch(host):
            raise PkiError(f"router {text!r}: {host!r} is neither an IP address nor a DNS name") from None
    return Router(host, port)


def _port(text: str, whole: str) -> int:
    if not text.isdigit() or not 1 <= int(text) <= 65535:
        raise PkiError(f"router {whole!r}: port must be 1-65535")
    return int(text)


@dataclass
class Layout:
    """Where ``init`` writes (``out``), and where the configurations say the files are (``cert_dir``:
    the same folder by default; the folder they will be copied to on the machines otherwise)."""

    out: Path
    cert_dir: Path

    def cert(self, name: str) -> Path:
        return self.out / f"{name}.pem"

    def key(self, name: str) -> Path:
        return self.out / f"{name}.key"

    def config(self, name: str) -> Path:
        return self.out / "zenoh" / f"{name}.json5"

    def remote(self, filename: str) -> str:
        return str(self.cert_dir / filename)


@dataclass
class Report:
    made: list[Path] = field(default_factory=list)
    kept: list[Path] = field(default_factory=list)
    configs: list[Path] = field(default_factory=list)


# -- openssl -----------------------------------------------------------------------------------

def _openssl(*args: str, input: bytes | None = None) -> bytes:
    exe = shutil.which("openssl")
    if exe is None:
        raise PkiError("the openssl command is not installed (Debian: apt-get install openssl)")
    try:
        done = subprocess.run([exe, *args], input=input, capture_output=True, timeout=OPENSSL_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise PkiError(f"openssl {args[0]} did not finish in {OPENSSL_TIMEOUT_S:.0f} s") from None
    if done.returncode != 0:
        message = done.stderr.decode(errors="replace").strip().splitlines()
        raise PkiError(f"openssl {args[0]} failed: {message[0] if message else f'exit status {done.returncode}'}")
    return done.stdout


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write atomically with ``mode`` from the start (a key is never readable by others, not even
    half-written)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


_REQ_CONFIG = """\
[req]
distinguished_name = dn
prompt = no
[dn]
[swarm_ca]
basicConstraints = critical, CA:TRUE, pathlen:0
keyUsage = critical, keyCertSign, cRLSign
subjectKeyIdentifier = hash
[swarm_leaf]
basicConstraints = critical, CA:FALSE
keyUsage = critical, digitalSignature
extendedKeyUsage = {eku}
subjectKeyIdentifier = hash
authorityKeyIdentifier = keyid
{san}
"""


def _conf(tmp: Path, eku: str = "clientAuth", sans: list[str] | None = None) -> str:
    path = tmp / f"openssl-{secrets.token_hex(4)}.cnf"
    san = f"subjectAltName = {', '.join(sans)}" if sans else ""
    path.write_text(_REQ_CONFIG.format(eku=eku, san=san))
    return str(path)


def _subject(swarm: str, cn: str) -> str:
    return f"/O=triswarm/OU={swarm}/CN={cn}"


def _new_key(path: Path) -> None:
    _write(path, _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256"), 0o600)


def _make_ca(layout: Layout, swarm: str, tmp: Path) -> None:
    key, cert = layout.key("ca"), layout.cert("ca")
    _new_key(key)
    pem = _openssl("req", "-x509", "-new", "-config", _conf(tmp), "-extensions", "swarm_ca", "-key", str(key),
                   "-sha256", "-days", str(CA_DAYS), "-subj", _subject(swarm, f"triswarm {swarm} CA"),
                   "-set_serial", _serial())
    _write(cert, pem, 0o644)


def _serial() -> str:
    return hex(secrets.randbits(120) | 1 << 119)


def _make_leaf(layout: Layout, swarm: str, name: str, days: int, tmp: Path, eku: str, sans: list[str]) -> None:
    key = layout.key(name)
    _new_key(key)
    conf = _conf(tmp, eku, sans)
    csr = _openssl("req", "-new", "-config", conf, "-key", str(key), "-subj", _subject(swarm, name))
    pem = _openssl("x509", "-req", "-CA", str(layout.cert("ca")), "-CAkey", str(layout.key("ca")),
                   "-set_serial", _serial(), "-days", str(days), "-sha256",
                   "-extfile", conf, "-extensions", "swarm_leaf", input=csr)
    _write(layout.cert(name), pem, 0o644)


def common_name(cert: Path) -> str | None:
    subject = _openssl("x509", "-in", str(cert), "-noout", "-subject", "-nameopt", "RFC2253").decode()
    m = re.search(r"(?:^|[=,\s])CN=([^,]+)", subject.removeprefix("subject="))
    return m.group(1).strip() if m else None


def alt_names(cert: Path) -> set[str]:
    """subjectAltName as ``DNS:x`` / ``IP:y`` strings."""
    text = _openssl("x509", "-in", str(cert), "-noout", "-ext", "subjectAltName").decode()
    names = set()
    for line in text.splitlines()[1:]:
        for item in line.split(","):
            kind, _, value = item.strip().partition(":")
            if value and kind == "IP Address":
                names.add(f"IP:{ipaddress.ip_address(value).compressed}")
            elif value:
                names.add(f"{kind}:{value}")
    return names


def _verifies(cert: Path, ca: Path, purpose: str) -> bool:
    try:
        out = _openssl("verify", "-CAfile", str(ca), "-purpose", purpose, str(cert))
    except PkiError:
        return False
    return out.strip().endswith(b"OK")


def _key_matches(cert: Path, key: Path) -> bool:
    try:
        return _openssl("x509", "-in", str(cert), "-noout", "-pubkey") == _openssl("pkey", "-in", str(key), "-pubout")
    except PkiError:
        return False


def _leaf_ok(layout: Layout, name: str, purpose: str, sans: list[str]) -> bool:
    cert, key = layout.cert(name), layout.key(name)
    if not (cert.is_file() and key.is_file()):
        return False
    if not (_verifies(cert, layout.cert("ca"), purpose) and _key_matches(cert, key)):
        return False
    try:
        return common_name(cert) == name and (not sans or alt_names(cert) == set(sans))
    except PkiError:
        return False


# -- Zenoh configurations ----------------------------------------------------------------------

def swarm_prefix(swarm: str) -> str:
    return f"triswarm/{swarm}"


def access_control(swarm: str, drones: int, routers: list[Router]) -> dict:
    """The router's access control (Zenoh 1.x ``access_control``): default deny; each agent reads
    the whole swarm's key space and writes (puts, liveliness tokens) only under its own
    ``triswarm/<swarm>/agent/<i>/**``; the ground station reads everything; routers trust each other.

    Flows are the router's: ``ingress`` is what a client sends to the router, ``egress`` what the
    router sends to it. A subscriber therefore needs ``declare_subscriber`` in and ``put`` out; a
    liveliness subscriber (``history=True`` included) ``declare_liveliness_subscriber`` in and
    ``liveliness_token`` out; ``liveliness().get`` is a ``liveliness_query`` in. ``declare_subscriber`` out tells a
    publisher that someone listens (Zenoh's write-side filtering). Zenoh has no ACL message for
    declaring a publisher: a publisher is local to its session, and only its puts are filtered."""
    everything = f"{swarm_prefix(swarm)}/**"
    rules = [
        {"id": "swarm-read-in", "messages": ["declare_subscriber", "query", "declare_liveliness_subscriber",
                                             "liveliness_query"],
         "flows": ["ingress"], "permission": "allow", "key_exprs": [everything]},
        {"id": "swarm-read-out", "messages": ["put", "reply", "liveliness_token", "declare_subscriber"],
         "flows": ["egress"], "permission": "allow", "key_exprs": [everything]},
        {"id": "gcs-read-in", "messages": ["declare_subscriber", "query", "declare_liveliness_subscriber",
                                           "liveliness_query"],
         "flows": ["ingress"], "permission": "allow", "key_exprs": ["**"]},
        {"id": "gcs-read-out", "messages": ["put", "reply", "liveliness_token"],
         "flows": ["egress"], "permission": "allow", "key_exprs": ["**"]},
    ]
    subjects = [{"id": "gcs", "cert_common_names": ["gcs"]}]
    policies = [{"id": "gcs", "rules": ["gcs-read-in", "gcs-read-out"], "subjects": ["gcs"]}]
    for i in range(1, drones + 1):
        rules.append({"id": f"agent-{i}-write", "messages": ["put", "liveliness_token"], "flows": ["ingress"],
                      "permission": "allow", "key_exprs": [f"{swarm_prefix(swarm)}/agent/{i}/**"]})
        # one subject per agent, holding every rule it needs: a transport matching several
        # subjects is not needed (and its treatment has changed across Zenoh releases)
        subjects.append({"id": f"agent-{i}", "cert_common_names": [f"agent-{i}"]})
        policies.append({"id": f"agent-{i}", "rules": ["swarm-read-in", "swarm-read-out", f"agent-{i}-write"],
                         "subjects": [f"agent-{i}"]})
    if len(routers) > 1:
        rules.append({"id": "router-trust", "messages": ALL_MESSAGES, "flows": ["ingress", "egress"],
                      "permission": "allow", "key_exprs": ["**"]})
        subjects.append({"id": "routers", "cert_common_names": [r.name for r in routers]})
        policies.append({"id": "routers", "rules": ["router-trust"], "subjects": ["routers"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def _link(layout: Layout, name: str, listen: bool, protocols: list[str]) -> dict:
    tls = {"root_ca_certificate": layout.remote("ca.pem")}
    if listen:
        tls |= {"listen_private_key": layout.remote(f"{name}.key"), "listen_certificate": layout.remote(f"{name}.pem")}
    tls |= {
        "enable_mtls": True,  # a listener demands a client certificate; a connector presents its own
        "connect_private_key": layout.remote(f"{name}.key"),
        "connect_certificate": layout.remote(f"{name}.pem"),
        "verify_name_on_connect": True,
        "close_link_on_expiration": True,
    }
    from triswarm.companion.zenoh_session import KEEP_ALIVES_PER_LEASE, LEASE_MS

    return {"protocols": protocols, "tx": {"lease": LEASE_MS, "keep_alive": KEEP_ALIVES_PER_LEASE}, "tls": tls}


RETRY = {"period_init_ms": 200, "period_max_ms": 1000, "period_increase_factor": 2}
"""How routers and clients try again a router out of reach (Zenoh's connect.retry)."""


def router_config(layout: Layout, swarm: str, drones: int, routers: list[Router], router: Router,
                  listen_host: str = "0.0.0.0") -> dict:
    listen = f"[{listen_host}]" if ":" in listen_host else listen_host
    return {
        "mode": "router",
        # clients on tls/ (TCP), routers on quic/ (UDP), the same port number
        "listen": {"endpoints": [f"tls/{listen}:{router.port}", f"quic/{listen}:{router.port}"]},
        # each pair of routers linked once: a router connects to those listed after it (and so the
        # last one to none), tries again every 0.2-1 s when one is out of reach, never gives up
        "connect": {"endpoints": [r.mesh_endpoint for r in routers[routers.index(router) + 1:]],
                    "timeout_ms": {"router": -1}, "exit_on_failure": {"router": False},
                    "retry": dict(RETRY)},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"unicast": {"max_links": 2},
                      "link": _link(layout, router.name, listen=True, protocols=["tls", "quic"])},
        "access_control": access_control(swarm, drones, routers),
    }


def client_config(layout: Layout, name: str, routers: list[Router]) -> dict:
    return {
        "mode": "client",
        # a router that went away (restarted) tried again every 0.2 s, backing off to 1 s (Zenoh's
        # default: 4 s)
        "connect": {"endpoints": [r.endpoint for r in routers], "retry": dict(RETRY)},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"unicast": {"max_links": 2}, "link": _link(layout, name, listen=False, protocols=["tls"])},
    }


def read_config(path: Path) -> dict:
    """A configuration this module wrote: its comment lines, then JSON (ValueError otherwise)."""
    lines = Path(path).read_text(encoding="utf-8").splitlines()
    return json.loads("\n".join(line for line in lines if not line.startswith("//")))


def _json5(header: str, obj: dict) -> bytes:
    lines = [f"// {line}".rstrip() for line in header.strip().splitlines()]
    return ("\n".join(lines) + "\n" + json.dumps(obj, indent=2) + "\n").encode()


# -- init --------------------------------------------------------------------------------------

def init(out: Path, swarm: str, drones: int, routers: list[Router] | list[str], days: int = DEFAULT_DAYS,
         force: bool = False, cert_dir: Path | None = None, listen_host: str = "0.0.0.0") -> Report:
    """Make (or complete) the swarm's PKI and Zenoh configurations in ``out``."""
    if not _SWARM.fullmatch(swarm):
        raise PkiError(f"swarm name {swarm!r}: letters, digits, '_', '.', '-' only (it is a key expression chunk)")
    if not 1 <= drones <= 255:
        raise PkiError(f"--drones must be 1-255 (MAVLink system ids), got {drones}")
    if not 1 <= days <= 36500:
        raise PkiError(f"--days must be 1-36500, got {days}")
    routers = [r if isinstance(r, Router) else parse_router(r) for r in routers]
    if not routers:
        raise PkiError("at least one --router HOST[:PORT] is needed")
    if len({r.name for r in routers}) != len(routers):
        raise PkiError("two --router with the same host")
    if cert_dir is not None and not Path(cert_dir).is_absolute():
        # Zenoh reads the paths in a configuration from its process's working folder
        raise PkiError(f"--cert-dir must be an absolute path, got {cert_dir}")
    out = Path(out)
    layout = Layout(out, Path(cert_dir) if cert_dir is not None else out.resolve())
    report = Report()
    if out.exists() and not out.is_dir():
        raise PkiError(f"--out {out}: not a folder")
    try:
        out.mkdir(parents=True, mode=0o700, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        raise PkiError(f"--out {out}: cannot write in this folder ({exc.strerror})") from None
    ca_cert, ca_key = layout.cert("ca"), layout.key("ca")
    with tempfile.TemporaryDirectory(prefix="triswarm-pki-") as tmp_name:
        tmp = Path(tmp_name)
        if force or not (ca_cert.exists() or ca_key.exists()):
            _make_ca(layout, swarm, tmp)
            report.made += [ca_cert, ca_key]
        else:
            if not (ca_cert.is_file() and ca_key.is_file()):
                missing = ca_key if ca_cert.exists() else ca_cert
                raise PkiError(f"{missing} is missing: the CA cannot sign (--force makes a new CA, and new certificates)")
            if not _verifies(ca_cert, ca_cert, "any") or not _key_matches(ca_cert, ca_key):
                raise PkiError(f"{ca_cert} is expired or does not match {ca_key} (--force makes a new CA)")
            report.kept += [ca_cert]
        leaves = [(r.name, "sslserver", "serverAuth, clientAuth", [r.san]) for r in routers]
        leaves += [(f"agent-{i}", "sslclient", "clientAuth", []) for i in range(1, drones + 1)]
        leaves += [("gcs", "sslclient", "clientAuth", [])]
        for name, purpose, eku, sans in leaves:
            if not force and _leaf_ok(layout, name, purpose, sans):
                report.kept.append(layout.cert(name))
                continue
            _make_leaf(layout, swarm, name, days, tmp, eku, sans)
            report.made += [layout.cert(name), layout.key(name)]
    for r in routers:
        header = f"""Zenoh router {r.name} of swarm {swarm}: mTLS and access control. Generated by `triswarm pki init`:
edit the command line and re-run it rather than this file.
  zenohd -c {r.name}.json5   (or any Python with eclipse-zenoh: zenoh.open(zenoh.Config.from_file(...)))
It listens on tls/ (clients) and quic/ (other routers; it connects to those listed after it) and
nothing else: a client must present a certificate signed by ca.pem (enable_mtls), and the
access control (default deny) keys on its common name: agent-<i> writes only under
{swarm_prefix(swarm)}/agent/<i>/**, every agent and gcs read. See deploy/README.md."""
        path = layout.config(r.name)
        _write(path, _json5(header, router_config(layout, swarm, drones, routers, r, listen_host)), 0o644)
        report.configs.append(path)
    for name in [f"agent-{i}" for i in range(1, drones + 1)] + ["gcs"]:
        if name == "gcs":
            who, use = "the ground station", "zenoh.open(zenoh.Config.from_file(\"gcs.json5\")): it may subscribe, never publish"
        else:
            i = name.removeprefix("agent-")
            who, use = f"companion {i}", f"triswarm-companion --id {i} ... --zenoh-config {name}.json5"
        header = f"""Zenoh client configuration of {who} ({name}), swarm {swarm}. Generated by `triswarm pki init`.
  {use}
It connects over tls/ to the router(s), checks the router's certificate against ca.pem and its name
(verify_name_on_connect), and presents its own certificate ({name}.pem, CN {name}) to the router."""
        path = layout.config(name)
        _write(path, _json5(header, client_config(layout, name, routers)), 0o644)
        report.configs.append(path)
    return report
