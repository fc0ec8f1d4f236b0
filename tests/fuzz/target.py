"""A companion process under fuzz: ``triswarm-companion`` started as gcs/stack.py starts it, on a
flight controller of the test's own (``peers.FakeFC``) and a ground-station port on loopback, with
its stats written at exit (SIGTERM)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

from triswarm.gcs.stack import free_ports, stop_in_turn
from triswarm.protocol.mavlink import new_codec, setup_signing

from .peers import FakeFC, Station

START_TIMEOUT_S = 120.0  # a fresh clone's first companion compiles its kernels
PROBE_LINK_ID = 9  # the signed probes' stream (the fuzz's signed frames are link 7's)
SETUP_RATES_S = 1.0  # the last step of a companion's set-up measures the telemetry's rates over 0.5 s


class CompanionUnderFuzz:
    """Use as a context manager: ``fc`` (the fake flight controller), ``station`` (a ground station
    on its port), ``stop()`` (SIGTERM; the stats it wrote), ``alive()``."""

    def __init__(self, workdir: Path, agent: int = 1, signing_key: bytes | None = None, plan: Path | None = None,
                 zenoh_base: int | None = None, swarm: str | None = None, rate_hz: float = 100.0,
                 exclude_ports: frozenset[int] = frozenset()) -> None:
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.agent, self.key, self.plan = agent, signing_key, plan
        self.zenoh_base, self.swarm, self.rate_hz = zenoh_base, swarm, rate_hz
        self.exclude = exclude_ports
        self.proc: subprocess.Popen | None = None
        self.fc: FakeFC | None = None
        self.station: Station | None = None
        self.stats: dict | None = None

    @property
    def log_path(self) -> Path:
        return self.workdir / "companion.log"

    def log_tail(self, chars: int = 3000) -> str:
        return self.log_path.read_text(errors="replace")[-chars:] if self.log_path.exists() else ""

    def __enter__(self) -> "CompanionUnderFuzz":
        try:
            self._start()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _start(self) -> None:
        self.fc = FakeFC(self.agent, self.rate_hz)
        self.gcs_port = free_ports(1, exclude=self.exclude)[0]
        cmd = [sys.executable, "-m", "triswarm.companion.cli", "--id", str(self.agent),
               "--fc", f"udpout:127.0.0.1:{self.fc.port}", "--gcs", f"udpin:127.0.0.1:{self.gcs_port}",
               "--rate-hz", str(self.rate_hz), "--state-dir", str(self.workdir / "state"),
               "--stats", str(self.workdir / "stats.json"),
               "--gcs-frames-per-s", "0"]  # (the parsers under fuzz, not the flood limit: test_fault_flood)
        if self.key is not None:
            keyfile = self.workdir / "swarm.key"
            keyfile.write_text(self.key.hex() + "\n")
            cmd += ["--signing-key", str(keyfile)]
        if self.plan is not None:
            cmd += [str(self.plan)]
        if self.zenoh_base is not None:
            cmd += ["--zenoh-base-port", str(self.zenoh_base)]
        if self.swarm is not None:
            cmd += ["--swarm", self.swarm]
        self._log = self.log_path.open("w")
        self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self.fc.set_up.wait(0.2):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the companion did not set up (exit {self.proc.poll()}): {self.log_tail()}")
        time.sleep(SETUP_RATES_S)  # (it measures the telemetry's rates, then flies: not a verdict's wait)
        self.station = Station(self.gcs_port)
        if self.key is not None:  # (the companion takes a parameter set only signed)
            self.station.probe_codec = new_codec(self.station.codec.srcSystem, self.station.codec.srcComponent)
            setup_signing(self.station.probe_codec, self.key, PROBE_LINK_ID, clock=time.time)
        if not self.station.probe(self.agent, timeout_s=30.0):
            raise RuntimeError(f"the companion does not answer on its ground-station port: {self.log_tail()}")

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self) -> dict:
        """SIGTERM, and the stats it wrote at exit."""
        if self.proc is not None and self.stats is None:
            stop_in_turn([[self.proc]], timeout_s=30.0, sig=signal.SIGTERM)
            path = self.workdir / "stats.json"
            if self.proc.returncode != 0 or not path.exists():
                raise RuntimeError(f"the companion exited with {self.proc.returncode}: {self.log_tail()}")
            self.stats = json.loads(path.read_text())
        return self.stats

    def __exit__(self, *exc) -> None:
        if self.proc is not None and self.proc.poll() is None:
            stop_in_turn([[self.proc]], timeout_s=10.0, sig=signal.SIGTERM)
        for peer in (self.station, self.fc):
            if peer is not None:
                peer.close()
        if getattr(self, "_log", None) is not None:
            self._log.close()
