"""The per-drone configuration of ``triswarm-companion`` (``--config FILE``) and its ``--check``.

The file is TOML; its keys are the command-line options' names (``options.OPTIONS``;
``deploy/drone.example.toml`` shows them all)::

    id = 3
    fc = "/dev/ttyAMA0:921600"          # serial DEVICE:BAUD (or DEVICE,BAUD), or a pymavlink URL
    gcs = "udpin:0.0.0.0:14550"
    rate_hz = 200
    state_dir = "/var/lib/triswarm"
    signing_key = "signing.key"          # relative paths are relative to this file's folder
    [zenoh]
    config = "zenoh.json5"               # or mode / listen / connect / base_port

An option given on the command line wins over the file. Unknown keys, and values of the wrong
type, are errors (one sentence naming the key), so a typo cannot silently fall back to a default.

``--check`` prints one line per check and says whether the drone is ready: the configuration is
valid, the flight controller's port is there (a serial device that exists, or a UDP/TCP URL that
parses), a Zenoh session opens with the configured Zenoh settings within 3 s (in client mode:
a router answered), the signing key (if any) is readable, and the state folder is writable.
Nothing is written, and nothing is sent to the flight controller.
"""

from __future__ import annotations

import json
import os
import re
import stat
import threading
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .errors import CompanionError
from .px4_link import is_px4_zenoh
from .px4_link import parse_url as parse_px4_url
from .options import BY_FILE_KEY, OPTIONS, REQUIRED

ZENOH_CHECK_TIMEOUT_S = 3.0

_URL_PREFIXES = ("udpin:", "udpout:", "udpbcast:", "udp:", "tcpin:", "tcp:")
SERIAL_PREFIX = "serial://"  # MAVSDK's form of a serial port


class ConfigError(CompanionError, ValueError):
    """What the operator wrote (an option, a link, the configuration file) that cannot be used: one
    sentence naming it."""


def load_config(path: Path) -> dict[str, Any]:
    """The file's settings as option name -> value, checked and with paths resolved against the
    file's folder. ConfigError for anything wrong."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such configuration file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the configuration ({exc.__class__.__name__})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    flat: dict[str, Any] = {}
    for key, value in data.items():
        if key == "zenoh":
            if not isinstance(value, dict):
                raise ConfigError(f"{path}: [zenoh] must be a table")
            flat.update({f"zenoh.{k}": v for k, v in value.items()})
        else:
            flat[key] = value
    out: dict[str, Any] = {}
    for key, value in flat.items():
        if key not in BY_FILE_KEY:
            known = ", ".join(sorted(BY_FILE_KEY))
            raise ConfigError(f"{path}: unknown key {key!r} (known: {known})")
        opt = BY_FILE_KEY[key]
        out[opt.name] = _convert(path, key, opt.kind, value)
    return out


def _convert(path: Path, key: str, kind: str, value: Any) -> Any:
    def bad(what: str) -> ConfigError:
        return ConfigError(f"{path}: {key} must be {what}, got {value!r}")

    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return value
    if kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad("a number")
        return float(value)
    if kind == "bool":
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if kind == "str":
        if not isinstance(value, str) or not value:
            raise bad("a non-empty string")
        return value
    if kind == "strlist":
        if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
            raise bad("a list of strings")
        return tuple(value)
    if kind == "path":
        if not isinstance(value, str) or not value:
            raise bad("a path (string)")
        p = Path(value).expanduser()
        return p if p.is_absolute() else path.parent / p
    raise AssertionError(kind)


def explicit_options(ctx) -> set[str]:
    """The options of a typer/click context that were given (command line or environment), not
    left at their defaults."""
    given = set()
    for name in ctx.params:
        source = ctx.get_parameter_source(name)
        if source is not None and source.name not in ("DEFAULT", "DEFAULT_MAP"):
            given.add(name)
    return given


def resolve_options(config_path: Path | None, params: dict[str, Any], given: set[str]) -> dict[str, Any]:
    """The companion's options: the configuration file's, overridden by those given on the
    command line. Checks that --id, --fc and --gcs are known and every value in range, and writes a
    serial port's baud rate the way pymavlink reads it (DEVICE,BAUD)."""
    values = dict(params)
    if config_path is not None:
        for name, value in load_config(config_path).items():
            if name not in given:
                values[name] = value
    for name in REQUIRED:
        if values.get(name) is None:
            where = f" or set {name} in {config_path}" if config_path is not None else " (or use --config FILE)"
            raise ConfigError(f"--{name} is missing: give it{where}")
    for opt in OPTIONS:
        value = values.get(opt.name, opt.default)
        values[opt.name] = value
        problem = None if value is None or opt.check is None else opt.check(value)
        if problem:
            raise ConfigError(problem)
    values["fc"] = fc_url(values["fc"])
    values["gcs"] = link_url(values["gcs"], "gcs")
    return values


def fc_url(text: str) -> str:
    """The flight-controller link: PX4's Zenoh bridge (``px4-zenoh://``), or a MAVLink link (``link_url``)."""
    if is_px4_zenoh(text.strip()):
        try:
            parse_px4_url(text.strip())
        except ValueError as exc:
            raise ConfigError(f"--fc {exc}") from None
        return text.strip()
    return link_url(text, "fc")


def link_url(text: str, what: str = "link") -> str:
    """A MAVLink link as pymavlink wants it. A serial port may be written DEVICE:BAUD (as in the
    per-drone configuration) or DEVICE,BAUD (pymavlink's own form); both become DEVICE,BAUD.
    ConfigError for a link that does not parse."""
    kind, _, _ = parse_link(text, what)
    if kind == "serial":
        device, baud = _split_serial(text)
        return device if baud is None else f"{device},{baud}"
    return text


def parse_link(text: str, what: str = "link") -> tuple[str, str, int | None]:
    """(kind, device or host, baud or port) of a MAVLink link: kind is "serial", "udp" or "tcp"."""
    text = text.strip()
    low = text.lower()
    for prefix in _URL_PREFIXES:
        if low.startswith(prefix):
            rest = text[len(prefix):]
            host, sep, port = rest.rpartition(":")
            if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
                raise ConfigError(f"--{what} {text!r}: expected {prefix}HOST:PORT with a port number 0-65535")
            return ("udp" if prefix.startswith("udp") else "tcp"), host, int(port)
    if low.startswith(SERIAL_PREFIX) or text.startswith("/") or re.fullmatch(r"COM\d+([,:]\d+)?", text, re.IGNORECASE):
        device, baud = _split_serial(text)
        if baud is not None and baud <= 0:
            raise ConfigError(f"--{what} {text!r}: the baud rate must be positive")
        return "serial", device, baud
    raise ConfigError(f"--{what} {text!r}: expected a serial port (/dev/ttyACM0:921600, /dev/ttyACM0,921600 or "
                      f"serial:///dev/ttyACM0:921600) or a pymavlink URL "
                      f"({', '.join(p + 'HOST:PORT' for p in ('udpin:', 'udpout:', 'tcp:'))})")


def _split_serial(text: str) -> tuple[str, int | None]:
    text = text.strip()
    if text.lower().startswith(SERIAL_PREFIX):  # MAVSDK's serial:///dev/ttyACM0:921600
        text = text[len(SERIAL_PREFIX):]
    m = re.fullmatch(r"(.+?)[,:](\d+)", text)
    if m and not os.path.exists(text):
        return m.group(1), int(m.group(2))
    return text, None


# -- --check ----------------------------------------------------------------------------------


class Checks:
    def __init__(self, emit: Callable[[str], None]) -> None:
        self.emit = emit
        self.failed = 0

    def ok(self, what: str, detail: str) -> None:
        self.emit(f"ok    {what}: {detail}")

    def fail(self, what: str, detail: str) -> None:
        self.failed += 1
        self.emit(f"FAIL  {what}: {detail}")

    def info(self, what: str, detail: str) -> None:
        self.emit(f"-     {what}: {detail}")


def run_checks(config_path: Path | None, params: dict[str, Any], given: set[str],
               emit: Callable[[str], None] = print) -> int:
    """``triswarm-companion --check``: one line per check; the exit status (0 ready, 1 not)."""
    c = Checks(emit)
    if config_path is None:
        c.fail("config", "--check needs --config FILE (the per-drone configuration)")
        return 1
    try:
        v = resolve_options(config_path, params, given)
    except ConfigError as exc:
        c.fail("config", str(exc))
        return 1
    c.ok("config", f"{config_path} (drone {v['id']})")
    _check_fc(c, v["fc"])
    _check_link(c, "ground station", v["gcs"])
    _check_zenoh(c, v)
    _check_signing_key(c, v.get("signing_key"))
    _check_state_dir(c, v.get("state_dir"))
    if v.get("plan") is not None:
        _check_plan(c, Path(v["plan"]))
    return 1 if c.failed else 0


def _check_fc(c: Checks, url: str) -> None:
    if is_px4_zenoh(url):
        endpoint, namespace, domain, simulator = parse_px4_url(url)
        c.ok("flight controller", f"PX4 over its Zenoh bridge: router {endpoint}, namespace {namespace or '(none)'}, "
                                  f"domain {domain}{', a simulator' if simulator else ''}")
        return
    kind, where, num = parse_link(url, "fc")
    if kind != "serial":
        c.ok("flight controller", f"{url} ({kind.upper()} {where} port {num})")
        return
    try:
        st = os.stat(where)
    except OSError as exc:
        c.fail("flight controller", f"{where}: {exc.strerror.lower() if exc.strerror else exc}")
        return
    if not stat.S_ISCHR(st.st_mode):
        c.fail("flight controller", f"{where} is not a character device")
        return
    access = "read/write" if os.access(where, os.R_OK | os.W_OK) else "no read/write access for this user"
    c.ok("flight controller", f"{where} present (serial, {num or 'default'} baud, {access})")


def _check_link(c: Checks, what: str, url: str) -> None:
    kind, where, num = parse_link(url, what)
    if kind == "serial":
        present = os.path.exists(where)
        (c.ok if present else c.fail)(what, f"{where} {'present' if present else 'missing'} (serial)")
    else:
        c.ok(what, f"{url} ({kind.upper()} {where} port {num})")


def _zenoh_check_config(v: dict[str, Any]):
    """The companion's Zenoh configuration, without its listen endpoints: the check must not take
    the running companion's ports, and only needs to reach the others."""
    import zenoh

    from .zenoh_session import peer_config, tune

    if v.get("zenoh_config") is not None:
        try:
            cfg = tune(zenoh.Config.from_file(str(v["zenoh_config"])))
        except Exception as exc:  # zenoh's own error type for a bad file
            raise ConfigError(f"{v['zenoh_config']}: not a usable Zenoh configuration ({exc})") from None
        mode = json.loads(cfg.get_json("mode")) if _has(cfg, "mode") else "peer"
        connect = json.loads(cfg.get_json("connect/endpoints")) if _has(cfg, "connect/endpoints") else []
        source = str(v["zenoh_config"])
    elif v.get("zenoh_listen") or v.get("zenoh_connect"):
        mode, connect = v.get("zenoh_mode") or "peer", list(v.get("zenoh_connect") or ())
        cfg = peer_config([], connect, mode)
        source = "endpoints of the configuration"
    else:
        mode, connect = "peer", []
        cfg = peer_config([], [], "peer")
        source = "default loopback peers"
    cfg.insert_json5("listen/endpoints", "[]")
    cfg.insert_json5("connect/timeout_ms", str(int(ZENOH_CHECK_TIMEOUT_S * 1000) - 500))
    if isinstance(connect, dict):  # per-mode endpoints: {router: [...], peer: [...], client: [...]}
        connect = connect.get(mode, [])
    return cfg, mode, list(connect), source


def _has(cfg, key: str) -> bool:
    try:
        return cfg.get_json(key) not in ("null", "")
    except Exception:
        return False


def _check_zenoh(c: Checks, v: dict[str, Any]) -> None:
    try:
        cfg, mode, connect, source = _zenoh_check_config(v)
    except ConfigError as exc:
        c.fail("zenoh", str(exc))
        return
    except ImportError as exc:
        c.fail("zenoh", f"eclipse-zenoh is not importable ({exc})")
        return
    from .zenoh_session import close_session, open_session

    box: dict[str, Any] = {}

    def attempt() -> None:
        try:
            box["session"] = open_session(cfg)
        except Exception as exc:
            box["error"] = exc

    t0 = time.monotonic()
    th = threading.Thread(target=attempt, name="zenoh-check", daemon=True)
    th.start()
    th.join(ZENOH_CHECK_TIMEOUT_S)
    where = f"{mode} mode, {source}" + (f": {', '.join(connect)}" if connect else "")
    if th.is_alive():
        c.fail("zenoh", f"no session within {ZENOH_CHECK_TIMEOUT_S:g} s ({where})")
        return
    if "error" in box:
        reason = str(box["error"]).split(" at /")[0].strip()
        c.fail("zenoh", f"cannot open a session ({where}): {reason}")
        return
    session = box["session"]
    try:
        routers: list = []
        peers: list = []
        wait_until = min(t0 + ZENOH_CHECK_TIMEOUT_S, time.monotonic() + 1.0)  # for the first peer to answer
        while True:
            routers, peers = list(session.info.routers_zid()), list(session.info.peers_zid())
            if routers or peers or not connect or time.monotonic() > wait_until:
                break
            time.sleep(0.05)
        if mode == "client" and not routers:
            c.fail("zenoh", f"no router reached ({where})")
        else:
            c.ok("zenoh", f"session opened in {time.monotonic() - t0:.1f} s ({where}); "
                          f"{len(routers)} router(s), {len(peers)} peer(s) seen")
    finally:
        close_session(session)


def _check_signing_key(c: Checks, path: Path | None) -> None:
    if path is None:
        c.info("signing key", "none configured: the ground-station link is not signed")
        return
    from .state import read_signing_key

    try:
        read_signing_key(Path(path))
    except ValueError as exc:
        c.fail("signing key", str(exc))
        return
    mode = stat.S_IMODE(os.stat(path).st_mode)
    note = "" if mode & 0o077 == 0 else f"; warning: mode {mode:04o}, others can read it (chmod 600)"
    c.ok("signing key", f"{path} readable, 32 bytes{note}")


def _check_state_dir(c: Checks, path: Path | None) -> None:
    if path is None:
        c.info("state dir", "none configured: a restarted companion does not resume its mission")
        return
    path = Path(path)
    if path.is_dir():
        ok = os.access(path, os.W_OK | os.X_OK)
        (c.ok if ok else c.fail)("state dir", f"{path} {'writable' if ok else 'not writable by this user'}")
        return
    if path.exists():
        c.fail("state dir", f"{path} is not a folder")
        return
    parent = next((p for p in path.parents if p.exists()), None)
    if parent is not None and os.access(parent, os.W_OK | os.X_OK):
        c.ok("state dir", f"{path} absent, will be created (under {parent})")
    else:
        c.info("state dir", f"{path} absent (systemd's StateDirectory= creates it for the service)")


def _check_plan(c: Checks, path: Path) -> None:
    try:
        tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        c.fail("plan", f"{path}: {exc.__class__.__name__}: {exc}")
        return
    c.ok("plan", f"{path} readable TOML (validated when the companion loads it)")
