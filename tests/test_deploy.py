"""Deploying the companion: `triswarm deploy` over a real OpenSSH server on loopback, the bootstrap
script on the target, `triswarm-companion --config/--check`, and the systemd unit.

The test starts Debian's /usr/sbin/sshd with a configuration, host key and user key of its own in tmp_path, on
a free loopback port (as root it logs in as root). `make test` installs openssh-server (the Makefile's netns-tools
target); otherwise, as root, the test installs it with apt-get; when it cannot, it skips with the reason (under
CI it fails: ``needs.missing``).

Test-only arrangement: installing numpy, scipy, numba and zenoh into a fresh environment takes minutes, so each
target's <root>/venv is made in advance by the test, with a .pth file that puts this development environment's
site-packages on its path, and the deploys run with --no-deps. Everything else (wheel, release, switch,
rollback, check) is what a drone gets.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import socket
import stat
import subprocess
import sys
import sysconfig
import time
import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest

from triswarm.companion.config import ConfigError, load_config, resolve_options, run_checks
from triswarm.gcs import deploy_release as dp
from triswarm.gcs.stack import stop_in_turn

from .needs import missing

REPO = Path(__file__).resolve().parents[1]
SSHD = Path("/usr/sbin/sshd")
UNIT = REPO / "deploy" / "systemd" / "triswarm-companion.service"
RELEASE_RE = r"\d+\.\d+\.\d+-[0-9a-f]{12}"

pytestmark = pytest.mark.timeout(300)


# -- the SSH server -------------------------------------------------------------------------------------


def _sshd_missing() -> str | None:
    """None when sshd is there (installing it with apt-get as root if needed), else why not."""
    if SSHD.exists():
        return None
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        return "needs OpenSSH's server (/usr/sbin/sshd): run `make test` as root, or apt-get install openssh-server"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    try:
        subprocess.run(["apt-get", "update", "-qq"], capture_output=True, timeout=180, env=env)
        r = subprocess.run(["apt-get", "install", "-y", "-qq", "openssh-server"], capture_output=True, text=True,
                           timeout=300, env=env)
    except subprocess.TimeoutExpired:
        return "apt-get install openssh-server timed out"
    return None if SSHD.exists() else f"apt-get install openssh-server failed: {r.stderr.strip()[-300:]}"


MV_SHIM = """#!/bin/sh
# The test's mv on the target: a real mv, but for the one move that switches <root>/current when the
# test has asked for it to fail (a file <root>/.fail-the-switch, used up by the failure).
for last in "$@"; do :; done
case $last in
    */current)
        trigger="$(dirname "$last")/.fail-the-switch"
        if [ -e "$trigger" ]; then rm -f "$trigger"; echo "mv: cannot move to $last: injected by the test" >&2; exit 1; fi ;;
esac
exec /usr/bin/mv "$@"
"""


def fail_the_switch(root: Path) -> None:
    """The next deploy to ``root`` fails as it switches ``current`` to the new release (``MV_SHIM``)."""
    (root / ".fail-the-switch").touch()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def sshd(tmp_path_factory):
    reason = _sshd_missing()
    if reason:
        missing(reason)
    d = tmp_path_factory.mktemp("sshd")
    for name in ("host_key", "user_key"):
        subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", f"triswarm-test-{name}", "-f", str(d / name)],
                       check=True, capture_output=True, timeout=30)
    (d / "authorized_keys").write_text((d / "user_key.pub").read_text())
    shims = d / "shims"  # on the sessions' PATH: a failure injected on the target (``fail_the_switch``)
    shims.mkdir()
    (shims / "mv").write_text(MV_SHIM)
    (shims / "mv").chmod(0o755)
    port = _free_port()
    (d / "sshd_config").write_text(f"""\
Port {port}
ListenAddress 127.0.0.1
HostKey {d / 'host_key'}
PidFile {d / 'sshd.pid'}
AuthorizedKeysFile {d / 'authorized_keys'}
PubkeyAuthentication yes
PasswordAuthentication no
KbdInteractiveAuthentication no
PermitRootLogin prohibit-password
StrictModes no
UsePAM no
Subsystem sftp /usr/lib/openssh/sftp-server
LogLevel VERBOSE
SetEnv PATH={shims}:/usr/local/bin:/usr/bin:/bin:/usr/local/sbin:/usr/sbin:/sbin
""")
    if os.geteuid() == 0:
        Path("/run/sshd").mkdir(mode=0o755, exist_ok=True)   # sshd's privilege separation folder
    log = open(d / "sshd.log", "w")
    proc = subprocess.Popen([str(SSHD), "-D", "-e", "-f", str(d / "sshd_config")], stdout=log, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 10
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            break
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                pytest.fail(f"sshd did not start: {(d / 'sshd.log').read_text()[-1000:]}")
            time.sleep(0.05)
    host_pub = (d / "host_key.pub").read_text().split()
    (d / "known_hosts").write_text(f"[127.0.0.1]:{port} {host_pub[0]} {host_pub[1]}\n")
    import pwd

    user = pwd.getpwuid(os.getuid()).pw_name
    try:
        yield SimpleNamespace(port=port, key=d / "user_key", known_hosts=d / "known_hosts", user=user, dir=d)
    finally:
        stop_in_turn([[proc]], timeout_s=10)
        log.close()


def ssh_args(sshd) -> list[str]:
    return ["--ssh-port", str(sshd.port), "--identity", str(sshd.key),
            "--ssh-option", f"UserKnownHostsFile={sshd.known_hosts}", "--ssh-option", "StrictHostKeyChecking=yes",
            "--ssh-option", "LogLevel=ERROR"]


def run_deploy(sshd, *args, env_extra=None, timeout=240):
    env = dict(os.environ)
    env.update({"COLUMNS": "200", **(env_extra or {})})
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "triswarm.gcs.deploy_cmd", *ssh_args(sshd), *args],
                       capture_output=True, text=True, timeout=timeout, env=env, cwd=REPO)
    r.elapsed = time.monotonic() - t0
    return r


def prepared_root(base: Path) -> Path:
    """A target root whose venv/ sees this environment's packages (tests only: see the module's docstring)."""
    root = base / "opt-triswarm"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root / "venv")], check=True, timeout=60)
    purelib = subprocess.run([str(root / "venv" / "bin" / "python"), "-c",
                              "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True, timeout=30).stdout.strip()
    Path(purelib, "triswarm-tests-only.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return root


def drone_config(d: Path, *, fc: str = "udpout:127.0.0.1:14600", key: bool = True, zenoh_file: bool = False) -> Path:
    """A drone's configuration: a UDP flight controller, a Zenoh peer on a free port (in the file, or in a Zenoh
    configuration beside it), a signing key beside it."""
    d.mkdir(parents=True, exist_ok=True)
    if key:
        (d / "swarm.key").write_text("ab" * 32 + "\n")
        (d / "swarm.key").chmod(0o600)
    zenoh = f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{_free_port()}"]'
    if zenoh_file:
        (d / "zenoh.json5").write_text(f'{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:{_free_port()}"] }} }}\n')
        zenoh = 'config = "zenoh.json5"'
    (d / "drone.toml").write_text(f"""\
id = 99                        # replaced by --drone
fc = "{fc}"
gcs = "udpin:127.0.0.1:14550"
rate_hz = 200
state_dir = "{d / 'state'}"
{'signing_key = "swarm.key"' if key else ''}
[zenoh]
{zenoh}
""")
    return d / "drone.toml"


def snapshot(root: Path) -> dict:
    """Every path under root: a symlink's target, a file's mtime, mode and content hash."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath, name)
            st = p.lstat()
            if stat.S_ISLNK(st.st_mode):
                out[str(p.relative_to(root))] = ("link", os.readlink(p))
            elif stat.S_ISREG(st.st_mode):
                out[str(p.relative_to(root))] = (st.st_mtime_ns, st.st_mode, hashlib.sha256(p.read_bytes()).hexdigest())
            else:
                out[str(p.relative_to(root))] = ("dir", st.st_mode)
    return out


def current(root: Path) -> str | None:
    link = root / "current"
    return os.readlink(link).split("/")[-1] if link.is_symlink() else None


def previous(root: Path) -> str | None:
    link = root / "previous"
    return os.readlink(link).split("/")[-1] if link.is_symlink() else None


def released(out: str, status: str) -> str:
    m = re.search(rf"drone \d+ \S+: {status}: .*?({RELEASE_RE})", out)
    assert m, out
    return m.group(1)


@pytest.fixture(scope="module")
def wheels(tmp_path_factory):
    """A copy of this checkout (the source of every deploy here: the checkout itself may be edited while the
    tests run), its wheel, and the same code as version 0.1.99 (an upgrade)."""
    d = tmp_path_factory.mktemp("wheels")
    source = dp.copy_source(REPO, d / "source")
    base = dp.build_wheel(source, d / "base")
    src = dp.copy_source(source, d / "src")
    text = (src / "pyproject.toml").read_text()
    bumped_text, n = re.subn(r'(?m)^version = "[^"]+"', 'version = "0.1.99"', text)
    assert n == 1
    (src / "pyproject.toml").write_text(bumped_text)
    bumped = dp.build_wheel(src, d / "bumped")
    return SimpleNamespace(source=source, base=base, bumped=bumped, version=tomllib.loads(text)["project"]["version"])


# -- the deploys --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_install_rerun_upgrade_failures_and_rollback(sshd, wheels, tmp_path):
    root = prepared_root(tmp_path)
    cfg = drone_config(tmp_path / "cfg")
    target = ["--host", f"{sshd.user}@127.0.0.1", "--drone", "4", "--root", str(root)]
    venv = ["--venv-python", sys.executable, "--no-deps", "--source", str(wheels.source)]   # --no-deps: tests only
    common = [*target, "--config", str(cfg), *venv]
    staging_before = set(Path("/tmp").glob("triswarm-deploy.*"))

    # 1. install, building the wheel from the checkout (its copy)
    r = run_deploy(sshd, *common)
    assert r.returncode == 0, r.stdout + r.stderr
    first = released(r.stdout, "installed")
    assert first.startswith(wheels.version + "-") and current(root) == first and previous(root) is None
    assert f"building the wheel from {wheels.source}" in r.stdout
    checks = [ln for ln in r.stdout.splitlines() if "check:" in ln]
    assert checks and all(" ok " in ln or "check: -" in ln for ln in checks), r.stdout
    for what in ("config", "flight controller", "ground station", "zenoh", "signing key", "state dir"):
        assert any(f"{what}:" in ln for ln in checks), (what, r.stdout)
    rel = root / "releases" / first
    assert stat.S_IMODE((rel / "signing.key").stat().st_mode) == 0o600
    assert (rel / "signing.key").read_text().strip() == "ab" * 32
    shipped = tomllib.loads((rel / "companion.toml").read_text())
    assert shipped["id"] == 4 and shipped["signing_key"] == "signing.key"
    assert f"ExecStart={root}/current/bin/triswarm-companion --config {root}/current/companion.toml" in \
        (rel / "triswarm-companion.service").read_text()
    assert (rel / "lib" / f"triswarm-{wheels.version}.dist-info").is_dir()
    assert "systemd is not running here" in r.stdout + r.stderr or Path("/run/systemd/system").is_dir()
    assert set(Path("/tmp").glob("triswarm-deploy.*")) == staging_before   # the staging folder is gone

    # 2. again with the same code (a wheel built separately, other timestamps): unchanged, nothing written
    before = snapshot(root)
    r = run_deploy(sshd, *common, "--wheel", str(wheels.base))
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"unchanged: {first} is already current" in r.stdout
    assert snapshot(root) == before

    # 3. a dry run of the upgrade: the actions, and nothing written
    r = run_deploy(sshd, *common, "--wheel", str(wheels.bumped), "--dry-run")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "plan (dry run, nothing changed)" in r.stdout and f"current {first}" in r.stdout
    assert "bootstrap.sh install" in r.stdout and "--check --config" in r.stdout and "abort" in r.stdout, r.stdout
    assert snapshot(root) == before

    # 4. the upgrade: a new release in force, the old one kept as previous
    r = run_deploy(sshd, *common, "--wheel", str(wheels.bumped))
    assert r.returncode == 0, r.stdout + r.stderr
    second = released(r.stdout, "installed")
    assert second.startswith("0.1.99-") and current(root) == second and previous(root) == first
    assert (root / "releases" / first / ".complete").exists()
    assert (root / "current" / "lib" / "triswarm-0.1.99.dist-info").is_dir()

    # 5. a configuration that fails the check on the target: rolled back, exit status 1 with the reason
    bad = drone_config(tmp_path / "bad", fc="/dev/ttyNOPE0:921600")
    r = run_deploy(sshd, *target, "--config", str(bad), *venv, "--wheel", str(wheels.bumped))
    assert r.returncode == 1, r.stdout + r.stderr
    assert re.search(r"failed: the check failed on \S+: flight controller: /dev/ttyNOPE0: no such file", r.stdout), r.stdout
    assert f"rolled back to {second}" in r.stdout
    assert current(root) == second and previous(root) == first
    assert sorted(p.name for p in (root / "releases").iterdir()) == sorted([first, second])

    # 6. a bootstrap step that fails (the switch itself): bootstrap rolls back by itself
    other = drone_config(tmp_path / "other")
    fail_the_switch(root)
    r = run_deploy(sshd, *target, "--config", str(other), *venv, "--wheel", str(wheels.bumped))
    assert r.returncode == 1, r.stdout + r.stderr
    assert not (root / ".fail-the-switch").exists(), "the injected failure did not happen"
    assert "bootstrap failed" in r.stdout and "injected by the test" in r.stdout and f"{second} is current" in r.stdout
    assert current(root) == second and previous(root) == first
    assert sorted(p.name for p in (root / "releases").iterdir()) == sorted([first, second])

    # 7. --rollback, explicitly: back to the first release (its dry run first); again: forward to the second
    before = snapshot(root)
    r = run_deploy(sshd, *target, "--rollback", "--dry-run")
    assert r.returncode == 0 and f"bootstrap.sh rollback --root {root}   (current {second} -> {first}" in r.stdout, r.stdout
    assert snapshot(root) == before
    r = run_deploy(sshd, *target, "--rollback")
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"rolled back: {first} is current again (from {second})" in r.stdout
    assert current(root) == first and previous(root) == second
    assert (root / "current" / "lib" / f"triswarm-{wheels.version}.dist-info").is_dir()
    r = run_deploy(sshd, *target, "--rollback")
    assert r.returncode == 0 and current(root) == second and previous(root) == first, r.stdout + r.stderr


def test_dry_run_on_a_new_target_writes_nothing(sshd, wheels, tmp_path):
    root = tmp_path / "nothing-here"
    r = run_deploy(sshd, "--host", f"{sshd.user}@127.0.0.1", "--drone", "2", "--root", str(root), "--config",
                   str(drone_config(tmp_path / "cfg")), "--wheel", str(wheels.base), "--dry-run",
                   "--source", str(wheels.source))
    assert r.returncode == 0, r.stdout + r.stderr
    lines = r.stdout.splitlines()
    assert any("plan (dry run, nothing changed)" in ln for ln in lines)
    steps = [ln for ln in lines if re.match(r"\s+\d+\. ", ln)]
    assert len(steps) >= 6 and "current none" in r.stdout and "scp:" in r.stdout, r.stdout
    assert not root.exists()


def test_inventory_deploys_several_targets_with_a_generated_key(sshd, wheels, tmp_path):
    roots = [prepared_root(tmp_path / f"t{i}") for i in (1, 2)]
    drone_config(tmp_path / "cfg", key=False, zenoh_file=True)   # the inventory names it: cfg/drone.toml
    inv = tmp_path / "swarm.toml"
    inv.write_text(f"""\
[defaults]
user = "{sshd.user}"
port = {sshd.port}
identity = "{sshd.key}"
config = "cfg/drone.toml"
python = "{sys.executable}"
no_deps = true                 # tests only: venv/ was made with the development environment's packages
signing_key = "keys/swarm.key"
generate_signing_key = true
ssh_options = ["UserKnownHostsFile={sshd.known_hosts}", "StrictHostKeyChecking=yes", "LogLevel=ERROR"]

[[hosts]]
host = "127.0.0.1"
drone_id = 1
root = "{roots[0]}"

[[hosts]]
host = "127.0.0.1"
drone_id = 2
root = "{roots[1]}"
""")
    r = subprocess.run([sys.executable, "-m", "triswarm.gcs.deploy_cmd", "--inventory", str(inv), "--wheel", str(wheels.base),
                        "--source", str(wheels.source)],
                       capture_output=True, text=True, timeout=240, cwd=REPO, env={**os.environ, "COLUMNS": "200"})
    assert r.returncode == 0, r.stdout + r.stderr
    key = tmp_path / "keys" / "swarm.key"
    assert "generated the signing key" in r.stdout and stat.S_IMODE(key.stat().st_mode) == 0o600
    assert re.fullmatch(r"[0-9a-f]{64}\n", key.read_text())
    assert "2 installed" in r.stdout
    for i, root in enumerate(roots, 1):
        assert re.search(rf"drone {i} {sshd.user}@127.0.0.1:{sshd.port}: installed", r.stdout), r.stdout
        rel = root / "current"
        assert (rel / "signing.key").read_bytes() == key.read_bytes()
        shipped = tomllib.loads((rel / "companion.toml").read_text())
        assert shipped["id"] == i and shipped["zenoh"]["config"] == "zenoh.json5"
        assert (rel / "zenoh.json5").read_text() == (tmp_path / "cfg" / "zenoh.json5").read_text()
    assert r.stdout.count("check: ok    zenoh: session opened") == 2, r.stdout
    assert current(roots[0]) != current(roots[1])   # a drone's configuration is part of its release


def test_pki_ships_the_drones_certificate_and_the_check_opens_mtls(sshd, wheels, tmp_path):
    """`--pki`: the drone gets the CA's certificate, its own certificate and key (0600) and its mTLS
    client configuration with the paths they have on the target, and nothing else of the PKI; the
    check on the target opens a session to a real router with them (mTLS handshake)."""
    import json

    import zenoh

    from triswarm.gcs import pki

    port = _free_port()
    d = tmp_path / "pki"
    pki.init(d, "deploy-test", 3, [f"127.0.0.1:{port}", "gs.example.org"], listen_host="127.0.0.1")
    router_cfg = zenoh.Config.from_file(str(d / "zenoh" / "router-127.0.0.1.json5"))
    router_cfg.insert_json5("connect/endpoints", "[]")   # gs.example.org is not there
    router = zenoh.open(router_cfg)
    try:
        root = prepared_root(tmp_path)
        r = run_deploy(sshd, "--host", f"{sshd.user}@127.0.0.1", "--drone", "2", "--root", str(root),
                       "--config", str(drone_config(tmp_path / "cfg")), "--wheel", str(wheels.base),
                       "--venv-python", sys.executable, "--no-deps", "--source", str(wheels.source),
                       "--pki", str(d), "--zenoh-router", f"127.0.0.1:{port}")
    finally:
        router.close()
    assert r.returncode == 0, r.stdout + r.stderr
    assert "check: ok    zenoh: session opened" in r.stdout, r.stdout
    rel = root / "current"
    assert sorted(p.name for p in (rel / "pki").iterdir()) == ["agent-2.json5", "agent-2.key", "agent-2.pem", "ca.pem"]
    for name in ("ca.pem", "agent-2.pem", "agent-2.key"):
        assert (rel / "pki" / name).read_bytes() == (d / name).read_bytes(), name
    assert stat.S_IMODE((rel / "pki" / "agent-2.key").stat().st_mode) == 0o600
    assert tomllib.loads((rel / "companion.toml").read_text())["zenoh"] == {"config": "pki/agent-2.json5"}
    shipped = json.loads((rel / "pki" / "agent-2.json5").read_text())
    tls = shipped["transport"]["link"]["tls"]
    assert (tls["root_ca_certificate"], tls["connect_certificate"], tls["connect_private_key"]) == \
        tuple(f"{root}/current/pki/{n}" for n in ("ca.pem", "agent-2.pem", "agent-2.key"))
    assert shipped["connect"]["endpoints"] == [f"tls/127.0.0.1:{port}"]   # its router only, not gs.example.org

    # a drone that pki init made no certificate for: refused before anything is copied
    r = run_deploy(sshd, "--host", f"{sshd.user}@127.0.0.1", "--drone", "4", "--root", str(tmp_path / "other"),
                   "--config", str(drone_config(tmp_path / "cfg")), "--wheel", str(wheels.base), "--pki", str(d))
    assert r.returncode == 2 and "no agent-4.pem" in r.stderr and "--drones 4 or more" in r.stderr, r.stdout + r.stderr
    assert not (tmp_path / "other").exists()


def test_unreachable_host_fails_with_the_reason(sshd, wheels, tmp_path):
    r = run_deploy(sshd, "--host", f"{sshd.user}@127.0.0.1", "--drone", "1", "--root", str(tmp_path / "r"),
                   "--wheel", str(wheels.base), "--config", str(drone_config(tmp_path / "cfg")),
                   "--ssh-port", str(_free_port()))
    assert r.returncode == 1 and "cannot reach" in r.stdout and "Connection refused" in r.stdout, r.stdout + r.stderr


@pytest.mark.parametrize("args, message", [
    (["--drone", "1"], "give either --host"),
    (["--host", "root@127.0.0.1"], "--host needs --drone"),
    (["--host", "root@127.0.0.1", "--drone", "300"], "--drone must be between 1 and 255"),
    (["--host", "root@127.0.0.1", "--drone", "1", "--root", "relative/path"], "--root"),
])
def test_bad_options_are_one_sentence(args, message):
    import typer
    from typer.testing import CliRunner

    from triswarm.gcs.deploy_cmd import deploy

    app = typer.Typer(add_completion=False, rich_markup_mode=None)
    app.command()(deploy)
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2 and message in r.stderr, (r.exit_code, r.stdout, r.stderr)
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


# -- the companion's configuration and check ----------------------------------------------------------------


def test_config_file_and_command_line(tmp_path):
    cfg = drone_config(tmp_path)
    values = load_config(cfg)
    assert values["id"] == 99 and values["signing_key"] == tmp_path / "swarm.key" and values["zenoh_mode"] == "peer"
    defaults = {"id": None, "fc": None, "gcs": None, "rate_hz": 200.0, "zenoh_mode": "peer"}
    o = resolve_options(cfg, {**defaults, "id": 7, "rate_hz": 100.0}, given={"id"})
    assert o["id"] == 7 and o["rate_hz"] == 200.0 and o["fc"] == "udpout:127.0.0.1:14600"
    serial = tmp_path / "serial.toml"
    serial.write_text('id = 1\nfc = "/dev/ttyAMA0:921600"\ngcs = "udpin:0.0.0.0:14550"\n')
    assert resolve_options(serial, defaults, set())["fc"] == "/dev/ttyAMA0,921600"   # pymavlink's form
    for text, message in [('idd = 3\n', "unknown key 'idd'"), ('id = "3"\n', "id must be an integer"),
                          ('[zenoh]\nconnect = "tcp/x:1"\n', "zenoh.connect must be a list of strings"),
                          ('id = 3\nfc = "udpout:host"\n', None)]:
        bad = tmp_path / "bad.toml"
        bad.write_text(text)
        if message is None:
            with pytest.raises(ValueError, match="expected udpout:HOST:PORT"):
                resolve_options(bad, {**defaults, "gcs": "udpin:0.0.0.0:1"}, set())
        else:
            with pytest.raises(ConfigError, match=re.escape(message)):
                load_config(bad)
    with pytest.raises(ValueError, match="--gcs is missing"):
        resolve_options(None, {**defaults, "id": 1, "fc": "udp:a:1"}, set())


@pytest.mark.realtime  # (the failed Zenoh check is judged bounded in wall time)
def test_check_lines_and_exit_status(tmp_path):
    cfg = drone_config(tmp_path, fc="/dev/null:57600")
    lines: list[str] = []
    defaults = {"id": None, "fc": None, "gcs": None, "rate_hz": 200.0, "zenoh_mode": "peer"}
    assert run_checks(cfg, defaults, set(), lines.append) == 0, lines
    assert [ln.split(":")[0].split()[-1] for ln in lines] == ["config", "controller", "station", "zenoh", "key", "dir"]
    lines.clear()
    status = run_checks(cfg, {**defaults, "fc": "/dev/ttyNOPE9:921600", "signing_key": tmp_path / "drone.toml",
                              "state_dir": tmp_path / "drone.toml"}, {"fc", "signing_key", "state_dir"}, lines.append)
    assert status == 1
    fails = [ln for ln in lines if ln.startswith("FAIL")]
    assert len(fails) == 3, lines
    assert "/dev/ttyNOPE9" in fails[0] and "not a signing key" in fails[1] and "is not a folder" in fails[2]
    lines.clear()
    assert run_checks(None, defaults, set(), lines.append) == 1 and "--check needs --config" in lines[0]
    # as a process: a Zenoh router that does not answer fails the check, within its bound (3 s)
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "triswarm.companion.cli", "--check", "--config", str(cfg),
                        "--zenoh-mode", "client", "--zenoh-connect", "tcp/192.0.2.1:7447"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and re.search(r"^FAIL  zenoh: ", r.stdout, re.MULTILINE), r.stdout + r.stderr
    assert time.monotonic() - t0 < 15   # the Zenoh attempt is bounded (3 s)


# -- the systemd unit and the bootstrap script ---------------------------------------------------------------


def test_systemd_unit(tmp_path):
    text = UNIT.read_text()
    for line in ("Restart=on-failure", "User=triswarm", "NoNewPrivileges=yes", "ProtectSystem=strict",
                 "ReadWritePaths=/var/lib/triswarm", "PrivateTmp=yes", "SupplementaryGroups=dialout",
                 "StandardError=journal", "Nice=-10", "CPUWeight=1000",
                 "ExecStart=/opt/triswarm/current/bin/triswarm-companion --config /opt/triswarm/current/companion.toml"):
        assert re.search(rf"^{re.escape(line)}$", text, re.MULTILINE), line
    tool = shutil.which("systemd-analyze")
    if tool is None:
        missing("systemd-analyze is not installed (Debian package systemd)")
    # verify wants ExecStart's program to exist: the same unit, run a program that does
    copy = tmp_path / UNIT.name
    copy.write_text(text.replace("ExecStart=/opt/triswarm/current/bin/triswarm-companion", f"ExecStart={shutil.which('true')}"))
    r = subprocess.run([tool, "verify", str(copy)], capture_output=True, text=True, timeout=60)
    # it exits 0 after mere warnings (an unknown key, a bad value): none may be printed either
    assert r.returncode == 0 and not (r.stdout + r.stderr).strip(), r.stdout + r.stderr


def test_bootstrap_is_posix_sh():
    for shell in ("sh", "dash", "bash"):
        if shutil.which(shell):
            r = subprocess.run([shell, "-n", str(REPO / "deploy" / "bootstrap.sh")], capture_output=True, text=True, timeout=30)
            assert r.returncode == 0, (shell, r.stderr)
    r = subprocess.run(["sh", str(REPO / "deploy" / "bootstrap.sh"), "status", "--root", "relative"],
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 1 and "--root must be an absolute path" in r.stderr
