"""triswarm's plant as the simulator of N PX4 firmwares, over PX4's ``simulator_mavlink`` interface.

Each PX4 instance connects as a TCP client to its simulator port and takes MAVLink: HIL_SENSOR
(the IMU of id 0 sets its clock: PX4 in SITL is in lockstep with whoever sends it) and HIL_GPS; it
answers with HIL_ACTUATOR_CONTROLS (its output channels: motors 0..1, servos -1..1), sent when its
outputs change.

The plant steps on one clock for all, a sensor period (SENSOR_HZ) at a time, paced at real time;
every PX4's clock is the plant's (each HIL_SENSOR sets it). The plant does not wait for PX4's
outputs: PX4 sends them when they change, which in offboard mode with direct actuator setpoints is
when the companion's setpoints arrive (at its estimator's rate, not the sensors'); a plant that
waited for an answer to every HIL_SENSOR would stand still between them, and one that waited for
the companions' answers to PX4's estimates would let PX4's UTC time, which is the host's, run away
from the simulation whenever it waited. Each step applies the
newest outputs of every firmware heard in the last FIRMWARE_SILENT_S (a silent one's motors stop;
the others fly on).

What the firmware reads, made from the plant's true state with stated noise (``SensorNoise``):
- HIL_SENSOR: accelerometer (specific force, FRD [m/s^2]), gyro (FRD [rad/s]), magnetometer (the
  World Magnetic Model's field at home, in the body [gauss]), barometer (ISA pressure at the
  altitude [hPa], temperature [degC]) and its pressure altitude;
- HIL_GPS at GPS_HZ: position (``frames.LocalProjection`` from home, as PX4 projects), velocity
  NED, fix 3D, the accuracies the noise has, and the time: this host's clock as it is sent (PX4's
  UTC time, what its clock is read as over the bridge; PX4 in SITL takes its realtime clock, which
  it says over MAVLink, from the host too: one clock, whoever reads it).
"""

from __future__ import annotations

import asyncio
import collections
import datetime
import math
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pygeomag import GeoMag

from triswarm.protocol import frames
from triswarm.protocol.mavlink import decode_actuators, mavlink, new_codec

from .physics import SENSOR_COLUMNS, Plant

SENSOR_HZ = 250.0
"""HIL_SENSOR rate: PX4's simulated IMU rate (IMU_INTEG_RATE 250 in its SITL start-up)."""
GPS_HZ = 10.0
FIRMWARE_SILENT_S = 3.0
CATCH_UP = 1.25
"""A plant behind the wall clock runs at most this many simulated seconds per wall second."""
OUTPUT_AGES_KEPT = 100_000
"""The newest outputs' ages kept for the run's statistics (over two minutes of six drones at PX4's 125 Hz)."""
SIM_SYSID, SIM_COMPID = 0, 51
"""What the simulator's frames say they are from (PX4's simulator_mavlink does not check)."""
FIELDS_IMU_MAG_BARO = 0x1FFF
"""HIL_SENSOR fields_updated: accel, gyro, mag, pressures, altitude, temperature."""
_FLIP = np.array([1.0, -1.0, -1.0])
_QFLIP = np.array([1.0, 1.0, -1.0, -1.0])


@dataclass(frozen=True)
class SensorNoise:
    """White noise (one standard deviation) on what the firmware reads."""
    accel_m_s2: float = 0.02
    gyro_rad_s: float = 0.002
    mag_gauss: float = 0.002
    baro_hpa: float = 0.005
    """About 4 cm of altitude."""
    gps_position_m: float = 0.01
    """An RTK receiver's fix."""
    gps_velocity_m_s: float = 0.02


def earth_field_ned_gauss(lat_deg: float, lon_deg: float, alt_m: float, when: datetime.date) -> np.ndarray:
    """The World Magnetic Model's field at a place and date, NED [gauss]."""
    year = when.year + (when.timetuple().tm_yday - 1) / 365.25
    r = GeoMag().calculate(glat=lat_deg, glon=lon_deg, alt=alt_m / 1000.0, time=year, allow_date_outside_lifespan=True)
    return np.array([r.x, r.y, r.z]) * 1e-5  # (nT)


def isa_pressure_hpa(alt_m: float) -> float:
    """The International Standard Atmosphere's pressure at an altitude [m]."""
    return 1013.25 * (1.0 - 2.25577e-5 * alt_m) ** 5.25588


class HilPhysics:
    """The plant's side of N firmwares' simulator links: a listening socket each (bound by the caller's
    ports), one clock for all."""

    def __init__(self, plant: Plant, sysids: list[int], home: tuple[float, float, float], start_unix_s: float,
                 noise: SensorNoise = SensorNoise(), seed: int = 0, on_sample: Callable[[np.ndarray], None] | None = None,
                 physics_hz: float = 1000.0, unix_clock: Callable[[], float] = time.time) -> None:
        self.plant, self.n, self.sysids = plant, plant.n, sysids
        self.home, self.unix_clock = home, unix_clock
        self.noise, self.rng = noise, np.random.default_rng(seed)
        self.projection = frames.LocalProjection(*home)
        self.field_ned = earth_field_ned_gauss(*home, datetime.datetime.fromtimestamp(start_unix_s, datetime.UTC).date())
        self.steps_per_sensor = max(1, round(physics_hz / SENSOR_HZ))
        self.gps_every = max(1, round(SENSOR_HZ / GPS_HZ))
        self.listeners: list[socket.socket] = []
        self.conns: list[socket.socket | None] = [None] * self.n
        self.codecs = [new_codec(SIM_SYSID, SIM_COMPID) for _ in range(self.n)]
        self.controls = np.zeros((self.n, 16))
        self.heard_at = [0.0] * self.n
        self.members: set[int] = set()
        self.sensor_steps = 0
        self.on_sample = on_sample
        """Called with the plant's sensor rows after every sensor period (the truth log)."""
        self.counters = {"bad_frames": 0, "left": 0, "joined": 0, "send_errors": 0, "behind_max_ms": 0}
        self.output_age_s: collections.deque[float] = collections.deque(maxlen=OUTPUT_AGES_KEPT)
        """How old each HIL_ACTUATOR_CONTROLS was when it came [s, simulated]: the plant's time then
        (from which it applies) minus PX4's stamp (when PX4 made the output)."""
        self._loop: asyncio.AbstractEventLoop | None = None

    @property
    def t_s(self) -> float:
        return self.plant.time_s

    def output_ages(self) -> dict[str, float | None]:
        """The outputs' ages when they came (``output_age_s``): median and 99th percentile [ms]."""
        if not self.output_age_s:
            return {"output_age_p50_ms": None, "output_age_p99_ms": None}
        p50, p99 = np.percentile(np.array(self.output_age_s), [50, 99]) * 1e3
        return {"output_age_p50_ms": round(float(p50), 3), "output_age_p99_ms": round(float(p99), 3)}

    def listen(self, loop: asyncio.AbstractEventLoop, ports: list[int]) -> None:
        """Listen on ``ports`` (one per vehicle, bound here: OSError if one is taken)."""
        self._loop = loop
        for i, port in enumerate(ports):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                s.close()
                self.close()
                raise
            s.listen(1)
            s.setblocking(False)
            self.listeners.append(s)
            loop.add_reader(s.fileno(), self._accept, i)

    def close(self) -> None:
        for s in self.listeners + [c for c in self.conns if c is not None]:
            if self._loop is not None:
                try:
                    self._loop.remove_reader(s.fileno())
                except (RuntimeError, ValueError):
                    pass
            s.close()
        self.listeners, self.conns = [], [None] * self.n

    def _accept(self, i: int) -> None:
        try:
            conn, _ = self.listeners[i].accept()
        except OSError:
            return
        old = self.conns[i]
        if old is not None:  # (a firmware started again)
            self._loop.remove_reader(old.fileno())
            old.close()
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.conns[i] = conn
        self.codecs[i] = new_codec(SIM_SYSID, SIM_COMPID)
        self._loop.add_reader(conn.fileno(), self._readable, i)

    def _readable(self, i: int) -> None:
        conn = self.conns[i]
        try:
            data = conn.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._loop.remove_reader(conn.fileno())
            conn.close()
            self.conns[i] = None
            return
        try:
            msgs = self.codecs[i].parse_buffer(data) or []
        except Exception:  # (garbage loses itself, never the link)
            self.counters["bad_frames"] += 1
            return
        for m in msgs:
            if m.get_type() != "HIL_ACTUATOR_CONTROLS":
                continue
            self.controls[i] = m.controls
            self.output_age_s.append(self.plant.time_s - (m.time_usec - 1) / 1e6)
            self.heard_at[i] = time.monotonic()
            if i not in self.members:
                self.members.add(i)
                self.counters["joined"] += 1

    async def run(self, stop: asyncio.Event) -> None:
        """Step the plant until ``stop``: a sensor period at a time, at the wall clock's pace. Behind
        it (this process was starved), it catches up at CATCH_UP times that pace at most; behind by
        a second, it gives the second up. (The firmwares' clocks are the plant's: run flat out to
        catch up, it would run PX4's clock several times faster than its companion, which commands
        at the wall clock's pace, with PX4's real-time threads busy on the burst of sensor messages;
        a second of PX4's clock without a command ends the flight.) ``behind_max_ms`` counts how
        far behind it fell."""
        wall0 = time.monotonic() - self.plant.time_s
        while not stop.is_set():
            started, t0_s = time.monotonic(), self.plant.time_s
            self._send_sensors()
            self._leave_silent()
            self._step()
            due, now = wall0 + self.plant.time_s, time.monotonic()
            if now - due > 1.0:
                wall0, due = wall0 + now - due, now
            self.counters["behind_max_ms"] = max(self.counters["behind_max_ms"], round(1e3 * (now - due)))
            wait_s = max(due, started + (self.plant.time_s - t0_s) / CATCH_UP) - now
            if wait_s > 0:
                await asyncio.sleep(wait_s)

    def _leave_silent(self) -> None:
        now = time.monotonic()
        for i in sorted(self.members):
            if now - self.heard_at[i] > FIRMWARE_SILENT_S:
                self.members.discard(i)
                self.counters["left"] += 1

    def _step(self) -> None:
        af = self.plant.airframes
        omega = np.zeros((self.n, 3))
        alpha = np.zeros((self.n, 3))
        for i in self.members:
            d = decode_actuators(self.controls[i, :6], af[i].max_rotor_speed_rad_s, af[i].servo_limit_rad)
            if d.omega_rad_s is not None:
                omega[i], alpha[i] = d.omega_rad_s, d.alpha_rad
        self.plant.command(omega, alpha)
        self.plant.advance(self.steps_per_sensor)
        self.sensor_steps += 1

    def _send_sensors(self) -> None:
        rows = self.plant.sensors()
        t_us = int(round(self.plant.time_s * 1e6)) + 1  # (PX4's clock starts above zero)
        gps = self.sensor_steps % self.gps_every == 0
        for i, conn in enumerate(self.conns):
            if conn is None:
                continue
            frames_out = self.hil_sensor(rows[i], t_us).pack(self.codecs[i])
            if gps:
                frames_out += self.hil_gps(rows[i], t_us).pack(self.codecs[i])
            try:
                conn.send(frames_out)
            except OSError:
                self.counters["send_errors"] += 1
        if self.on_sample is not None:
            self.on_sample(rows)

    def hil_sensor(self, row: np.ndarray, t_us: int):
        col, nz, rng = SENSOR_COLUMNS, self.noise, self.rng
        acc = row[col["specific_force_b"]] * _FLIP + rng.normal(0.0, nz.accel_m_s2, 3)
        gyro = row[col["rate_b_rad_s"]] * _FLIP + rng.normal(0.0, nz.gyro_rad_s, 3)
        R_ned_frd = frames.rotation_from_quaternion(row[col["quaternion"]] * _QFLIP)
        mag = R_ned_frd.T @ self.field_ned + rng.normal(0.0, nz.mag_gauss, 3)
        alt_m = self.home[2] + float(row[col["position_m"]][2])
        pressure = isa_pressure_hpa(alt_m) + rng.normal(0.0, nz.baro_hpa)
        return mavlink.MAVLink_hil_sensor_message(
            t_us, *acc, *gyro, *mag, pressure, 0.0, alt_m, 15.0 - 0.0065 * alt_m, FIELDS_IMU_MAG_BARO, 0)

    def hil_gps(self, row: np.ndarray, t_us: int):
        col, nz, rng = SENSOR_COLUMNS, self.noise, self.rng
        north, west, up = row[col["position_m"]] + rng.normal(0.0, nz.gps_position_m, 3)
        lat, lon = self.projection.to_geodetic(north, -west)
        vn, vw, vu = row[col["velocity_e_m_s"]] + rng.normal(0.0, nz.gps_velocity_m_s, 3)
        ve, vd = -vw, -vu
        cog = (math.degrees(math.atan2(ve, vn)) % 360.0) * 100.0
        accuracy_cm = max(1, round(100 * nz.gps_position_m))
        return mavlink.MAVLink_hil_gps_message(
            int(self.unix_clock() * 1e6), 3, _fit(lat * 1e7, 32), _fit(lon * 1e7, 32), _fit((self.home[2] + up) * 1000, 32),
            accuracy_cm, accuracy_cm, _fit(math.hypot(vn, ve) * 100, 16, signed=False), _fit(vn * 100, 16),
            _fit(ve * 100, 16), _fit(vd * 100, 16), round(cog) % 36000, 16, 0, 0)


def _fit(value: float, bits: int, signed: bool = True) -> int:
    """``value`` rounded into a field of ``bits`` (a vehicle the plant has flung past what the
    message can say is said at the field's limit, not dropped with the link)."""
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 2)
    return min(max(round(value), lo), hi) if math.isfinite(value) else 0
