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

gcs/deploy_release.py makes what is shipped (steps 1 and 2), gcs/deploy_ssh.py carries it; this module runs
the steps on each target (3 to 5) and on all of them.
"""

from __future__ import annotations

import re
import shlex
import shutil
import tempfile
import traceback
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from .deploy_release import (SERVICE, SOURCE, DeployError, Release, Target, Wheel, build_wheel, ensure_signing_key,
                             make_release, read_wheel, validate_target)
from .deploy_ssh import Remote, last_lines

PROBE_TIMEOUT_S = 60
BOOTSTRAP_TIMEOUT_S = 1800   # the first install builds the dependencies' environment
CHECK_TIMEOUT_S = 90


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
        raise DeployError(f"cannot reach {remote.t.host} over ssh: {last_lines(r, 2)}")
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
        out.status, out.message = "failed", f"cannot make a staging folder on the target: {last_lines(r, 2)}"
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
        out.status, out.message = "failed", f"scp failed: {last_lines(r, 2)}; nothing changed"
        return out

    step("bootstrap (venv, release, switch, service)")
    r = remote.run(_bootstrap_install_cmd(t, release, staging), BOOTSTRAP_TIMEOUT_S)
    out.log = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
    if r.returncode != 0:
        remote.run(f"rm -rf {shlex.quote(staging)}", PROBE_TIMEOUT_S)
        now, _ = _probe_quietly(remote, t.root)
        back = f"; {now} is current" if now else ""
        out.status = "failed"
        out.message = f"bootstrap failed: {last_lines(r, 1)}{back}"
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
                          f"the rollback failed too: {last_lines(r, 1)}"))
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
    out.check = [ln for ln in r.stdout.splitlines() if ln.strip()] or [f"FAIL  check: {last_lines(r, 2)}"]
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
        out.status, out.message = "failed", f"rollback failed: {last_lines(r, 1)}"
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
    missing = [tool for tool in ("ssh", "scp") if shutil.which(tool) is None]
    if missing:
        raise DeployError(f"{missing[0]} not found: deploy needs OpenSSH's ssh and scp on this machine "
                          f"(Debian: apt-get install openssh-client)")
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
            except Exception as exc:   # a bug: shown as one, and the other targets' outcomes kept
                say(f"{t.label}: a bug in triswarm deploy, not a fault of the target:\n"
                    + "".join(traceback.format_exception(exc)).rstrip())
                o = Outcome(t, status="failed", message=f"a bug in triswarm deploy ({exc.__class__.__name__}: {exc}; "
                                                        f"its traceback is above)")
            progress(t, f"{o.status}: {o.message}" if o.status != "plan" else "planned")
            return o

        with ThreadPoolExecutor(max_workers=max(1, min(jobs, len(targets)))) as pool:
            return list(pool.map(one, range(len(targets))))
