"""How ``triswarm deploy`` reaches a target: OpenSSH's own ssh and scp, never a password prompt."""

from __future__ import annotations

import subprocess
from pathlib import Path

from .deploy_release import Target

SSH_CONNECT_TIMEOUT_S = 10


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


def last_lines(r: subprocess.CompletedProcess, n: int = 3) -> str:
    lines = [ln for ln in (r.stderr or "").splitlines() + (r.stdout or "").splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error" in ln.lower() or "FAIL" in ln]
    return " | ".join((errors or lines)[-n:]) or f"exit status {r.returncode}"
