"""The flight-controller face of an agent: its link, what the autopilot says of itself, its clock,
its telemetry turned into samples, and the commands the companion sends it.

Telemetry: a sample is ATTITUDE and LOCAL_POSITION_NED of the same ``time_boot_ms``, converted to
the paper's frames here (the only place they are read); each one waits in ``backlog`` for the
control loop, which the link wakes after every read. A repeat of the newest state (a simulator in
lockstep offering it again) is not a new sample, but is answered again (``settle``). SYSTEM_TIME
sets the clock (``clock.FcClock``); HEARTBEAT and EXTENDED_SYS_STATE the vehicle's state, which
``on_state`` hears of.

Set-up (``setup``): wait for the autopilot, read its actuator scaling (MOT_MAX_RPM, SERVO_LIM_DEG)
and whether it is a simulator in lockstep (SIM_LOCKSTEP), ask for the telemetry at the control
rate, and wait for its clock.
"""

from __future__ import annotations

import asyncio
import gc
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink

from .actuators import ActuatorControlTarget
from .clock import REBOOT_JUMP_MS, Answers, FcClock
from .links import MavLink


@dataclass(slots=True)
class Sample:
    """One telemetry sample, in the paper's frames (earth: x north, y west, z up; body FLU)."""
    t_rx: float                      # Unix time the datagram arrived (kernel receive time on UDP) [s]
    boot_ms: int                     # the flight controller's time of the sample [ms since its boot]
    eta_rad: tuple                   # roll, pitch, yaw
    rate_b_rad_s: tuple              # body rates p, q, r
    position_e_m: tuple
    velocity_e_m_s: tuple

    @property
    def y(self) -> tuple:
        """The measured output y = (eta, lambda) of the observer (73)."""
        return self.eta_rad + self.position_e_m


class Autopilot:
    """One agent's flight controller (system ``sysid``, component 1) on link ``url``."""

    def __init__(self, sysid: int, url: str, log, on_state: Callable[[], None]) -> None:
        self.sysid = sysid
        self.link = MavLink("fc", url, sysid, COMP_ONBOARD)
        self.log = log
        self.on_state = on_state
        self.heard = False
        self.armed = False
        self.mode = 0
        self.critical = False
        """The autopilot says it is in a failsafe (its heartbeat's MAV_STATE_CRITICAL)."""
        self.landed = True
        self.max_rpm: float | None = None
        self.servo_deg: float | None = None
        self.output: ActuatorControlTarget | None = None
        self.clock = FcClock()
        self.answers = Answers(self.write)
        self.last_sample: Sample | None = None
        self.backlog: deque[Sample] = deque(maxlen=50)
        """Samples not acted on yet (the control loop takes them)."""
        self._att: tuple | None = None  # the newest ATTITUDE: (boot_ms, eta, rates)
        self._woke = False
        self._pending: dict = {}

    def write(self, frame: bytes) -> None:
        self.link.write(frame)

    def send(self, msg) -> None:
        self.link.send(msg)

    @property
    def ready(self) -> bool:
        """Set up: the actuator scaling is known, commands can be made."""
        return self.output is not None

    # -- what the autopilot says ----------------------------------------------------------------

    def take(self, msg, t_rx: float) -> None:
        """A message from this agent's autopilot."""
        t = msg.get_type()
        if t == "ATTITUDE":
            self.answers.telemetry(msg.time_boot_ms)
            self._att = (msg.time_boot_ms, (msg.roll, -msg.pitch, -msg.yaw),
                         (msg.rollspeed, -msg.pitchspeed, -msg.yawspeed))  # FRD in NED -> the paper's
        elif t == "LOCAL_POSITION_NED":
            self.answers.telemetry(msg.time_boot_ms)
            att = self._att
            if att is not None and att[0] == msg.time_boot_ms:
                self._sample(Sample(t_rx, msg.time_boot_ms, att[1], att[2], (msg.x, -msg.y, -msg.z),
                                    (msg.vx, -msg.vy, -msg.vz)))
        elif t in ("ATTITUDE_QUATERNION", "ODOMETRY", "HIGHRES_IMU"):
            self.answers.telemetry(msg.time_boot_ms if hasattr(msg, "time_boot_ms") else msg.time_usec // 1000)
        elif t == "HEARTBEAT":
            self.heard = True
            self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self.mode = msg.custom_mode
            self.critical = msg.system_status == mavlink.MAV_STATE_CRITICAL
            self.on_state()
        elif t == "SYSTEM_TIME":
            if msg.time_unix_usec > 0:
                self.clock.set_offset(msg.time_unix_usec, msg.time_boot_ms)
        elif t == "EXTENDED_SYS_STATE":
            self.landed = msg.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
        elif t == "COMMAND_ACK":
            self._resolve(("ack", msg.command), msg.result)
        elif t == "PARAM_VALUE":
            self._resolve(("param", msg.param_id), msg.param_value)

    def _sample(self, s: Sample) -> None:
        last = self.last_sample
        if last is not None and 0 <= last.boot_ms - s.boot_ms < REBOOT_JUMP_MS:
            return  # the same state again (a lockstep simulator's re-send): one tick each
        if last is not None and s.t_rx - last.t_rx > 0.05:
            self.log.debug(f"telemetry gap {1e3 * (s.t_rx - last.t_rx):.0f} ms (fc time {s.boot_ms - last.boot_ms} ms)")
        self.last_sample = s
        self.answers.defer = self._woke = self.clock.advance(s.boot_ms)
        self.backlog.append(s)

    def take_woke(self) -> bool:
        """Whether the newest sample woke a wait (once)."""
        woke, self._woke = self._woke, False
        return woke

    def _resolve(self, key, value) -> None:
        fut = self._pending.pop(key, None)
        if fut is not None and not fut.done():
            fut.set_result(value)

    # -- asking it ------------------------------------------------------------------------------

    async def _request(self, key, send, timeout_s: float = 0.5, tries: int = 6):
        loop = asyncio.get_running_loop()
        for _ in range(tries):
            fut = loop.create_future()
            self._pending[key] = fut
            send()
            try:
                return await asyncio.wait_for(fut, timeout_s)
            except asyncio.TimeoutError:
                continue
        raise TimeoutError(f"flight controller did not answer {key}")

    async def command(self, command: int, *params: float) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        return await self._request(("ack", command), lambda: self.send(
            mavlink.MAVLink_command_long_message(self.sysid, 1, command, 0, *p)))

    async def param(self, name: str) -> float:
        return await self._request(("param", name), lambda: self.send(
            mavlink.MAVLink_param_request_read_message(self.sysid, 1, name.encode(), -1)))

    async def setup(self, rate_hz: float, heartbeat: Callable[[], object]) -> None:
        """Wait for the flight controller, learn its actuator scaling, ask for the telemetry."""
        while not self.heard:
            self.send(heartbeat())
            await asyncio.sleep(0.2)
        self.max_rpm = await self.param("MOT_MAX_RPM")
        self.servo_deg = await self.param("SERVO_LIM_DEG")
        try:
            self.answers.lockstep = await self.param("SIM_LOCKSTEP") == 1.0
        except TimeoutError:  # an autopilot, not triswarm's simulator
            self.answers.lockstep = False
        if self.answers.lockstep:
            self.log.info("the flight controller is a simulator in lockstep: every state is answered")
        interval = 1e6 / rate_hz
        for msg_id, us in ((mavlink.MAVLINK_MSG_ID_ATTITUDE, interval), (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, interval),
                           (mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, -1), (mavlink.MAVLINK_MSG_ID_ODOMETRY, -1),
                           (mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, -1), (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, 1e6)):
            await self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, us)
        await self.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_SYSTEM_TIME)
        while not self.clock.known:
            await asyncio.sleep(0.05)
        self.output = ActuatorControlTarget(self.link.codec, self.sysid, self.max_rpm * math.pi / 30.0,
                                            math.radians(self.servo_deg))
        # Set up and about to fly: keep the start-up objects out of every later garbage collection,
        # which would otherwise stall the loop for tens of milliseconds at a time.
        gc.collect()
        gc.freeze()

    # -- commanding it --------------------------------------------------------------------------

    def actuate(self, boot_ms: int, omega_rad_s, alpha_rad) -> None:
        """The command answering the sample of ``boot_ms``."""
        self.answers.command(boot_ms, self.output.command(boot_ms, omega_rad_s, alpha_rad))

    def settle(self, busy: bool) -> None:
        """After a sample was taken: in lockstep, answer what is due and was not commanded."""
        self.answers.settle(busy, self._no_command)

    def _no_command(self, boot_ms: int) -> bytes:
        if self.output is None:  # (not set up: the simulator waits for an answer all the same)
            return ActuatorControlTarget(self.link.codec, self.sysid, 1.0, 1.0).no_command(boot_ms)
        return self.output.no_command(boot_ms)

    def unix(self, boot_ms: int) -> float:
        """The flight controller's time of a sample, as Unix time (its SYSTEM_TIME clock)."""
        return self.clock.unix(boot_ms)

    def now_unix(self) -> float:
        return self.clock.now()

    def telemetry_age_s(self, s: Sample) -> float:
        return time.time() - self.clock.unix(s.boot_ms)
