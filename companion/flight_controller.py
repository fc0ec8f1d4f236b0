"""The flight-controller face of an agent: its link, what the flight controller says of itself, its
clock, its telemetry turned into samples, and the commands the companion sends it. What differs
from one kind of flight controller to another (its modes, its actuator scaling and output path,
its set-up, its position frame) is its ``Autopilot`` (``autopilots/``), picked at set-up.

Telemetry: attitude, position and gyro rates come on streams of their own (``telemetry.py`` turns
them into a sample at each new attitude instant, the position brought to it). Of the messages
that carry the same quantity, one is used: ATTITUDE before ATTITUDE_QUATERNION before ODOMETRY for
the attitude, LOCAL_POSITION_NED before ODOMETRY for the position; a less preferred one takes
over when the preferred one has not come for FALLBACK_US. Every message is converted to the
paper's frames here, the only place they are read. SYSTEM_TIME sets the clock
(``clock.FcClock``); HEARTBEAT and EXTENDED_SYS_STATE the vehicle's state, which ``on_state``
hears of. Samples wait in ``backlog`` for the control loop, which the link wakes after every read.

Set-up (``setup``): wait for the flight controller's HEARTBEAT (saying every few seconds what it
waits for), pick its ``Autopilot`` from it (or as configured), learn from that its actuator
scaling, whether it is a simulator (in lockstep or not) and its own set-up, ask for the telemetry
at the control rate, and wait for its clock.
"""

from __future__ import annotations

import asyncio
import gc
import math
import time
from collections import deque
from collections.abc import Callable

from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink, plausible_unix_us

from .actuators import ActuatorControlTarget
from .autopilots.base import Autopilot, AutopilotError
from .autopilots.registry import pick
from .clock import Answers, FcClock
from .links import MavLink
from .px4_link import Px4ZenohLink, is_px4_zenoh
from .telemetry import Assembler, Sample, accel_of, attitude_of, gyro_of, position_of
from .timesync import EVERY_S as TIMESYNC_EVERY_S
from .timesync import TimeSync

FALLBACK_US = 500_000
"""A less preferred message carries a quantity once the preferred one has not come for this long."""
ATTITUDE_SOURCES = ("ATTITUDE", "ATTITUDE_QUATERNION", "ODOMETRY")
POSITION_SOURCES = ("LOCAL_POSITION_NED", "ODOMETRY")
MEASURE_US = 500_000
"""Set-up measures the telemetry's rates over this much of the flight controller's clock."""
WAITING_SAY_EVERY_S = 5.0
"""While set-up waits for the flight controller, it says what for this often [s, wall]."""


class FlightController:
    """One agent's flight controller (system ``sysid``, component 1) on link ``url``, of the kind
    ``profile`` names (``autopilots.registry.PROFILES``; "auto": as its HEARTBEAT says). ``home``:
    the swarm's common origin (latitude, longitude [deg], altitude [m]), for autopilots whose local
    frame is their own. ``after_read`` and ``on_link_event``: its link's (``links.MavLink``)."""

    def __init__(self, sysid: int, url: str, log, on_state: Callable[[], None], profile: str = "auto",
                 home: tuple[float, float, float] | None = None, after_read: Callable[[], None] | None = None,
                 on_link_event: Callable[[str], None] = lambda text: None) -> None:
        self.sysid = sysid
        self.profile, self.home = profile, home
        self.autopilot: Autopilot | None = None
        """What kind of flight controller it is (set up: ``setup``)."""
        self.identity = (-1, -1)
        """Its HEARTBEAT's autopilot and type fields."""
        self._told_identity: tuple[int, int] | None = None
        link = Px4ZenohLink if is_px4_zenoh(url) else MavLink
        self.link = link("fc", url, sysid, COMP_ONBOARD, after_read=after_read, on_event=on_link_event)
        """MAVLink, or PX4's Zenoh bridge carrying the same (``px4_link``)."""
        self.log = log
        self.on_state = on_state
        self.heard = False
        self.heard_s: float | None = None
        """When it was last heard [s, time.monotonic] (kept by ``forget``: the agent's watchdog of a
        lost flight controller)."""
        self.armed = False
        self.mode = 0
        self.critical = False
        """The autopilot says it is in a failsafe (its heartbeat's MAV_STATE_CRITICAL)."""
        self.landed = True
        self.max_rpm: float | None = None
        self.servo_deg: float | None = None
        self.output: ActuatorControlTarget | None = None
        self.accelerometer_asked = False
        """Whether its accelerometer stream was asked for (``ask_accelerometer``)."""
        self.clock = FcClock()
        self.answers = Answers(self.write)
        self.timesync = TimeSync(self.send, sysid)
        self.last_sample: Sample | None = None
        self.backlog: deque[Sample] = deque(maxlen=50)
        """Samples not acted on yet (the control loop takes them)."""
        self.assembler = Assembler()
        self.heard_at_us: dict[str, int] = {}
        """Each telemetry message's newest stamp [boot us]."""
        self._woke = False
        self._pending: dict = {}

    def forget(self) -> None:
        """The flight controller may be another one (it rebooted, its clock broke, a simulator was
        started again): nothing of the one before is kept (its clock, its streams, its state, its
        answers); ``setup`` learns it anew."""
        self.heard = False
        self.autopilot = None
        self.output = self.last_sample = None
        self.accelerometer_asked = False
        self.clock.forget()
        self.answers = Answers(self.write)
        self.backlog.clear()
        self.assembler = Assembler()
        self.heard_at_us.clear()
        self._woke = False

    def write(self, frame: bytes) -> None:
        self.link.write(frame)

    def send(self, msg) -> None:
        self.link.send(msg)

    @property
    def simulator(self) -> bool:
        """A simulator, whose clock is its host's: no wall-clock checks against it."""
        return self.autopilot is not None and self.autopilot.simulator

    @property
    def offset_e_m(self) -> tuple[float, float, float]:
        return (0.0, 0.0, 0.0) if self.autopilot is None else self.autopilot.position_offset_e_m

    @property
    def in_control(self) -> bool:
        """In the mode that hands the vehicle to the companion."""
        return self.autopilot is not None and self.mode == self.autopilot.control_mode

    def released(self) -> str | None:
        """Why the flight controller has taken the vehicle back, or None (in flight, armed)."""
        return None if self.autopilot is None else self.autopilot.released(self.mode, self.critical)

    def mode_name(self) -> str:
        return f"mode {self.mode}" if self.autopilot is None else self.autopilot.mode_name(self.mode)

    async def take_control(self) -> None:
        """Into the mode that hands the vehicle to the companion (RuntimeError: refused)."""
        command, params = self.autopilot.take_control()
        result = await self.command(command, *params)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            raise RuntimeError(f"the flight controller refused external control ({result})")
        self.mode = self.autopilot.control_mode

    async def launch(self, height_m: float, say: Callable[[str], None]) -> None:
        """Off the ground by its own controllers, if its kind needs that before it hands over."""
        await self.autopilot.launch(self, height_m, say)

    @property
    def ready(self) -> bool:
        """Set up: the actuator scaling is known, commands can be made."""
        return self.output is not None

    # -- what the autopilot says ----------------------------------------------------------------

    def take(self, msg, t_rx: float) -> None:
        """A message from this agent's autopilot."""
        self.heard_s = time.monotonic()
        t = msg.get_type()
        if t in _TELEMETRY:
            self._telemetry(t, msg, t_rx)
        elif t == "HEARTBEAT":
            self.heard = True
            self.identity = (msg.autopilot, msg.type)
            self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self.mode = msg.custom_mode
            self.critical = msg.system_status == mavlink.MAV_STATE_CRITICAL
            self.on_state()
        elif t == "SYSTEM_TIME":
            if plausible_unix_us(msg.time_unix_usec):  # (0: it has no time yet)
                self.clock.set_offset(msg.time_unix_usec, msg.time_boot_ms)
            elif msg.time_unix_usec:
                self.assembler.counters["clock_implausible"] += 1
        elif t == "TIMESYNC":
            self.timesync.take(msg)
        elif t == "EXTENDED_SYS_STATE":
            self.landed = msg.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
        elif t == "COMMAND_ACK":
            self._resolve(("ack", msg.command), msg.result)
        elif t == "PARAM_VALUE":
            self._resolve(("param", msg.param_id), msg.param_value)
        elif self.autopilot is not None:
            self.autopilot.take(msg)

    def _telemetry(self, t: str, msg, t_rx: float) -> None:
        t_us = msg.time_boot_ms * 1000 if hasattr(msg, "time_boot_ms") else int(msg.time_usec)
        self.heard_at_us[t] = t_us
        asm = self.assembler
        if t in ATTITUDE_SOURCES and self._preferred(t, ATTITUDE_SOURCES, t_us):
            self.answers.telemetry(t_us)  # (the attitude is what a tick, and so an answer, is of)
            asm.take_attitude(t_us, *attitude_of(msg), t_rx)
        if t in POSITION_SOURCES and self._preferred(t, POSITION_SOURCES, t_us):
            state = position_of(msg)
            if state is None:
                asm.counters["odometry_frames_not_used"] += 1
            else:
                (x, y, z), velocity = state
                dx, dy, dz = self.offset_e_m
                asm.take_position(t_us, (x + dx, y + dy, z + dz), velocity, t_rx)
        if t == "HIGHRES_IMU":
            asm.take_gyro(t_us, gyro_of(msg), t_rx)
        if t in ("HIGHRES_IMU", "SCALED_IMU"):
            asm.take_accel(t_us, accel_of(msg), t_rx)
        s = asm.sample(t_rx)
        if s is not None:
            self._sample(s)

    def _preferred(self, t: str, sources: tuple[str, ...], t_us: int) -> bool:
        """Whether message ``t`` carries its quantity now: no more preferred one came lately."""
        for better in sources[:sources.index(t)]:
            heard = self.heard_at_us.get(better)
            if heard is not None and 0 <= t_us - heard < FALLBACK_US:
                return False
        return True

    def _sample(self, s: Sample) -> None:
        last = self.last_sample
        if last is not None and s.t_rx - last.t_rx > 0.05:
            self.log.debug(f"telemetry gap {1e3 * (s.t_rx - last.t_rx):.0f} ms (fc time {(s.boot_us - last.boot_us) / 1e3:.0f} ms)")
        self.last_sample = s
        self.answers.defer = self._woke = self.clock.advance(s.boot_us)
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

    async def ask_accelerometer(self, rate_hz: float) -> None:
        """Ask for the accelerometer at ``rate_hz`` (once; set up first), for a plan whose
        controllers take it (``Autopilot.accelerometer_streams``)."""
        if self.accelerometer_asked or self.autopilot is None:
            return
        self.accelerometer_asked = True
        for msg_id, us in self.autopilot.accelerometer_streams(rate_hz):
            await self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, us)

    async def setup(self, rate_hz: float, heartbeat: Callable[[], object], scaling: tuple[float, float],
                    say: Callable[[str], None]) -> float:
        """Wait for the flight controller, pick its ``Autopilot``, learn its actuator scaling (else
        ``scaling``: the plan airframe's [RPM, deg]) and the rest of its set-up, ask for the
        telemetry at ``rate_hz`` and see what comes. Says what it waits for, every
        WAITING_SAY_EVERY_S. Returns the rate [Hz] the attitude comes at (``rate_hz`` if within 5 %
        of it). AutopilotError: it cannot be flown as it is."""
        await self.wait("a HEARTBEAT", lambda: self.heard, lambda: self.send(heartbeat()), say)
        await self.wait("a HEARTBEAT of an autopilot the companion knows", lambda: self._pick(say),
                        lambda: self.send(heartbeat()), say)
        ap = self.autopilot
        self.max_rpm, self.servo_deg = await ap.scaling(self, scaling, say)
        await ap.detect_simulator(self)
        self.answers.lockstep = ap.lockstep
        if ap.lockstep:
            self.log.info("the flight controller is a simulator in lockstep: every state is answered")
        await ap.prepare(self, say)
        for msg_id, us in ap.streams(rate_hz):
            await self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, us)
        request_time = lambda: self.send(mavlink.MAVLink_command_long_message(  # noqa: E731
            self.sysid, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, 0, 0, 0, 0, 0, 0))
        await self.wait("SYSTEM_TIME", lambda: self.clock.known, request_time, say)
        if self.answers.lockstep:
            # (a simulator in lockstep sends what it is asked, and its clock stands while this set-up
            # holds its answers: the rates are told once they have been seen, nothing waits for them)
            attitude_hz = rate_hz
            asyncio.ensure_future(self._measure_rates(rate_hz, None))
        else:
            attitude_hz = await self._measure_rates(rate_hz, say)
        await ap.ready(self, say)
        self.output = ap.output(self.link.codec, self.sysid, self.max_rpm * math.pi / 30.0, math.radians(self.servo_deg))
        self.answers.holding = False
        # Set up and about to fly: keep the start-up objects out of every later garbage collection,
        # which would otherwise stall the loop for tens of milliseconds at a time.
        gc.collect()
        gc.freeze()
        return attitude_hz

    def _pick(self, say: Callable[[str], None]) -> bool:
        """The ``Autopilot`` of the identity heard last (``registry.pick``); an unknown one is said
        (once per identity) and waited past: one HEARTBEAT of nonsense on the link does not end the
        set-up, and an autopilot the companion does not know is told every few seconds."""
        try:
            self.autopilot = pick(self.profile, *self.identity, home=self.home)
            return True
        except AutopilotError as exc:
            if self._told_identity != self.identity:
                self._told_identity = self.identity
                say(str(exc))
            return False

    async def wait(self, what: str, done: Callable[[], bool], poke: Callable[[], None] | None,
                    say: Callable[[str], None] | None) -> None:
        """Until ``done()``, poking every 0.2 s and saying every WAITING_SAY_EVERY_S what for (not
        with ``say`` None). AutopilotError: the link cannot carry this flight controller."""
        since = told = time.monotonic()
        while not done():
            if getattr(self.link, "fatal", None):
                raise AutopilotError(self.link.fatal)
            if poke is not None:
                poke()
            await asyncio.sleep(0.2)
            now = time.monotonic()
            if say is not None and now - told >= WAITING_SAY_EVERY_S and not done():
                told = now
                say(f"waiting {now - since:.0f} s for {what} from the flight controller (system {self.sysid}) "
                    f"on {self.link.url}")

    async def _measure_rates(self, rate_hz: float, say: Callable[[str], None] | None) -> float:
        """The attitude's and the position's rates over half a second of the flight controller's
        clock, as they come now that they were asked for; said in one line."""
        asm = self.assembler
        for stream in (asm.attitude, asm.position):
            stream.count, stream.first_us = 0, -1
        await self.wait("attitude (ATTITUDE, ATTITUDE_QUATERNION or ODOMETRY)", lambda: asm.attitude.count >= 2, None, say)
        await self.wait("position (LOCAL_POSITION_NED or ODOMETRY)", lambda: asm.position.count >= 2, None, say)
        await self.wait("half a second of telemetry", lambda: asm.attitude.t_us - asm.attitude.first_us >= MEASURE_US
                         and asm.position.t_us - asm.position.first_us >= MEASURE_US, None, say)
        att_hz, pos_hz = asm.attitude.rate_hz(), asm.position.rate_hz()
        if self.answers.lockstep:
            self.log.info(f"telemetry: attitude {att_hz:.0f} Hz, position {pos_hz:.0f} Hz (in lockstep: as asked)")
            return rate_hz
        sources = [t for t in ATTITUDE_SOURCES if t in self.heard_at_us][:1] + \
                  [t for t in POSITION_SOURCES if t in self.heard_at_us][:1]
        line = f"telemetry: attitude {att_hz:.0f} Hz ({sources[0]}), position {pos_hz:.0f} Hz ({sources[-1]})"
        if pos_hz < 0.95 * att_hz:
            line += f", brought up to {1e3 / pos_hz:.0f} ms forward to the attitude's instants"
        if abs(att_hz - rate_hz) > 0.05 * rate_hz:
            line += f"; asked {rate_hz:g} Hz: the controller runs at {att_hz:.0f} Hz"
            say(line)
            return float(round(att_hz))
        self.log.info(line)
        return rate_hz

    async def keep_time(self) -> None:
        """TIMESYNC requests every TIMESYNC_EVERY_S once set up (not with a simulator in lockstep,
        whose clock is no clock the wall's can be held against)."""
        while True:
            if self.ready and not self.answers.lockstep:
                self.timesync.request()
            await asyncio.sleep(TIMESYNC_EVERY_S)

    # -- commanding it --------------------------------------------------------------------------

    def actuate(self, s: Sample, omega_rad_s, alpha_rad) -> None:
        """The command answering sample ``s`` (and whatever telemetry came with it)."""
        t_us = self.answers.answer_time(s.boot_us)
        self.answers.command(t_us, self.output.command(t_us, omega_rad_s, alpha_rad))

    def settle(self, busy: bool) -> None:
        """After a sample was taken: in lockstep, answer what is due and was not commanded."""
        self.answers.settle(busy, self._no_command)

    def _no_command(self, boot_us: int) -> bytes:
        if self.output is None:  # (not set up: the simulator waits for an answer all the same)
            return ActuatorControlTarget(self.link.codec, self.sysid, 1.0, 1.0).no_command(boot_us)
        return self.output.no_command(boot_us)

    def unix(self, boot_us: int) -> float:
        """The flight controller's time of a sample, as Unix time (its SYSTEM_TIME clock)."""
        return self.clock.unix(boot_us)

    def now_unix(self) -> float:
        return self.clock.now()


_TELEMETRY = frozenset({"ATTITUDE", "ATTITUDE_QUATERNION", "LOCAL_POSITION_NED", "ODOMETRY", "HIGHRES_IMU",
                        "SCALED_IMU"})
