"""`triswarm sitl up --autopilot ardupilot`: N ArduCopter SITL firmwares, each flying triswarm's plant.

The firmwares are ArduPilot's own code (``firmware.py`` starts them with the shipped vehicle files);
this process is their physics: one batched plant (wind, servo delay, motor limit as in every
triswarm simulation) stepped on their frames over the JSON interface (``json_physics.py``). Every
firmware's frame k is in before the plant steps, so all firmwares share one clock, and each
firmware's clock moves only when the plant answers: the loop is lockstep by construction. The
firmwares pace themselves at real time (their ``--speedup 1``); the companions fly them as they
would real flight controllers, in real time, on their MAVLink ports.

The manifest keeps ``sitl up``'s shape: per vehicle its ``companion`` and ``gcs`` links, both the
firmware's own TCP ports (its serial2 and serial0). It adds ``autopilot``, each firmware's run
folder, and the truth log: the plant's true position and attitude of every vehicle at
``truth_hz`` of simulated time, stamped with the firmwares' clock (their boot time, which their
SYSTEM_TIME turns into Unix time as it does their telemetry's stamps): what a flight is judged by
beside the firmwares' own telemetry.

A firmware whose process ends leaves the clock at once (within WATCH_EVERY_S): its motors stop,
and the others fly on. (ArduPilot resends its frame after 1 s without an answer, and firmwares kept
waiting for 3 s in flight aborted, one after another, when the answers came again: one firmware's
end must not starve the others.) A firmware alive but silent for FIRMWARE_SILENT_S of wall time
while the others wait (it hangs) leaves the clock too. Either rejoins at its next frame.
"""

from __future__ import annotations

import asyncio
import math
import os
import signal
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from triswarm.protocol import frames
from triswarm.protocol.airframe import TABLE_1
from triswarm.protocol.wind import Wind

from .firmware import SERIAL_COMPANION, SERIAL_GCS, Firmware, FirmwareError, FirmwareSpec
from .json_physics import OutputMap, decode_servo_packet, frame_period_s, state_json
from .physics import SENSOR_COLUMNS, Plant
from .params import AIRFRAME_PARAMS, plant_airframe
from .swarm import ground_grid

FIRMWARE_SILENT_S = 3.0
WATCH_EVERY_S = 0.1
TRUTH_COLUMNS = "sysid,boot_s,x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad"
"""The truth log's header: the firmwares' clock (seconds since their boot: what their telemetry's
stamps count), position in the paper's earth frame (x north, y west, z up, from home), attitude as
the paper's Euler angles."""


@dataclass(frozen=True)
class ArduPilotOptions:
    n: int
    firmware: Path
    run_dir: Path
    home: tuple[float, float, float] = frames.DEFAULT_HOME
    first_id: int = 1
    spacing_m: float = 2.5
    physics_hz: float = 1000.0
    """The plant's step and the firmwares' frame rate [Hz] (ArduCopter wants its gyro at 1.8 times
    its 400 Hz loop at least)."""
    wind: Wind | None = None
    seed: int = 0
    params: tuple[tuple[str, float], ...] = ()
    """Airframe parameters (``params.AIRFRAME_PARAMS``: the plant's) and firmware parameters (the rest)."""
    duration_s: float | None = None
    truth_path: Path | None = None
    truth_hz: float = 50.0


class JsonPhysics:
    """The plant's side of N firmwares' JSON links: one UDP socket each, one clock for all."""

    def __init__(self, plant: Plant, sysids: list[int], output_map: OutputMap = OutputMap(), truth=None,
                 truth_every: int = 20) -> None:
        self.plant = plant
        self.n = plant.n
        self.sysids = sysids
        self.map = output_map
        self.socks: list[socket.socket] = []
        self.addr: list[tuple | None] = [None] * self.n
        self.pwm = np.zeros((self.n, 16))
        self.pending = [False] * self.n
        self.heard_at = [0.0] * self.n
        self.members = set(range(self.n))
        """Vehicles the clock waits for."""
        self.started = False
        self.t_s = 0.0
        self.frames = 0
        self.counters = {"bad_packets": 0, "left": 0, "rejoined": 0}
        self.truth = truth
        self.truth_every = truth_every
        self.on_step: Callable[[], None] = lambda: None

    @property
    def ports(self) -> list[int]:
        return [s.getsockname()[1] for s in self.socks]

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        for i in range(self.n):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
            self.socks.append(s)
            loop.add_reader(s.fileno(), self._readable, i)

    def close(self, loop: asyncio.AbstractEventLoop) -> None:
        for s in self.socks:
            try:
                loop.remove_reader(s.fileno())
            except (RuntimeError, ValueError):
                pass
            s.close()
        self.socks = []

    def _readable(self, i: int) -> None:
        for _ in range(64):
            try:
                data, addr = self.socks[i].recvfrom(512)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                continue
            frame = decode_servo_packet(data)
            if frame is None:
                self.counters["bad_packets"] += 1
                continue
            self.pwm[i] = frame.pwm
            self.addr[i] = addr
            self.pending[i] = True
            self.heard_at[i] = time.monotonic()
            if i not in self.members:
                self.members.add(i)
                self.counters["rejoined"] += 1
        self._step_if_due()

    def _step_if_due(self) -> None:
        if not self.members or not all(self.pending[i] for i in self.members):
            return
        self.started = True
        af = self.plant.airframes
        omega, alpha = self.map.commands(self.pwm, np.array([a.max_rotor_speed_rad_s for a in af]),
                                         np.array([a.servo_limit_rad for a in af]))
        for i in range(self.n):
            if i not in self.members:
                omega[i] = 0.0  # (its firmware is gone: its motors stop)
        self.plant.command(omega, alpha)
        self.plant.advance(1)
        self.frames += 1
        self.t_s = self.plant.time_s
        rows = self.plant.sensors()
        for i in self.members:
            self.pending[i] = False
            try:
                self.socks[i].sendto(state_json(self.t_s, rows[i]), self.addr[i])
            except OSError:
                pass
        if self.truth is not None and self.frames % self.truth_every == 0:
            self._log_truth(rows)
        self.on_step()

    def _log_truth(self, rows: np.ndarray) -> None:
        self.truth.write(truth_rows(self.sysids, self.t_s, rows))

    def watch(self, now: float) -> list[int]:
        """Vehicles whose firmware fell silent while the others wait: out of the clock now."""
        left = []
        if self.started and any(self.pending[i] for i in self.members):
            left = [i for i in sorted(self.members) if not self.pending[i] and now - self.heard_at[i] > FIRMWARE_SILENT_S]
            self.leave(left)
        return left

    def leave(self, vehicles: list[int]) -> None:
        """These vehicles' firmwares leave the clock (their motors stop); the others step on."""
        for i in vehicles:
            if i in self.members:
                self.members.discard(i)
                self.counters["left"] += 1
        if vehicles:
            self._step_if_due()


def truth_rows(sysids: list[int], t_s: float, rows: np.ndarray) -> str:
    """The truth log's lines (``TRUTH_COLUMNS``) of every vehicle's ``Plant.sensors`` row at ``t_s``."""
    pos, eta = rows[:, SENSOR_COLUMNS["position_m"]], rows[:, SENSOR_COLUMNS["euler_rad"]]
    return "".join(f"{sysid},{t_s:.6f},{pos[i, 0]:.5f},{pos[i, 1]:.5f},{pos[i, 2]:.5f},"
                   f"{eta[i, 0]:.6f},{eta[i, 1]:.6f},{eta[i, 2]:.6f}\n" for i, sysid in enumerate(sysids))


def split_params(params) -> tuple[dict[str, float], tuple[tuple[str, float], ...]]:
    """(the plant's airframe parameters, the firmware's parameters) of ``--param``'s."""
    plant = {name: value for name, value in params if name in AIRFRAME_PARAMS}
    return plant, tuple((name, value) for name, value in params if name not in AIRFRAME_PARAMS)


async def run_ardupilot(opts: ArduPilotOptions, on_ready: Callable[[dict], None] | None = None,
                        say: Callable[..., None] = lambda text, warning=False: print(text)) -> dict:
    """Start the firmwares and fly their plant until a signal (or ``duration_s`` of simulated time);
    return the stats. FirmwareError: one could not start."""
    if opts.n < 1:
        raise ValueError(f"-n must be at least 1, got {opts.n}")
    plant_changes, firmware_params = split_params(opts.params)
    airframe = plant_airframe(TABLE_1, plant_changes)
    dt_s = frame_period_s(opts.physics_hz)
    plant = Plant(airframe, opts.n, dt_s=dt_s, wind=opts.wind, wind_seed=opts.seed)
    plant.reset(ground_grid(opts.n, opts.spacing_m, opts.first_id))
    sysids = list(range(opts.first_id, opts.first_id + opts.n))
    start_time_utc = int(time.time())
    truth = None
    if opts.truth_path is not None:
        truth = open(opts.truth_path, "w", buffering=1 << 16)
        truth.write(TRUTH_COLUMNS + "\n")
    every = max(1, round(1.0 / (opts.truth_hz * dt_s)))
    physics = JsonPhysics(plant, sysids, truth=truth, truth_every=every)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    physics.on_step = lambda: stop.set() if opts.duration_s is not None and physics.t_s >= opts.duration_s else None
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    firmwares: list[Firmware] = []
    wall0 = time.monotonic()
    try:
        physics.open(loop)
        for i, sysid in enumerate(sysids):
            spec = FirmwareSpec(opts.firmware, opts.run_dir / f"vehicle-{sysid}", sysid, opts.home, start_time_utc,
                                physics.ports[i], airframe.max_rotor_speed_rad_s * 30.0 / math.pi,
                                math.degrees(airframe.servo_limit_rad), firmware_params)
            firmwares.append(Firmware(spec))
            await asyncio.to_thread(firmwares[-1].start)
        if on_ready is not None:
            on_ready(_manifest(opts, firmwares, start_time_utc, dt_s))
        while not stop.is_set():
            try:
                await asyncio.wait_for(stop.wait(), WATCH_EVERY_S)
            except asyncio.TimeoutError:
                pass
            if truth is not None:
                truth.flush()  # (readable as it grows)
            ended = [i for i in sorted(physics.members) if not firmwares[i].alive()]
            physics.leave(ended)
            for i in ended:
                say(f"vehicle {sysids[i]}: its firmware's process ended: its motors stop, the others fly on "
                    f"({firmwares[i].last_words()})", warning=True)
            for i in physics.watch(time.monotonic()):
                say(f"vehicle {sysids[i]}: no frame from its firmware for {FIRMWARE_SILENT_S:g} s (it hangs): its "
                    f"motors stop, the others fly on", warning=True)
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        physics.close(loop)
        await asyncio.gather(*(asyncio.to_thread(fw.stop) for fw in firmwares))
        if truth is not None:
            truth.close()
    wall = time.monotonic() - wall0
    return {"autopilot": "ardupilot", "sim_time_s": physics.t_s, "wall_time_s": wall, "frames": physics.frames,
            "real_time_factor": physics.t_s / wall if wall > 0 else None, **physics.counters,
            "vehicles": [{"sysid": s, "ports": fw.ports} for s, fw in zip(sysids, firmwares)]}


def _manifest(opts: ArduPilotOptions, firmwares: list[Firmware], start_time_utc: int, dt_s: float) -> dict:
    lat, lon, alt = opts.home
    start = ground_grid(opts.n, opts.spacing_m, opts.first_id)

    def link(port: int) -> dict:
        return {"pymavlink": f"tcp:127.0.0.1:{port}", "mavsdk": f"tcp://127.0.0.1:{port}", "host": "127.0.0.1",
                "port": port, "transport": "tcp"}

    vehicles = []
    for fw, p0 in zip(firmwares, start):
        vehicles.append({"sysid": fw.spec.sysid, "start_ned_m": [float(v) + 0.0 for v in frames.flip(p0)],
                         "links": {"companion": link(fw.ports[SERIAL_COMPANION]), "gcs": link(fw.ports[SERIAL_GCS])},
                         "run_dir": str(fw.spec.run_dir), "pid": fw.proc.pid if fw.proc else None})
    return {"home": {"lat_deg": lat, "lon_deg": lon, "alt_m": alt}, "frame": "local NED, origin at home",
            "autopilot": "ardupilot", "speedup": 1.0,
            "clock": {"lockstep": False, "boot_unix_s": float(start_time_utc)},
            "physics_hz": 1.0 / dt_s, "pid": os.getpid(), "vehicles": vehicles,
            "truth": None if opts.truth_path is None else str(opts.truth_path)}


__all__ = ["ArduPilotOptions", "FirmwareError", "JsonPhysics", "run_ardupilot", "TRUTH_COLUMNS", "truth_rows"]
