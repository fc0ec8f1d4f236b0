"""How each simulated autopilot streams on its companion link (`triswarm sitl up --fc-profile`): which
messages at which default rates, what their stamps mean, how late and how irregularly they leave,
and how it honours MAV_CMD_SET_MESSAGE_INTERVAL. A profile is a table; ``server.py`` reads it.

The timing model, on the physics clock (1 ms steps by default):

- A stream falls due every 1/rate (``server.py``'s schedule). At a due instant k the message is
  made from the estimator's newest product: the state at the newest multiple of 1/``product_hz``
  (the topic's publication rate; None: the state at k). A stream with ``new_only`` is not sent when
  that product was already sent (PX4 sends only new uORB data).
- It leaves at k + d, d drawn from U[0, ``jitter_ms``) and rounded down to whole physics steps
  (the autopilot's MAVLink task runs on a loop of that period), never before the stream's previous
  message. The draws are a table made from the seed and the stream, indexed by the instant: a
  lockstep run is the same every time. One instant's delay is the same on every vehicle of the
  process: in lockstep the companions exchange their estimates of an instant before they answer
  it, so every vehicle's state of that instant must be out before the clock waits for answers
  (independent delays would have it wait for an answer that waits for a state not yet sent).
- Its stamp is the product's instant (``stamp="sample"``) or the instant it leaves (``"send"``).

Only the companion link follows the profile; the ground-station link keeps triswarm's own timing
(every stamp the instant of its state), which the recorder that judges a flight reads.

Sources (the research is summarised, with line numbers, in docs/flight-controllers.md):
PX4 at https://github.com/PX4/PX4-Autopilot/blob/aa998d88b89cb4553c36cbdea7e7379b5cb8b74c/ (main,
2026-03; the Onboard-mode lines are unchanged since 2018-2021, so v1.14 and later have them),
ArduPilot at https://github.com/ArduPilot/ardupilot/blob/Copter-4.5.4/.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

STAMPS = ("sample", "send")
JITTER_TABLE = 4096


@dataclass(frozen=True)
class Timing:
    """One telemetry stream's timing on the companion link."""
    product_hz: float | None = None
    """How often the estimator publishes what the message carries (None: the state at the due instant)."""
    stamp: str = "sample"
    new_only: bool = False


@dataclass(frozen=True)
class Profile:
    name: str
    rates_hz: MappingProxyType
    """Stream code (``telemetry.STREAMS``) -> default rate on the companion link [Hz]; codes not
    listed are off until asked for."""
    timing: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    """Stream code -> Timing; streams not listed leave at their due instant stamped with it."""
    jitter_ms: float = 0.0
    min_interval_us: int = 1
    """The shortest interval SET_MESSAGE_INTERVAL gets (shorter ones are raised to it)."""
    whole_ms_intervals: bool = False
    """Intervals are kept in whole milliseconds, shorter than 1 ms taken as 1 ms."""
    not_streamable: frozenset = frozenset()
    """Stream codes SET_MESSAGE_INTERVAL refuses (MAV_RESULT_DENIED): the autopilot cannot send them."""
    unknown_result: str = "UNSUPPORTED"
    """The MAV_RESULT for a message the autopilot does not know."""

    def interval_us(self, requested_us: float) -> float:
        """The interval the autopilot keeps for a positive requested interval [us]."""
        us = float(requested_us)
        if self.whole_ms_intervals:
            us = max(1, int(us // 1000)) * 1000.0
        return max(us, float(self.min_interval_us))

    def jitter_steps(self, seed: int, code: str, dt_s: float) -> np.ndarray | None:
        """The send delays [physics steps] of a stream due at step k: element k % JITTER_TABLE
        (None: no jitter)."""
        if self.jitter_ms <= 0.0 or code not in self.timing:
            return None
        rng = np.random.default_rng([seed, 0x717, sum(ord(c) << (8 * k) for k, c in enumerate(code))])
        return np.floor(rng.random(JITTER_TABLE) * (self.jitter_ms * 1e-3 / dt_s)).astype(np.int64)


TRISWARM = Profile(
    name="triswarm",
    # The SITL's own link: every telemetry message of one step together, stamped with that step.
    rates_hz=MappingProxyType({"ATT": 100.0, "ATTQ": 50.0, "LPOS": 100.0, "GPOS": 10.0, "ODOM": 50.0, "IMU": 50.0,
                               "SYS": 1.0, "BATT": 1.0, "EXT": 1.0, "HOME": 0.2, "ACT": 10.0, "TIME": 1.0}),
)

PX4 = Profile(
    name="px4",
    # MAV_1_MODE = Onboard (the TELEM2 companion default): Mavlink::configure_streams_to_default,
    # case MAVLINK_MODE_ONBOARD, src/modules/mavlink/mavlink_main.cpp L1518-1590. HEARTBEAT 1 Hz
    # separately (L2335). HOME_POSITION and ACTUATOR_OUTPUT_STATUS are not in the Onboard list.
    rates_hz=MappingProxyType({"ATT": 100.0, "ATTQ": 50.0, "LPOS": 30.0, "GPOS": 50.0, "ODOM": 30.0, "IMU": 50.0,
                               "SYS": 5.0, "BATT": 0.5, "EXT": 5.0, "TIME": 1.0}),
    timing=MappingProxyType({
        # ATTITUDE / ATTITUDE_QUATERNION: time_boot_ms = vehicle_attitude.timestamp / 1000
        # (streams/ATTITUDE.hpp L73, ATTITUDE_QUATERNION.hpp L77), published by EKF2 on every IMU
        # sample (EKF2.cpp L856) at IMU_INTEG_RATE = 200 Hz (sensors/vehicle_imu/imu_parameters.c L50).
        # Its publication lags the sample by the filter's run time, well under the 1 ms the field
        # keeps: the ms stamp is the sample's.
        "ATT": Timing(product_hz=200.0, stamp="sample", new_only=True),
        "ATTQ": Timing(product_hz=200.0, stamp="sample", new_only=True),
        # LOCAL_POSITION_NED: vehicle_local_position.timestamp / 1000 (LOCAL_POSITION_NED.hpp L67),
        # published only when the filter updates, every EKF2_PREDICT_US = 10 ms (EKF2.cpp L802-806,
        # ekf2/module.yaml L15-25): at most 100 Hz however fast it is asked for.
        "LPOS": Timing(product_hz=100.0, stamp="sample", new_only=True),
        # ODOMETRY: time_usec = vehicle_odometry.timestamp_sample, the IMU sample (ODOMETRY.hpp L66,
        # EKF2.cpp L1685), also at the filter's 100 Hz.
        "ODOM": Timing(product_hz=100.0, stamp="sample", new_only=True),
        # HIGHRES_IMU: time_usec = vehicle_imu.timestamp_sample (HIGHRES_IMU.hpp L183), 200 Hz.
        "IMU": Timing(product_hz=200.0, stamp="sample", new_only=True),
    }),
    # The MAVLink instance's thread sleeps max(1.5 ms, ...) per loop at 921600 baud (mavlink_main.cpp
    # L2351-2360, MAVLINK_MIN_INTERVAL 1500 in mavlink_main.h L529): a message waits up to 1.5 ms.
    jitter_ms=1.5,
    # SET_MESSAGE_INTERVAL has no maximum rate of its own (mavlink_receiver.cpp L2254-2300), but
    # nothing leaves faster than the 1.5 ms loop.
    min_interval_us=1500,
)

ARDUPILOT = Profile(
    name="ardupilot",
    # Copter 4.5.4: every SRn_ stream-group default is 0 (ArduCopter/GCS_Mavlink.cpp L401-491): the
    # companion port sends HEARTBEAT (1 Hz) and nothing else until asked.
    rates_hz=MappingProxyType({}),
    timing=MappingProxyType({
        # ATTITUDE, ATTITUDE_QUATERNION, LOCAL_POSITION_NED: time_boot_ms = AP_HAL::millis() when
        # sent (GCS_Common.cpp send_attitude L5483-5497, send_attitude_quaternion L5500-5520,
        # send_local_position L2765-2785), the AHRS's newest output (it runs in the 400 Hz loop).
        "ATT": Timing(product_hz=None, stamp="send"),
        "ATTQ": Timing(product_hz=None, stamp="send"),
        "LPOS": Timing(product_hz=None, stamp="send"),
    }),
    # GCS::update_send runs in the 400 Hz scheduler (SCHED_LOOP_RATE; ArduCopter/Copter.cpp L210):
    # a due message waits up to one 2.5 ms loop.
    jitter_ms=2.5,
    # Intervals are whole milliseconds (uint16_t interval_ms), < 1000 us taken as 1 ms
    # (GCS_Common.cpp L2911-2950), and no faster than 80 % of the 400 Hz loop: 3 ms (L1608-1612).
    min_interval_us=3000,
    whole_ms_intervals=True,
    # No ap_message for HIGHRES_IMU or ODOMETRY: SET_MESSAGE_INTERVAL answers DENIED ("No
    # ap_message for mavlink id", GCS_Common.cpp L2916-2922; table L948-1110).
    not_streamable=frozenset({"IMU", "ODOM"}),
    unknown_result="DENIED",
)

PROFILES = {p.name: p for p in (TRISWARM, PX4, ARDUPILOT)}


def profile(name: str) -> Profile:
    try:
        return PROFILES[name]
    except KeyError:
        raise ValueError(f"--fc-profile must be one of {', '.join(PROFILES)}, got {name!r}") from None


def product_step(step: int, product_hz: float | None, dt_s: float) -> int:
    """The physics step of the estimator's newest product at ``step``."""
    if product_hz is None:
        return step
    period = 1.0 / (product_hz * dt_s)  # in steps (may be fractional: 400 Hz on a 1 kHz clock)
    return int(math.floor(math.floor(step / period + 1e-9) * period + 1e-9))
