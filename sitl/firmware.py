"""ArduPilot's SITL firmware as processes: each in a run folder of its own and a process group of its
own, started with triswarm's vehicle files (``deploy/ardupilot/``) unchanged, and stopped for sure.

A run folder holds what the firmware reads and writes: ``scripts/triswarm.lua`` (a copy of the
shipped script), ``sitl.parm`` (what a simulated vehicle needs beyond the shipped parameters: no
radio mode switch, calibrations a real vehicle would have made, the airframe's actuator limits),
``eeprom.bin`` (parameters; wiped at every start so the files decide), ``logs/`` (dataflash logs)
and ``firmware.log`` (its console).

Ports: each firmware listens on TCP for its MAVLink links (serial0: the ground station, serial2:
the companion, as on a flight controller's USB and TELEM2; serial1 has a port too, unused), and
sends its outputs to the plant's UDP port. The TCP ports are picked free and confirmed from what
the firmware says it bound; one taken meanwhile costs a restart on other ports. (The firmware
listens on every interface, not only loopback: its own choice.)

Stopping: SIGTERM does not stop it (seen: seconds later it still ran), so ``stop`` sends SIGKILL to
its process group after a grace period. It also exits by itself when its parent process is gone.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

from .errors import SitlError
from .processes import signal_group, spawn

DEPLOY_DIR = Path(__file__).resolve().parents[1] / "deploy" / "ardupilot"
"""The vehicle files a user loads onto a real flight controller: the simulated ones take them unchanged."""
SCRIPT, PARAMS = "triswarm.lua", "triswarm.parm"
SERIAL_GCS, SERIAL_SPARE, SERIAL_COMPANION = 0, 1, 2
STOP_GRACE_S = 2.0
READY_TIMEOUT_S = 20.0
_BOUND = re.compile(r"SERIAL(\d) on TCP port (\d+)")

SITL_PARAMS = (
    ("FLTMODE_CH", 0, "no radio mode switch: nobody holds the simulated transmitter"),
    ("RC1_MIN", 1000, "the simulated radio's calibration: 1000-2000 us"),
    ("RC1_MAX", 2000, ""), ("RC2_MIN", 1000, ""), ("RC2_MAX", 2000, ""), ("RC3_MIN", 1000, ""),
    ("RC3_MAX", 2000, ""), ("RC4_MIN", 1000, ""), ("RC4_MAX", 2000, ""),
    ("COMPASS_OFS_X", 5, "the simulated compasses' offsets, as a calibration would find them"),
    ("COMPASS_OFS_Y", 13, ""), ("COMPASS_OFS_Z", -18, ""), ("COMPASS_OFS2_X", 5, ""), ("COMPASS_OFS2_Y", 13, ""),
    ("COMPASS_OFS2_Z", -18, ""), ("COMPASS_OFS3_X", 5, ""), ("COMPASS_OFS3_Y", 13, ""), ("COMPASS_OFS3_Z", -18, ""),
    ("GPS1_DELAY_MS", 110, "the simulated GPS's lag (SIM_GPS1_LAG_MS, 100 ms) and the driver's reading it at "
                           "50 Hz (10 ms on average), told to the EKF"),
    ("SIM_GPS1_HZ", 10, "an RTK receiver's 10 Hz, not the simulated one's default 5 Hz"),
    ("GPS1_RATE_MS", 100, "and the driver asks it for 10 Hz"),
    ("EK3_SRC1_POSZ", 3, "height from the GPS: the simulated receiver is RTK-class (no noise), the barometer not"),
    ("SERIAL0_PROTOCOL", 2, "the ground station's link: MAVLink 2"),
    ("SERIAL1_PROTOCOL", -1, "nothing on serial1"),
)
"""What a simulated vehicle needs beyond the shipped parameters (name, value, why)."""


class FirmwareError(SitlError, RuntimeError):
    """A firmware would not start (missing, not executable, its ports, its files): one sentence."""


def find_firmware(path: str | os.PathLike | None, env: str = "TRISWARM_ARDUCOPTER") -> Path:
    """The ArduCopter SITL binary: ``path``, else the environment variable ``env``."""
    given = path if path is not None else os.environ.get(env)
    if not given:
        raise FirmwareError(f"no ArduCopter SITL binary: give --firmware PATH or set {env} "
                            "(build one: docs/flight-controllers.md)")
    binary = Path(given).expanduser()
    if not binary.is_file() or not os.access(binary, os.X_OK):
        raise FirmwareError(f"{binary}: not an executable file (an ArduCopter SITL binary: bin/arducopter)")
    return binary


def free_tcp_ports(count: int) -> list[int]:
    """``count`` TCP ports the kernel gave as free just now (bound on port 0, then closed)."""
    socks = []
    try:
        for _ in range(count):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


@dataclass
class FirmwareSpec:
    """One vehicle's firmware: its binary, its run folder, who it is and where it lives."""
    binary: Path
    run_dir: Path
    sysid: int
    home: tuple[float, float, float]
    """Latitude, longitude [deg] and altitude [m] of the simulation's origin (the JSON position's)."""
    start_time_utc: int
    """The firmware's GPS clock at boot [Unix s]: one for the whole swarm, so all agree on the time."""
    physics_port: int
    """The plant's UDP port for this vehicle's outputs."""
    max_rpm: float
    servo_limit_deg: float
    extra_params: tuple[tuple[str, float], ...] = ()


class FirmwareProcess:
    """What every firmware's process has: ``proc``, its console log ``_log`` at ``log_path``."""

    proc: subprocess.Popen | None
    _log: object
    log_path: Path
    STOP_GRACE_S = STOP_GRACE_S

    def last_words(self) -> str:
        return last_words(self.log_path)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self) -> None:
        """SIGTERM to its group, SIGKILL after STOP_GRACE_S (ArduPilot's ignores SIGTERM); wait for it."""
        proc, self.proc = self.proc, None
        stop_group(proc, self.STOP_GRACE_S)
        if self._log is not None:
            self._log.close()
            self._log = None


def last_words(log_path: Path) -> str:
    """A firmware's last line in its console log, and where the log is."""
    try:
        lines = [ln for ln in log_path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        lines = []
    return f"{lines[-1].strip() if lines else 'no output'} (log: {log_path})"


def stop_group(proc: subprocess.Popen | None, grace_s: float) -> None:
    """SIGTERM to a process's group, SIGKILL after ``grace_s``; wait for it."""
    if proc is None:
        return
    for sig, wait_s in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 5.0)):
        signal_group(proc, sig)
        try:
            proc.wait(timeout=wait_s)
            return
        except subprocess.TimeoutExpired:
            continue


@dataclass
class Firmware(FirmwareProcess):
    spec: FirmwareSpec
    proc: subprocess.Popen | None = None
    ports: dict[int, int] = field(default_factory=dict)
    """Serial port number -> the TCP port it listens on."""
    _log: object = None

    @property
    def log_path(self) -> Path:
        return self.spec.run_dir / "firmware.log"

    def prepare(self) -> None:
        """The run folder: the shipped script and parameters, and the simulation's own."""
        s = self.spec
        try:
            (s.run_dir / "scripts").mkdir(parents=True, exist_ok=True)
            shutil.copyfile(DEPLOY_DIR / SCRIPT, s.run_dir / "scripts" / SCRIPT)
            lines = [f"{name} {value:g}  # {why}" if why else f"{name} {value:g}" for name, value, why in SITL_PARAMS]
            lines += [f"TSW_MAX_RPM {s.max_rpm:g}  # the plant's top rotor speed",
                      f"TSW_SRV_DEG {s.servo_limit_deg:g}  # the plant's servo limit"]
            lines += [f"{name} {value:g}" for name, value in s.extra_params]
            (s.run_dir / "sitl.parm").write_text("\n".join(lines) + "\n")
        except OSError as exc:
            raise FirmwareError(f"cannot prepare the run folder {s.run_dir}: {exc.strerror or exc}") from None
        if not (DEPLOY_DIR / PARAMS).is_file():
            raise FirmwareError(f"{DEPLOY_DIR / PARAMS}: missing (the vehicle's parameters, shipped with triswarm)")

    def command(self, ports: dict[int, int]) -> list[str]:
        s = self.spec
        lat, lon, alt = s.home
        return [str(s.binary), "--model", "JSON:127.0.0.1", "--speedup", "1", "--wipe",
                "--home", f"{lat:.9f},{lon:.9f},{alt:.3f},0", "--start-time", str(s.start_time_utc),
                "--sysid", str(s.sysid), "--sim-port-out", str(s.physics_port),
                *(a for n, p in sorted(ports.items()) for a in (f"--serial{n}", f"tcp:{p}")),
                "--defaults", f"{DEPLOY_DIR / PARAMS},{s.run_dir / 'sitl.parm'}"]

    def start(self) -> None:
        """Start it in its run folder, in a process group of its own that ends with this process's
        thread (``processes.spawn``); return once it listens on its ports (FirmwareError if it would
        not)."""
        self.prepare()
        for _ in range(3):
            ports = dict(zip((SERIAL_GCS, SERIAL_SPARE, SERIAL_COMPANION), free_tcp_ports(3)))
            self._log = self.log_path.open("a")
            try:
                self.proc = spawn(self.command(ports), cwd=self.spec.run_dir, stdout=self._log,
                                  stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
            except OSError as exc:
                raise FirmwareError(f"cannot start {self.spec.binary}: {exc.strerror or exc}") from None
            if self._wait_bound(ports):
                self.ports = ports
                return
            self.stop()
        raise FirmwareError(f"the firmware of vehicle {self.spec.sysid} did not start: {self.last_words()}")

    def _wait_bound(self, ports: dict[int, int]) -> bool:
        """Until the firmware says it listens on the GCS port (the companion's is bound at its
        first frames, after the plant answers): False if it exited or said a bind failed."""
        deadline = time.monotonic() + READY_TIMEOUT_S
        while time.monotonic() < deadline:
            text = self.log_path.read_text(errors="replace")
            if "bind failed" in text or self.proc.poll() is not None:
                return False
            bound = {int(n): int(p) for n, p in _BOUND.findall(text)}
            if bound.get(SERIAL_GCS) == ports[SERIAL_GCS]:
                return True
            time.sleep(0.05)
        return False
