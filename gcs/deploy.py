"""``triswarm deploy``: install the companion on drones' onboard computers over SSH.

For each target it:

1. builds a wheel of this checkout (once for all targets: ``pip wheel --no-deps``, or ``python -m build``
   when installed, from a clean copy of the source tree), unless ``--wheel`` names one;
2. makes the release: the wheel, the drone's configuration (``id`` set to its drone id, files it names by
   a relative path shipped along), the signing key (mode 0600) and the systemd unit. Its name is
   ``<version>-<12 hex digits>``, a SHA-256 of the wheel's *contents* (not of the zip file, whose
   timestamps change at every build) and of every other file shipped;
3. asks the target which release is current (``ssh``); the same name means "unchanged": nothing is
   copied or written, only the check runs;
4. copies the files with ``scp`` into a fresh temporary folder on the target (``mktemp -d``), runs
   ``bootstrap.sh install`` there (deploy/bootstrap.sh: venv, dependencies, release, atomic switch of
   ``current``, service), which rolls back by itself if one of its steps fails;
5. runs ``triswarm-companion --check --config <root>/current/companion.toml`` on the target; if that
   fails, ``bootstrap.sh abort`` switches back to the release that was current before.

``ssh`` and ``scp`` are OpenSSH's own, with ``BatchMode=yes`` (never a password prompt), the given port,
identity and ``-o`` options. Targets are deployed in parallel (threads), one progress line each.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shlex
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

DEFAULT_ROOT = "/opt/triswarm"
SERVICE = "triswarm-companion.service"
SOURCE = Path(__file__).resolve().parents[1]   # the checkout this triswarm runs from
SSH_CONNECT_TIMEOUT_S = 10
PROBE_TIMEOUT_S = 60
BOOTSTRAP_TIMEOUT_S = 1800   # the first install builds the dependencies' environment
CHECK_TIMEOUT_S = 90


class DeployError(ValueError):
    """A mistake in what was asked (one sentence); the command exits with status 2."""


# -- the wheel ----------------------------------------------------------------------------------------


def source_files(source: Path) -> list[Path]:
    """The files of a checkout, relative: git's tracked and untracked-not-ignored files when it is a git
    repository, else everything but virtual environments, build output and caches."""
    if (source / ".git").exists() and shutil.which("git"):
        out = subprocess.run(["git", "-C", str(source), "ls-files", "-z", "-co", "--exclude-standard"],
                             capture_output=True, timeout=60)
        if out.returncode == 0:
            names = sorted({n for n in out.stdout.decode().split("\0") if n})
            return [Path(n) for n in names if (source / n).is_file()]
    skip = {".git", ".venv", "venv", "build", "dist", "runs", "__pycache__", ".pytest_cache", ".ruff_cache"}
    files = []
    for dirpath, dirnames, filenames in os.walk(source):
        dirnames[:] = [d for d in dirnames if d not in skip and not d.endswith(".egg-info")]
        files += [Path(dirpath, f).relative_to(source) for f in filenames]
    return sorted(files)


def copy_source(source: Path, dest: Path) -> Path:
    """A clean copy of a checkout (see source_files): no stale build/ folder can leak into the wheel."""
    for rel in source_files(source):
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(source / rel, dest / rel)
    return dest


def build_wheel(source: Path, out_dir: Path) -> Path:
    """Build triswarm's wheel from a clean copy of ``source`` into ``out_dir``; its path."""
    if not (source / "pyproject.toml").is_file():
        raise DeployError(f"{source} is not a triswarm checkout (no pyproject.toml); give --wheel FILE")
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="triswarm-src-") as tmp:
        src = copy_source(source, Path(tmp) / "src")
        import importlib.util

        if importlib.util.find_spec("build") is not None:
            cmd = [sys.executable, "-m", "build", "--wheel", "--outdir", str(out_dir), str(src)]
        else:
            cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "--wheel-dir", str(out_dir), str(src)]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600,
                           env={**os.environ, "PIP_DISABLE_PIP_VERSION_CHECK": "1"})
        if r.returncode != 0:
            tail = " | ".join((r.stderr or r.stdout).strip().splitlines()[-5:])
            raise DeployError(f"building the wheel failed ({' '.join(cmd[2:4])}): {tail}")
    wheels = sorted(out_dir.glob("triswarm-*.whl"))
    if not wheels:
        raise DeployError(f"building the wheel left no triswarm-*.whl in {out_dir}")
    return wheels[-1]


@dataclass(frozen=True)
class Wheel:
    path: Path
    version: str
    digest: str   # SHA-256 of the contents: names and bytes of the entries, not their timestamps


def read_wheel(path: Path) -> Wheel:
    try:
        with zipfile.ZipFile(path) as z:
            h = hashlib.sha256()
            meta = None
            for info in sorted(z.infolist(), key=lambda i: i.filename):
                data = z.read(info)
                h.update(info.filename.encode() + b"\0" + hashlib.sha256(data).digest())
                if info.filename.endswith(".dist-info/METADATA"):
                    meta = data.decode("utf-8")
    except (OSError, zipfile.BadZipFile) as exc:
        raise DeployError(f"{path}: not a wheel ({exc})") from None
    fields = dict(re.findall(r"^(Name|Version): (.+)$", meta or "", re.MULTILINE))
    if fields.get("Name", "").lower() != "triswarm" or "Version" not in fields:
        raise DeployError(f"{path}: not a triswarm wheel")
    return Wheel(Path(path), fields["Version"].strip(), h.hexdigest())


# -- targets and inventories --------------------------------------------------------------------------


@dataclass(frozen=True)
class Target:
    host: str                         # HOST or USER@HOST
    drone_id: int
    config: Path | None = None        # the drone's configuration (TOML); None: deploy/drone.example.toml
    port: int | None = None
    identity: Path | None = None
    root: str = DEFAULT_ROOT
    python: str | None = None         # interpreter that creates <root>/venv on the target
    system_site_packages: bool = False
    no_deps: bool = False
    sudo: bool = False
    signing_key: Path | None = None
    generate_signing_key: bool = False
    ssh_options: tuple[str, ...] = ()
    pki: Path | None = None           # the folder of `triswarm pki init`: ship this drone's certificate
    zenoh_router: str | None = None   # with pki: connect to this router only (HOST[:PORT], one of pki init's)

    @property
    def label(self) -> str:
        return f"drone {self.drone_id} {self.host}" + (f":{self.port}" if self.port else "")


INVENTORY_KEYS = {"host", "user", "drone_id", "port", "identity", "config", "root", "python", "system_site_packages",
                  "no_deps", "sudo", "signing_key", "generate_signing_key", "ssh_options", "pki", "zenoh_router"}


def load_inventory(path: Path, base: Target) -> list[Target]:
    """Targets from an inventory (TOML): ``[defaults]`` (any host key) and ``[[hosts]]`` with at least
    ``host`` and ``drone_id``. Paths are relative to the inventory's folder; the command line's options
    are the defaults of [defaults]."""
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DeployError(f"{path}: no such inventory") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise DeployError(f"{path}: not a readable TOML inventory ({exc})") from None
    unknown = set(data) - {"defaults", "hosts"}
    if unknown:
        raise DeployError(f"{path}: unknown table(s) {', '.join(sorted(unknown))} (expected [defaults] and [[hosts]])")
    hosts = data.get("hosts")
    if not isinstance(hosts, list) or not hosts or not all(isinstance(h, dict) for h in hosts):
        raise DeployError(f"{path}: no [[hosts]] entries")
    defaults = data.get("defaults", {})
    here = Path(path).parent
    targets = []
    for n, entry in enumerate(hosts, 1):
        merged = {**defaults, **entry}
        bad = set(merged) - INVENTORY_KEYS
        if bad:
            raise DeployError(f"{path}: host {n}: unknown key(s) {', '.join(sorted(bad))} "
                              f"(known: {', '.join(sorted(INVENTORY_KEYS))})")
        targets.append(_target_from(merged, base, here, f"{path}: host {n}"))
    ids = [t.drone_id for t in targets]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise DeployError(f"{path}: drone id(s) {', '.join(map(str, dup))} appear more than once")
    places = [(t.host.split("@")[-1], t.port, t.root) for t in targets]
    if len(set(places)) != len(places):
        raise DeployError(f"{path}: two hosts share a host, port and root")
    return targets


def _target_from(d: dict, base: Target, here: Path, where: str) -> Target:
    def typed(key, kind, default):
        v = d.get(key, default)
        if v is default:
            return v
        if kind is bool and not isinstance(v, bool) or kind is int and (isinstance(v, bool) or not isinstance(v, int)) \
                or kind is str and not (isinstance(v, str) and v):
            raise DeployError(f"{where}: {key} must be {'true or false' if kind is bool else kind.__name__}, got {v!r}")
        return v

    def path(key, default):
        v = typed(key, str, None)
        if v is None:
            return default
        p = Path(v).expanduser()
        return p if p.is_absolute() else here / p

    host = typed("host", str, None)
    if host is None:
        raise DeployError(f"{where}: no host")
    user = typed("user", str, None)
    if user and "@" not in host:
        host = f"{user}@{host}"
    drone_id = typed("drone_id", int, None)
    if drone_id is None:
        raise DeployError(f"{where}: no drone_id")
    opts = d.get("ssh_options", list(base.ssh_options))
    if not isinstance(opts, list) or not all(isinstance(o, str) for o in opts):
        raise DeployError(f"{where}: ssh_options must be a list of strings (KEY=VALUE)")
    t = Target(host=host, drone_id=drone_id, config=path("config", base.config), port=typed("port", int, base.port),
               identity=path("identity", base.identity), root=typed("root", str, base.root),
               python=typed("python", str, base.python),
               system_site_packages=typed("system_site_packages", bool, base.system_site_packages),
               no_deps=typed("no_deps", bool, base.no_deps), sudo=typed("sudo", bool, base.sudo),
               signing_key=path("signing_key", base.signing_key),
               generate_signing_key=typed("generate_signing_key", bool, base.generate_signing_key),
               ssh_options=tuple(opts), pki=path("pki", base.pki),
               zenoh_router=typed("zenoh_router", str, base.zenoh_router))
    validate_target(t)
    return t


def validate_target(t: Target) -> None:
    if not re.fullmatch(r"(?:[A-Za-z0-9._-]+@)?[A-Za-z0-9._:\[\]-]+", t.host):
        raise DeployError(f"--host {t.host!r}: expected USER@HOST or HOST")
    if not 1 <= t.drone_id <= 255:
        raise DeployError(f"--drone must be between 1 and 255, got {t.drone_id}")
    if t.port is not None and not 1 <= t.port <= 65535:
        raise DeployError(f"--ssh-port must be between 1 and 65535, got {t.port}")
    if not re.fullmatch(r"/[A-Za-z0-9._/+-]*", t.root):
        raise DeployError(f"--root {t.root!r}: an absolute path of letters, digits and ._/+-")
    if t.identity is not None and not t.identity.is_file():
        raise DeployError(f"--identity {t.identity}: no such file")
    if t.config is not None and not t.config.is_file():
        raise DeployError(f"--config {t.config}: no such file")
    if t.pki is not None and not t.pki.is_dir():
        raise DeployError(f"--pki {t.pki}: no such folder (triswarm pki init --out {t.pki} makes it)")
    if t.zenoh_router is not None and t.pki is None:
        raise DeployError("--zenoh-router needs --pki (it picks one of the routers of pki init's configurations)")
    for o in t.ssh_options:
        if "=" not in o:
            raise DeployError(f"--ssh-option {o!r}: expected KEY=VALUE (an ssh -o option)")


def ensure_signing_key(path: Path, *, generate: bool, dry_run: bool, say: Callable[[str], None]) -> bytes | None:
    """The signing key's file content; with ``generate``, a missing key is made (``secrets.token_hex(32)``,
    mode 0600). In a dry run nothing is written and None stands for the key to be made."""
    if path.exists():
        from triswarm.companion.state import read_signing_key

        try:
            read_signing_key(path)
        except ValueError as exc:   # unreadable, or not a key (one sentence naming the file)
            raise DeployError(f"signing key {exc}") from None
        return path.read_bytes()
    if not generate:
        raise DeployError(f"signing key {path}: no such file (generate_signing_key = true makes one)")
    if dry_run:
        say(f"would generate the signing key {path} (secrets.token_hex(32), mode 0600)")
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(secrets.token_hex(32) + "\n")
    say(f"generated the signing key {path} (mode 0600): give the ground station the same, --signing-key {path}")
    return path.read_bytes()


# -- the release --------------------------------------------------------------------------------------


@dataclass
class Release:
    name: str
    wheel: Wheel
    files: dict[str, bytes]   # staging name -> content: companion.toml, the unit, signing.key, files/...
    key_pending: bool = False  # dry run: the signing key is still to be generated

    def summary(self) -> str:
        return ", ".join([self.wheel.path.name, *sorted(self.files)])


def make_release(target: Target, wheel: Wheel, key: bytes | None, key_pending: bool = False,
                 source: Path = SOURCE) -> Release:
    """The release for one target: its configuration rendered with its drone id, the files that
    configuration names by relative path, the key and the unit; named after all of them."""
    import tomli_w

    from triswarm.companion.config import ConfigError, load_config

    config_path = target.config or source / "deploy" / "drone.example.toml"
    try:
        load_config(config_path)   # the same validation as on the target
        data = tomllib.loads(config_path.read_text(encoding="utf-8"))
    except (ConfigError, tomllib.TOMLDecodeError) as exc:
        raise DeployError(str(exc)) from None
    data["id"] = target.drone_id
    files: dict[str, bytes] = {}
    here = config_path.parent

    def ship(table: dict, key_name: str, label: str) -> None:
        value = table.get(key_name)
        if not isinstance(value, str) or Path(value).expanduser().is_absolute():
            return   # absent, or a path on the target
        local = here / value
        if not local.is_file():
            raise DeployError(f"{config_path}: {label} = {value!r}: no such file next to the configuration")
        name = f"files/{local.name}"
        if name in files and files[name] != local.read_bytes():
            raise DeployError(f"{config_path}: two shipped files are both named {local.name}")
        files[name] = local.read_bytes()
        table[key_name] = local.name

    if key is not None or key_pending:
        data["signing_key"] = "signing.key"
        if key is not None:
            files["signing.key"] = key
    elif isinstance(data.get("signing_key"), str) and not Path(data["signing_key"]).expanduser().is_absolute():
        local = here / data["signing_key"]
        if not local.is_file():
            raise DeployError(f"{config_path}: signing_key = {data['signing_key']!r}: no such file; give --signing-key "
                              f"FILE, or an absolute path of a key already on the target")
        files["signing.key"] = local.read_bytes()
        data["signing_key"] = "signing.key"
    ship(data, "plan", "plan")
    if target.pki is not None:
        data["zenoh"] = {"config": f"pki/{ship_pki(target, files)}"}
    elif isinstance(data.get("zenoh"), dict):
        ship(data["zenoh"], "config", "zenoh.config")
    header = (f"# drone {target.drone_id}: written by triswarm deploy from {config_path.name}; relative paths are "
              f"relative to this file.\n")
    files["companion.toml"] = (header + tomli_w.dumps(data)).encode()
    files[SERVICE] = (source / "deploy" / "systemd" / SERVICE).read_bytes()
    h = hashlib.sha256(wheel.digest.encode())
    for name in sorted(files):
        h.update(b"\0" + name.encode() + b"\0" + hashlib.sha256(files[name]).digest())
    if key_pending:
        h.update(b"\0signing.key\0(to be generated)")
    return Release(f"{wheel.version}-{h.hexdigest()[:12]}", wheel, files, key_pending)


def ship_pki(target: Target, files: dict[str, bytes]) -> str:
    """Add this drone's part of ``pki init``'s output to ``files`` (the CA's certificate, the agent's
    certificate and key, its Zenoh client configuration with the paths they will have on the target:
    ``<root>/current/pki/``) and return the configuration's name. Nothing else leaves: not the CA's
    key, not another agent's."""
    from triswarm.gcs import pki

    d, name = target.pki, f"agent-{target.drone_id}"
    needed = [d / "ca.pem", d / f"{name}.pem", d / f"{name}.key", d / "zenoh" / f"{name}.json5"]
    missing = [p for p in needed if not p.is_file()]
    if missing:
        raise DeployError(f"--pki {d}: no {missing[0].relative_to(d)} (triswarm pki init --out {d} --drones "
                          f"{target.drone_id} or more makes it)")
    try:
        config = pki.read_config(needed[3])
        tls = config["transport"]["link"]["tls"]
    except (ValueError, KeyError, TypeError):
        raise DeployError(f"{needed[3]}: not a configuration of triswarm pki init") from None
    on_target = f"{target.root.rstrip('/')}/current/pki"
    tls |= {"root_ca_certificate": f"{on_target}/ca.pem", "connect_certificate": f"{on_target}/{name}.pem",
            "connect_private_key": f"{on_target}/{name}.key"}
    if target.zenoh_router is not None:
        try:
            config["connect"]["endpoints"] = [pki.parse_router(target.zenoh_router).endpoint]
        except pki.PkiError as exc:
            raise DeployError(f"zenoh_router: {exc}") from None
    for p in needed[:3]:
        files[f"files/pki/{p.name}"] = p.read_bytes()
    files[f"files/pki/{name}.json5"] = (json.dumps(config, indent=2) + "\n").encode()
    return f"{name}.json5"


# -- the remote side ----------------------------------------------------------------------------------


class Remote:
    """OpenSSH's ssh and scp, non-interactive (BatchMode=yes)."""

    def __init__(self, target: Target) -> None:
        self.t = target
        common = ["-o", "BatchMode=yes", "-o", f"ConnectTimeout={SSH_CONNECT_TIMEOUT_S}",
                  "-o", "ServerAliveInterval=15", "-o", "ServerAliveCountMax=4"]
        if target.identity is not None:
            common += ["-i", str(target.identity), "-o", "IdentitiesOnly=yes"]
        for o in target.ssh_options:
            common += ["-o", o]
        self._ssh = ["ssh", *common] + (["-p", str(target.port)] if target.port else [])
        self._scp = ["scp", "-q", *common] + (["-P", str(target.port)] if target.port else [])

    def ssh_argv(self, command: str) -> list[str]:
        return [*self._ssh, "--", self.t.host, command]

    def run(self, command: str, timeout: float) -> subprocess.CompletedProcess:
        try:
            return subprocess.run(self.ssh_argv(command), capture_output=True, text=True, timeout=timeout,
                                  stdin=subprocess.DEVNULL)
        except subprocess.TimeoutExpired as exc:
            return subprocess.CompletedProcess(exc.cmd, 124, _text(exc.stdout), _text(exc.stderr) +
                                               f"\ntimed out after {timeout:g} s")

    def copy(self, local: list[Path], remote_dir: str, timeout: float = 600) -> subprocess.CompletedProcess:
        host = self.t.host
        user, at, name = host.rpartition("@")
        if ":" in name and not name.startswith("["):
            host = f"{user}{at}[{name}]"
        argv = [*self._scp, "-r", *map(str, local), f"{host}:{remote_dir}/"]
        try:
            return subprocess.run(argv, capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL)
        except subprocess.TimeoutExpired as exc:
            return subprocess.CompletedProcess(argv, 124, "", _text(exc.stderr) + f"\ntimed out after {timeout:g} s")


def _text(b) -> str:
    return b.decode(errors="replace") if isinstance(b, bytes) else (b or "")


def _last_lines(r: subprocess.CompletedProcess, n: int = 3) -> str:
    lines = [ln for ln in (r.stderr or "").splitlines() + (r.stdout or "").splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error" in ln.lower() or "FAIL" in ln]
    return " | ".join((errors or lines)[-n:]) or f"exit status {r.returncode}"


# -- one target ---------------------------------------------------------------------------------------


@dataclass
class Outcome:
    target: Target
    status: str = "pending"        # installed, unchanged, rolled back, failed, plan
    release: str | None = None
    previous: str | None = None
    message: str = ""
    check: list[str] = field(default_factory=list)
    log: list[str] = field(default_factory=list)   # bootstrap's output
    plan: list[str] = field(default_factory=list)  # dry run: the actions

    @property
    def ok(self) -> bool:
        return self.status in ("installed", "unchanged", "rolled back", "plan")


def probe(remote: Remote, root: str) -> tuple[str | None, str | None]:
    """(current, previous) release names on the target; DeployError if it cannot be reached."""
    q = shlex.quote(root)
    script = (f"r={q}; for l in current previous; do t=; if [ -L \"$r/$l\" ]; then "
              f"t=$(basename \"$(readlink \"$r/$l\")\"); [ -f \"$r/$l/.complete\" ] || t=; fi; echo \"$l=$t\"; done")
    r = remote.run(script, PROBE_TIMEOUT_S)
    if r.returncode != 0:
        raise DeployError(f"cannot reach {remote.t.host} over ssh: {_last_lines(r, 2)}")
    found = dict(re.findall(r"^(current|previous)=(.*)$", r.stdout, re.MULTILINE))
    return found.get("current") or None, found.get("previous") or None


def _sudo(t: Target) -> str:
    return "sudo -n " if t.sudo else ""


def _check_cmd(t: Target) -> str:
    """The check, as root with --sudo (the signing key belongs to the service's user, mode 0600)."""
    q = shlex.quote
    return (f"{_sudo(t)}{q(t.root + '/current/bin/triswarm-companion')} --check "
            f"--config {q(t.root + '/current/companion.toml')}")


def _bootstrap_install_cmd(t: Target, release: Release, staging: str) -> str:
    q = shlex.quote
    args = ["install", "--root", t.root, "--release", release.name, "--from", staging, "--remove-from"]
    if t.python:
        args += ["--python", t.python]
    if t.system_site_packages:
        args.append("--system-site-packages")
    if t.no_deps:
        args.append("--no-deps")
    sudo = "sudo -n " if t.sudo else ""
    return f"{sudo}sh {q(staging + '/bootstrap.sh')} " + " ".join(q(a) for a in args)


def plan_actions(t: Target, release: Release, current: str | None, previous: str | None, *, rollback: bool,
                 built: str) -> list[str]:
    """What a deploy would do, in order (the dry run's output)."""
    q = shlex.quote
    if rollback:
        if not previous:
            return [f"nothing to roll back to: current {current or 'none'}, no previous release"]
        return [f"ssh: {_sudo(t)}sh {t.root}/bootstrap.sh rollback --root {t.root}   "
                f"(current {current} -> {previous}, restart the service where systemd runs)",
                f"ssh: {_check_cmd(t)}"]
    if current == release.name:
        return [f"release {release.name} is already current: unchanged, nothing copied or written",
                f"ssh: {_check_cmd(t)}"]
    where = t.root + "/releases/" + release.name
    return [
        built,
        f"release {release.name}: {release.summary()}" + (" (signing key to be generated)" if release.key_pending else ""),
        f"target {t.host}: current {current or 'none'}, previous {previous or 'none'}",
        "ssh: STAGING=$(mktemp -d /tmp/triswarm-deploy.XXXXXX)   (a staging folder)",
        f"scp: {release.wheel.path.name}, bootstrap.sh, {', '.join(sorted(release.files))} -> STAGING",
        f"ssh: {_bootstrap_install_cmd(t, release, 'STAGING')}",
        f"      venv {t.root}/venv (create with {t.python or 'python3'} or reuse), "
        + ("no dependencies (--no-deps)" if t.no_deps else "dependencies from the wheel's metadata")
        + f", install into {where}, switch {t.root}/current to it"
        + (f" and {t.root}/previous to {current}" if current else "")
        + f", enable and restart {SERVICE} where systemd runs",
        f"ssh: {_check_cmd(t)}",
        f"      if it fails: ssh: {_sudo(t)}sh {q(t.root + '/bootstrap.sh')} abort --root {q(t.root)} "
        f"--release {release.name}   (back to {current or 'nothing'})",
    ]


def deploy_target(t: Target, release: Release, *, dry_run: bool, rollback: bool, built: str,
                  step: Callable[[str], None] = lambda s: None) -> Outcome:
    out = Outcome(t, release=release.name)
    remote = Remote(t)
    try:
        step("asking the target for its current release")
        current, previous = probe(remote, t.root)
    except DeployError as exc:
        out.status, out.message = "failed", str(exc)
        return out
    out.previous = current
    if dry_run:
        out.status = "plan"
        out.plan = plan_actions(t, release, current, previous, rollback=rollback, built=built)
        return out
    if rollback:
        return _rollback(remote, out, current, previous, step)
    if current == release.name:
        step("unchanged; checking")
        out.status, out.message = "unchanged", f"{release.name} is already current"
        if not _check(remote, out):
            out.status = "failed"
            out.message = f"{release.name} is current, but the check fails: {_fails(out)}"
        return out

    step("copying")
    r = remote.run("mktemp -d \"${TMPDIR:-/tmp}/triswarm-deploy.XXXXXX\"", PROBE_TIMEOUT_S)
    staging = r.stdout.strip()
    if r.returncode != 0 or not staging.startswith("/"):
        out.status, out.message = "failed", f"cannot make a staging folder on the target: {_last_lines(r, 2)}"
        return out
    with tempfile.TemporaryDirectory(prefix="triswarm-deploy-") as tmp:
        local = Path(tmp)
        for name, data in release.files.items():
            p = local / name
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(data)
            if name.endswith(".key"):   # the signing key, a certificate's key
                p.chmod(0o600)
        shutil.copy2(t_bootstrap(), local / "bootstrap.sh")
        shutil.copy2(release.wheel.path, local / release.wheel.path.name)
        r = remote.copy(sorted(local.iterdir()), staging)
    if r.returncode != 0:
        remote.run(f"rm -rf {shlex.quote(staging)}", PROBE_TIMEOUT_S)
        out.status, out.message = "failed", f"scp failed: {_last_lines(r, 2)}; nothing changed"
        return out

    step("bootstrap (venv, release, switch, service)")
    r = remote.run(_bootstrap_install_cmd(t, release, staging), BOOTSTRAP_TIMEOUT_S)
    out.log = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
    if r.returncode != 0:
        remote.run(f"rm -rf {shlex.quote(staging)}", PROBE_TIMEOUT_S)
        now, _ = _probe_quietly(remote, t.root)
        back = f"; {now} is current" if now else ""
        out.status = "failed"
        out.message = f"bootstrap failed: {_last_lines(r, 1)}{back}"
        return out

    step("checking")
    if not _check(remote, out):
        step("check failed; rolling back")
        q = shlex.quote
        r = remote.run(f"{_sudo(t)}sh {q(t.root + '/bootstrap.sh')} abort --root {q(t.root)} --release {q(release.name)}",
                       BOOTSTRAP_TIMEOUT_S)
        out.log += [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
        now, _ = _probe_quietly(remote, t.root)
        out.status = "failed"
        out.message = (f"the check failed on {release.name}: {_fails(out)}; "
                       + (f"rolled back to {now}" if now and r.returncode == 0 else
                          "rolled back: no release installed" if r.returncode == 0 else
                          f"the rollback failed too: {_last_lines(r, 1)}"))
        return out
    out.status = "installed"
    out.message = f"{release.name} (previous: {current or 'none'})"
    return out


def t_bootstrap(source: Path = SOURCE) -> Path:
    return source / "deploy" / "bootstrap.sh"


def _probe_quietly(remote: Remote, root: str) -> tuple[str | None, str | None]:
    try:
        return probe(remote, root)
    except DeployError:
        return None, None


def _check(remote: Remote, out: Outcome) -> bool:
    r = remote.run(_check_cmd(out.target), CHECK_TIMEOUT_S)
    out.check = [ln for ln in r.stdout.splitlines() if ln.strip()] or [f"FAIL  check: {_last_lines(r, 2)}"]
    return r.returncode == 0


def _fails(out: Outcome) -> str:
    return "; ".join(ln.split(None, 1)[1] for ln in out.check if ln.startswith("FAIL")) or "see above"


def _rollback(remote: Remote, out: Outcome, current: str | None, previous: str | None,
              step: Callable[[str], None]) -> Outcome:
    t = out.target
    out.release = previous
    if not previous:
        out.status, out.message = "failed", f"no previous release to roll back to (current: {current or 'none'})"
        return out
    step("rolling back")
    q = shlex.quote
    r = remote.run(f"{_sudo(t)}sh {q(t.root + '/bootstrap.sh')} rollback --root {q(t.root)}", BOOTSTRAP_TIMEOUT_S)
    out.log = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
    if r.returncode != 0:
        out.status, out.message = "failed", f"rollback failed: {_last_lines(r, 1)}"
        return out
    step("checking")
    ok = _check(remote, out)
    out.status = "rolled back" if ok else "failed"
    out.message = (f"{previous} is current again (from {current})" if ok else
                   f"rolled back to {previous} (from {current}), but its check fails: {_fails(out)}")
    return out


# -- all targets --------------------------------------------------------------------------------------


def deploy_all(targets: list[Target], *, wheel_path: Path | None, dry_run: bool, rollback: bool,
               source: Path = SOURCE, jobs: int = 8, say: Callable[[str], None] = print,
               progress: Callable[[Target, str], None] = lambda t, s: None) -> list[Outcome]:
    """Deploy (or roll back, or plan) every target, in parallel; an outcome each, in their order."""
    for t in targets:
        validate_target(t)
    if not t_bootstrap(source).is_file():
        raise DeployError(f"{t_bootstrap(source)}: missing; deploy runs from a triswarm checkout")
    keys: dict[Path, bytes | None] = {}
    for t in targets if not rollback else ():   # a rollback ships nothing
        if t.signing_key is not None and t.signing_key not in keys:
            keys[t.signing_key] = ensure_signing_key(t.signing_key, generate=t.generate_signing_key,
                                                     dry_run=dry_run, say=say)
        elif t.signing_key is None and t.generate_signing_key:
            raise DeployError(f"{t.label}: generate_signing_key needs signing_key = FILE (where to keep it)")
    with tempfile.TemporaryDirectory(prefix="triswarm-wheel-") as tmp:
        if rollback:
            wheel, built = None, ""
        elif wheel_path is not None:
            wheel, built = read_wheel(wheel_path), f"use the wheel {wheel_path}"
        else:
            say(f"building the wheel from {source}")
            wheel_file = build_wheel(source, Path(tmp))
            wheel, built = read_wheel(wheel_file), f"build the wheel from {source} (pip wheel --no-deps; done locally " \
                                                   f"for its hash: {wheel_file.name})"
        releases = []
        for t in targets:
            if wheel is None:   # rollback: no release is made
                releases.append(Release("-", Wheel(Path("-"), "-", ""), {}))
                continue
            key = keys.get(t.signing_key) if t.signing_key is not None else None
            pending = t.signing_key is not None and key is None
            releases.append(make_release(t, wheel, key, pending, source))

        def one(i: int) -> Outcome:
            t = targets[i]
            try:
                o = deploy_target(t, releases[i], dry_run=dry_run, rollback=rollback, built=built,
                                  step=lambda s: progress(t, s))
            except Exception as exc:   # one target's surprise must not lose the others' outcomes
                o = Outcome(t, status="failed", message=f"{exc.__class__.__name__}: {exc}")
            progress(t, f"{o.status}: {o.message}" if o.status != "plan" else "planned")
            return o

        with ThreadPoolExecutor(max_workers=max(1, min(jobs, len(targets)))) as pool:
            return list(pool.map(one, range(len(targets))))


def single_target(host: str, drone_id: int, **kw) -> Target:
    t = Target(host=host, drone_id=drone_id, **kw)
    validate_target(t)
    return t


__all__ = ["DeployError", "Target", "Outcome", "Release", "Wheel", "build_wheel", "copy_source", "deploy_all",
           "load_inventory", "make_release", "read_wheel", "single_target"]
