"""What ``triswarm deploy`` ships, and to whom: the wheel of this checkout, the targets (``--host`` or an
inventory), the signing key, and each target's release (its configuration rendered with its drone id,
the files it names, the key, the systemd unit), named after a hash of all of them. No SSH here:
gcs/deploy_ssh.py carries it, gcs/deploy.py runs the steps on each target."""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from .errors import GcsError

DEFAULT_ROOT = "/opt/triswarm"
SERVICE = "triswarm-companion.service"
SOURCE = Path(__file__).resolve().parents[1]   # the checkout this triswarm runs from


class DeployError(GcsError):
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
