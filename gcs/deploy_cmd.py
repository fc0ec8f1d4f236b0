"""``triswarm deploy``: the command line of gcs/deploy.py.

Also runs on its own: ``python -m triswarm.gcs.deploy_cmd ...``. It reports like the rest of the CLI
(gcs/errors.py): a mistake in what was asked (DeployError) in one sentence and exit status 2.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.text import Text

from .deploy import Outcome, deploy_all
from .deploy_release import DEFAULT_ROOT, SOURCE, DeployError, Target, load_inventory, validate_target
from .errors import console, user_errors

_STYLE = {"installed": "green", "unchanged": "green", "rolled back": "yellow", "failed": "red", "plan": "cyan"}


def deploy(
    host: Annotated[Optional[str], typer.Option(help="The target, USER@HOST (or HOST with ssh's default user).")] = None,
    drone: Annotated[Optional[int], typer.Option("--drone", metavar="N", help="The drone's id (1-255): the "
                                                                              "configuration's id.")] = None,
    config: Annotated[Optional[Path], typer.Option(help="The drone's configuration (TOML, as deploy/drone.example.toml, "
                                                        "whose values are the default). Files it names by relative "
                                                        "path are shipped along.")] = None,
    dry_run: Annotated[bool, typer.Option(help="Print the actions and change nothing (the wheel is still built "
                                               "locally, and the target asked which release it runs).")] = False,
    rollback: Annotated[bool, typer.Option(help="Switch the target back to its previous release.")] = False,
    ssh_port: Annotated[Optional[int], typer.Option(help="SSH port.")] = None,
    identity: Annotated[Optional[Path], typer.Option(help="SSH private key (ssh -i).")] = None,
    root: Annotated[str, typer.Option(help="Install root on the target.")] = DEFAULT_ROOT,
    inventory: Annotated[Optional[Path], typer.Option(help="Several targets at once (TOML: [defaults] and [[hosts]] "
                                                           "with host, drone_id, user, port, config, ...).")] = None,
    wheel: Annotated[Optional[Path], typer.Option(help="Deploy this wheel instead of building one from the checkout.")] = None,
    signing_key: Annotated[Optional[Path], typer.Option(help="MAVLink signing key to ship (mode 0600 on the target).")] = None,
    pki: Annotated[Optional[Path], typer.Option(help="The folder of `triswarm pki init`: ship the drone's certificate, key "
                                                     "(0600), the CA's certificate and its Zenoh mTLS configuration.")] = None,
    zenoh_router: Annotated[Optional[str], typer.Option(help="With --pki: connect to this router only, HOST[:PORT] "
                                                              "(the drone's own host's, in a swarm over several hosts).")] = None,
    venv_python: Annotated[Optional[str], typer.Option(help="Interpreter on the target that creates <root>/venv "
                                                            "(default python3; >= 3.11).")] = None,
    system_site_packages: Annotated[bool, typer.Option(help="Create <root>/venv with --system-site-packages (e.g. "
                                                            "Debian's python3-numpy).")] = False,
    no_deps: Annotated[bool, typer.Option("--no-deps", help="Install no dependencies: <root>/venv already has them (images "
                                               "made with them; the tests).")] = False,
    sudo: Annotated[bool, typer.Option(help="Run bootstrap.sh with sudo -n (a non-root SSH user).")] = False,
    ssh_option: Annotated[Optional[list[str]], typer.Option(help="An ssh -o option, KEY=VALUE (repeat), e.g. "
                                                                 "StrictHostKeyChecking=accept-new.")] = None,
    jobs: Annotated[int, typer.Option(help="Targets deployed at once.")] = 8,
    source: Annotated[Path, typer.Option(help="The triswarm checkout to build and take deploy/ from.")] = SOURCE,
) -> None:
    """Install the companion on onboard computers over SSH: wheel, configuration, key, systemd unit; then check."""
    with user_errors():
        if (host is None) == (inventory is None):
            raise DeployError("give either --host USER@HOST with --drone N, or --inventory FILE")
        if jobs < 1:
            raise DeployError(f"--jobs must be at least 1, got {jobs}")
        if wheel is not None and rollback:
            raise DeployError("--rollback takes no --wheel: it switches back to the release already on the target")
        base = dict(config=config, port=ssh_port, identity=identity, root=root, python=venv_python,
                    system_site_packages=system_site_packages, no_deps=no_deps, sudo=sudo, signing_key=signing_key,
                    ssh_options=tuple(ssh_option or ()), pki=pki, zenoh_router=zenoh_router)
        if inventory is not None:
            targets = load_inventory(inventory, Target(host="-", drone_id=1, **base))
        else:
            if drone is None:
                raise DeployError("--host needs --drone N")
            targets = [Target(host=host, drone_id=drone, **base)]
            validate_target(targets[0])
        outcomes = _run(targets, wheel=wheel, dry_run=dry_run, rollback=rollback, source=source, jobs=jobs)
    _report(outcomes)
    if not all(o.ok for o in outcomes):
        raise typer.Exit(code=1)


def _run(targets: list[Target], **kw) -> list[Outcome]:
    lock = threading.Lock()
    with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(), console=console,
                  transient=True, disable=not console.is_terminal) as bar:
        tasks = {t: bar.add_task(f"{t.label}: waiting") for t in targets}

        def progress(t: Target, what: str) -> None:
            with lock:
                bar.update(tasks[t], description=f"{t.label}: {what}")

        def say(text: str) -> None:
            bar.console.print(text, markup=False, highlight=False, soft_wrap=True)

        return deploy_all(targets, wheel_path=kw["wheel"], dry_run=kw["dry_run"], rollback=kw["rollback"],
                          source=kw["source"], jobs=kw["jobs"], say=say, progress=progress)


def _report(outcomes: list[Outcome]) -> None:
    for o in outcomes:
        style = _STYLE.get(o.status, "white")
        if o.status == "plan":
            console.print(Text(f"{o.target.label}: plan (dry run, nothing changed)", style=style), soft_wrap=True)
            for n, action in enumerate(o.plan, 1):
                console.print(f"  {n}. {action}", markup=False, highlight=False, soft_wrap=True)
            continue
        console.print(Text.assemble((f"{o.target.label}: {o.status}", style), f": {o.message}"), soft_wrap=True)
        if o.status == "failed" and o.log:
            for line in o.log[-8:]:
                console.print(f"  | {line}", markup=False, highlight=False, soft_wrap=True)
        elif o.log:   # what bootstrap says of the service (installed and running, or why not) and warnings
            for line in o.log:
                if "service:" in line or "warning" in line.lower() or "creating the service user" in line:
                    console.print(f"  {line}", markup=False, highlight=False, soft_wrap=True)
        for line in o.check:
            console.print(f"  check: {line}", markup=False, highlight=False, soft_wrap=True)
    if len(outcomes) > 1:
        counts: dict[str, int] = {}
        for o in outcomes:
            counts[o.status] = counts.get(o.status, 0) + 1
        console.print(", ".join(f"{n} {s}" for s, n in counts.items()), soft_wrap=True)


def main() -> None:
    app = typer.Typer(add_completion=False, rich_markup_mode=None)
    app.command()(deploy)
    app()


if __name__ == "__main__":
    main()
