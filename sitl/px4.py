"""`triswarm sitl up --autopilot px4`: N PX4 SITL firmwares (a ``px4_sitl_zenoh`` build), each flying
triswarm's plant, each bridged to Zenoh.

The firmware package (``--firmware`` or TRISWARM_PX4): the build's folder (``bin/px4``, ``etc/``)
or its ``.tar.gz``, unpacked once into the run folder. Its ``etc/`` is copied there with the
shipped airframe (``deploy/px4/``) added, as a user adds it to a board's ROMFS.

Order: a Zenoh router first (PX4's Zenoh client does not survive losing it), on a port bound here;
the plant (``px4_hil``: PX4's simulator, one listening port per vehicle at 4560 + its instance,
as PX4 connects to); then each firmware in a run folder of its own (``vehicle-<sysid>``: its
parameters, its logs, ``zenoh/`` with the router's address and its topics under the namespace
``px4_<sysid>``, ``firmware.log``). Stopping: the firmwares, the plant, the router last.

Instances: PX4 takes its ports from its instance number (simulator 4560+i; MAVLink UDP 18570+i for
the ground station, 14580+i onboard, 14280+i and 13030+i for payloads). An instance is used only if
all of them are free when it starts; the simulator's is then held by the plant.

The manifest keeps ``sitl up``'s shape: per vehicle its ``gcs`` link (PX4's own MAVLink port for
a ground station, UDP) and its ``companion`` link (``url``: the ``px4-zenoh://`` link a companion
takes as --fc, with the router's endpoint, the namespace and the domain).
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import socket
import subprocess
import tarfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import zenoh

from triswarm.protocol import frames
from triswarm.protocol import px4_msgs as px4
from triswarm.protocol.airframe import TABLE_1

from .ardupilot import TRUTH_COLUMNS, ArduPilotOptions, split_params, truth_rows
from .params import plant_airframe
from .firmware import FirmwareError, FirmwareProcess, free_tcp_ports
from .physics import Plant
from .processes import spawn
from .px4_hil import HilPhysics, SensorNoise
from .swarm import ground_grid

DEPLOY_DIR = Path(__file__).resolve().parents[1] / "deploy" / "px4"
AIRFRAME = "16100_triswarm_trirotor"
SIMULATOR_BASE_PORT = 4560
UDP_BASES = (18570, 14580, 14280, 13030)
"""PX4 SITL's MAVLink UDP ports of instance i: base + i (ground station, onboard, payload, gimbal)."""
READY_TIMEOUT_S = 90.0
STOP_GRACE_S = 3.0
FIRMWARE_PARAMS = (("EKF2_GPS_DELAY", 0.0, "the simulated receiver has no lag"),
                   ("ZENOH_ENABLE", 1.0, "the uORB bridge to Zenoh, started at boot"))
"""What a simulated vehicle needs beyond the airframe (name, value, why)."""


@dataclass(frozen=True)
class Px4Options(ArduPilotOptions):
    """``ArduPilotOptions``' fields, ``firmware`` the PX4 build (its folder or its .tar.gz), and the
    bridges' ZENOH_DOMAIN_ID."""
    domain: int = 0


def find_package(path: str | os.PathLike | None, env: str = "TRISWARM_PX4") -> Path:
    """The PX4 firmware package: ``path``, else the environment variable ``env`` (FirmwareError: none)."""
    given = path if path is not None else os.environ.get(env)
    if not given:
        raise FirmwareError(f"no PX4 firmware: give --firmware PATH or set {env} (a px4_sitl_zenoh build: its "
                            "folder or its .tar.gz; docs/flight-controllers.md)")
    package = Path(given).expanduser()
    if not package.exists():
        raise FirmwareError(f"{package}: no such file or folder (a px4_sitl_zenoh build: its folder or its .tar.gz)")
    return package


def unpack(package: Path, into: Path) -> Path:
    """The build's folder (``bin/px4`` and ``etc/`` in it): ``package`` itself, or its archive unpacked
    under ``into``."""
    if package.is_dir():
        root = package
    else:
        try:
            with tarfile.open(package) as tar:
                tar.extractall(into, filter="tar")
                tops = {Path(m.name).parts[0] for m in tar.getmembers() if m.name.strip("./")}
        except (tarfile.TarError, OSError) as exc:
            raise FirmwareError(f"{package}: not a readable .tar.gz of a PX4 build ({exc})") from None
        root = into / next(iter(tops)) if len(tops) == 1 else into
    binary = root / "bin" / "px4"
    if not (binary.is_file() and os.access(binary, os.X_OK) and (root / "etc" / "init.d-posix").is_dir()):
        raise FirmwareError(f"{package}: no bin/px4 and etc/init.d-posix in it (a px4_sitl_zenoh build)")
    return root


def free_instances(count: int) -> list[int]:
    """``count`` instance numbers whose ports are all free now (the simulator's TCP, the MAVLink UDP)."""
    found, i = [], 0
    while len(found) < count and i < 1000:
        if _free(socket.SOCK_STREAM, SIMULATOR_BASE_PORT + i) and \
                all(_free(socket.SOCK_DGRAM, base + i) for base in UDP_BASES):
            found.append(i)
        i += 1
    if len(found) < count:
        raise FirmwareError(f"no {count} PX4 instances with free ports (simulator {SIMULATOR_BASE_PORT}+i, "
                            f"MAVLink {', '.join(f'{b}+i' for b in UDP_BASES)})")
    return found


def _free(kind: int, port: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


def open_router(port: int) -> zenoh.Session:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


def bridge_tables(namespace: str) -> tuple[str, str]:
    """(pub.csv, sub.csv) of a vehicle's bridge: the topics the companion reads and writes, under
    ``namespace``. (PX4's default table maps /fmu/in/vehicle_mocap_odometry and
    vehicle_visual_odometry onto the uORB topic vehicle_odometry, which then publishes an empty
    instance: they are left out.)"""
    pub = [f"{px4.topic_path(namespace, 'out', t)};{'sensor_gps' if t == 'vehicle_gps_position' else t};0"
           for t in px4.TOPICS_OUT]
    sub = [f"{px4.topic_path(namespace, 'in', t)};{t};0" for t in px4.TOPICS_IN]
    return "\n".join(pub) + "\n", "\n".join(sub) + "\n"


class Px4Firmware(FirmwareProcess):
    """One PX4 instance in its run folder."""

    STOP_GRACE_S = STOP_GRACE_S

    def __init__(self, root: Path, etc: Path, run_dir: Path, sysid: int, instance: int, router_port: int,
                 params: dict[str, float]) -> None:
        self.root, self.etc, self.run_dir = root, etc, run_dir
        self.sysid, self.instance, self.router_port, self.params = sysid, instance, router_port, params
        self.namespace = f"px4_{sysid}"
        self.proc: subprocess.Popen | None = None
        self._log = None

    @property
    def log_path(self) -> Path:
        return self.run_dir / "firmware.log"

    def start(self) -> None:
        try:
            (self.run_dir / "zenoh").mkdir(parents=True, exist_ok=True)
            (self.run_dir / "zenoh" / "net.txt").write_text(f"client;tcp/127.0.0.1:{self.router_port}\n")
            pub, sub = bridge_tables(self.namespace)
            (self.run_dir / "zenoh" / "pub.csv").write_text(pub)
            (self.run_dir / "zenoh" / "sub.csv").write_text(sub)
            self._log = self.log_path.open("a")
        except OSError as exc:
            raise FirmwareError(f"cannot prepare the run folder {self.run_dir}: {exc.strerror or exc}") from None
        env = {k: v for k, v in os.environ.items() if not k.startswith(("PX4_", "ROS_"))}
        env.update({"PX4_SYS_AUTOSTART": AIRFRAME.split("_")[0], "PX4_PARAM_MAV_SYS_ID": str(self.sysid),
                    **{f"PX4_PARAM_{k}": f"{v:g}" for k, v in self.params.items()}})
        try:
            self.proc = spawn([str(self.root / "bin" / "px4"), "-i", str(self.instance), "-d", "-w", str(self.run_dir),
                               str(self.etc)], cwd=self.run_dir, env=env, stdout=self._log, stderr=subprocess.STDOUT,
                              stdin=subprocess.DEVNULL)
        except OSError as exc:
            raise FirmwareError(f"cannot start {self.root / 'bin' / 'px4'}: {exc.strerror or exc}") from None

    def said(self, text: str) -> bool:
        try:
            return text in self.log_path.read_text(errors="replace")
        except OSError:
            return False



def prepare_etc(root: Path, run_dir: Path) -> Path:
    """The firmware's ``etc/`` with the shipped airframe added, in the run folder."""
    etc = run_dir / "etc"
    try:
        if etc.exists():
            shutil.rmtree(etc)
        shutil.copytree(root / "etc", etc, symlinks=True)
        shutil.copyfile(DEPLOY_DIR / AIRFRAME, etc / "init.d-posix" / "airframes" / AIRFRAME)
    except OSError as exc:
        raise FirmwareError(f"cannot prepare {etc}: {exc.strerror or exc}") from None
    return etc


async def run_px4(opts: Px4Options, on_ready: Callable[[dict], None] | None = None,
                  say: Callable[..., None] = lambda text, warning=False: print(text)) -> dict:
    """Start the router, the plant and the firmwares; fly until a signal (or ``duration_s`` of simulated
    time); return the stats. FirmwareError: a firmware could not start."""
    if opts.n < 1:
        raise ValueError(f"-n must be at least 1, got {opts.n}")
    plant_changes, firmware_params = split_params(opts.params)
    airframe = plant_airframe(TABLE_1, plant_changes)
    plant = Plant(airframe, opts.n, dt_s=1.0 / opts.physics_hz, wind=opts.wind, wind_seed=opts.seed)
    plant.reset(ground_grid(opts.n, opts.spacing_m, opts.first_id))
    sysids = list(range(opts.first_id, opts.first_id + opts.n))
    opts.run_dir.mkdir(parents=True, exist_ok=True)
    root = unpack(find_package(opts.firmware), opts.run_dir / "firmware")
    etc = prepare_etc(root, opts.run_dir)
    truth = None
    if opts.truth_path is not None:
        truth = open(opts.truth_path, "w", buffering=1 << 16)
        truth.write(TRUTH_COLUMNS + "\n")
    every = max(1, round(250.0 / opts.truth_hz))
    samples = [0]

    def log_truth(rows) -> None:
        samples[0] += 1
        if truth is not None and samples[0] % every == 0:
            truth.write(truth_rows(sysids, plant.time_s, rows))

    start_unix_s = float(int(time.time()))
    physics = HilPhysics(plant, sysids, opts.home, start_unix_s, SensorNoise(), opts.seed, log_truth, opts.physics_hz)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    params = {name: value for name, value, _ in FIRMWARE_PARAMS} | dict(firmware_params)
    firmwares: list[Px4Firmware] = []
    router = None
    wall0 = time.monotonic()
    stepping = None
    try:
        router_port = free_tcp_ports(1)[0]
        router = open_router(router_port)
        instances = free_instances(opts.n)
        physics.listen(loop, [SIMULATOR_BASE_PORT + i for i in instances])
        stepping = asyncio.ensure_future(physics.run(stop))
        for sysid, inst in zip(sysids, instances):
            fw = Px4Firmware(root, etc, opts.run_dir / f"vehicle-{sysid}", sysid, inst, router_port, params)
            firmwares.append(fw)
            fw.start()
        await _wait_ready(firmwares, stop)
        if on_ready is not None and not stop.is_set():
            on_ready(_manifest(opts, firmwares, router_port, start_unix_s))
        while not stop.is_set():
            try:
                await asyncio.wait_for(stop.wait(), 0.5)
            except asyncio.TimeoutError:
                pass
            if opts.duration_s is not None and physics.t_s >= opts.duration_s:
                stop.set()
            if truth is not None:
                truth.flush()
            for fw in firmwares:
                if fw.proc is not None and not fw.alive():
                    say(f"vehicle {fw.sysid}: its firmware ended ({fw.last_words()}): its motors stop when the "
                        f"plant stops hearing it, the others fly on", warning=True)
                    fw.proc = None
    finally:
        stop.set()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        await asyncio.gather(*(asyncio.to_thread(fw.stop) for fw in firmwares))
        if stepping is not None:
            await stepping
        physics.close()
        if router is not None:
            router.close()
        if truth is not None:
            truth.close()
    wall = time.monotonic() - wall0
    return {"autopilot": "px4", "sim_time_s": physics.t_s, "wall_time_s": wall, "sensor_steps": physics.sensor_steps,
            "real_time_factor": physics.t_s / wall if wall > 0 else None, **physics.counters, **physics.output_ages(),
            "vehicles": [{"sysid": fw.sysid, "instance": fw.instance} for fw in firmwares]}


async def _wait_ready(firmwares: list[Px4Firmware], stop: asyncio.Event) -> None:
    """Until every firmware says it is ready for takeoff (its estimator converged on the plant's
    sensors); FirmwareError if one ends or READY_TIMEOUT_S passes."""
    deadline = time.monotonic() + READY_TIMEOUT_S
    waiting = list(firmwares)
    while waiting and not stop.is_set():
        for fw in list(waiting):
            if not fw.alive():
                raise FirmwareError(f"the PX4 firmware of vehicle {fw.sysid} ended: {fw.last_words()}")
            if fw.said("Ready for takeoff"):
                waiting.remove(fw)
        if time.monotonic() > deadline:
            raise FirmwareError(f"PX4 of vehicle(s) {', '.join(str(fw.sysid) for fw in waiting)} not ready for takeoff "
                                f"after {READY_TIMEOUT_S:g} s: {waiting[0].last_words()}")
        await asyncio.sleep(0.2)


def _manifest(opts: Px4Options, firmwares: list[Px4Firmware], router_port: int, start_unix_s: float) -> dict:
    lat, lon, alt = opts.home
    start = ground_grid(opts.n, opts.spacing_m, opts.first_id)
    vehicles = []
    for fw, p0 in zip(firmwares, start):
        gcs_port = UDP_BASES[0] + fw.instance
        url = f"px4-zenoh://127.0.0.1:{router_port}/{fw.namespace}?domain={opts.domain}&simulator=1"
        vehicles.append({
            "sysid": fw.sysid, "start_ned_m": [float(v) + 0.0 for v in frames.flip(p0)],
            "links": {"companion": {"url": url, "zenoh": f"tcp/127.0.0.1:{router_port}", "namespace": fw.namespace,
                                    "domain": opts.domain, "transport": "zenoh"},
                      "gcs": {"pymavlink": f"udpout:127.0.0.1:{gcs_port}", "mavsdk": f"udpout://127.0.0.1:{gcs_port}",
                              "host": "127.0.0.1", "port": gcs_port, "transport": "udp"}},
            "run_dir": str(fw.run_dir), "instance": fw.instance, "pid": fw.proc.pid if fw.proc else None})
    return {"home": {"lat_deg": lat, "lon_deg": lon, "alt_m": alt}, "frame": "local NED, origin at home",
            "autopilot": "px4", "speedup": 1.0, "zenoh_router": f"tcp/127.0.0.1:{router_port}",
            "clock": {"lockstep": False, "boot_unix_s": start_unix_s}, "physics_hz": opts.physics_hz,
            "pid": os.getpid(), "vehicles": vehicles, "truth": None if opts.truth_path is None else str(opts.truth_path)}
