"""The MAVLink conventions shared by the SITL flight controllers and the companions.

The dialect is chosen here, once: everything in triswarm that speaks MAVLink imports ``mavlink``
from this module, never through pymavlink's environment variables. It is triswarm's dialect
(``protocol/dialect/triswarm.xml``: common.xml plus the plan and leader commands), shipped generated
(``protocol/dialect/triswarm_v20.py``, pymavlink's own generator's output); its messages are
common.xml's, byte for byte.

Custom modes (HEARTBEAT.custom_mode, with MAV_MODE_FLAG_CUSTOM_MODE_ENABLED in base_mode):

    EXTERNAL = 1  rotors and servos follow SET_ACTUATOR_CONTROL_TARGET (a companion flies the drone)
    HOLD     = 2  the flight controller's own controller holds position, level
    LAND     = 3  it descends at LAND_SPEED_M_S and disarms once on the ground
    TAKEOFF  = 4  it climbs to the takeoff altitude, then HOLD

Actuator mapping of SET_ACTUATOR_CONTROL_TARGET (group_mlx 0), normalised as MAVLink asks:

    controls[0..2]  rotor i speed / MOT_MAX_RPM         in [0, 1]
    controls[3..5]  servo i angle / SERVO_LIM_DEG       in [-1, 1]
    controls[6..7]  unused (0)

Values outside those ranges are clamped and counted; a message with a non-finite value in
controls[0..5] is dropped and counted.

MAVLink 2 signing (https://mavlink.io/en/guide/message_signing.html) of a link: ``signing_key``
and ``setup_signing``, on pymavlink's own signing state (``MAVLink.signing``). Like all of
``protocol/``, this module does no I/O: the key file is read, and the clock that timestamps signed
frames is given, by the caller (the companion or the ground station).
"""

from __future__ import annotations

import enum
import math
import hashlib
import hmac
import struct
from collections import Counter
from collections.abc import Callable, MutableMapping
from dataclasses import dataclass

import numpy as np
from . import frames
from .dialect import triswarm_v20 as mavlink  # the dialect, chosen once

ACTUATOR_GROUP = 0
COMP_AUTOPILOT = mavlink.MAV_COMP_ID_AUTOPILOT1
COMP_ONBOARD = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER


class CustomMode(enum.IntEnum):
    EXTERNAL = 1
    HOLD = 2
    LAND = 3
    TAKEOFF = 4


def mode_name(mode: int) -> str:
    """A HEARTBEAT custom_mode by name (EXTERNAL, HOLD, ...), or "mode N" for one we do not know."""
    try:
        return CustomMode(mode).name
    except ValueError:
        return f"mode {mode}"


def new_codec(sysid: int, compid: int) -> "mavlink.MAVLink":
    """A MAVLink 2 encoder/parser for one link: robust parsing (bad frames become BAD_DATA)."""
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.robust_parsing = True
    return mav


def reset_parser(mav: "mavlink.MAVLink") -> None:
    """Forget any partial frame (a UDP datagram carries whole frames; leftovers are garbage)."""
    mav.buf = bytearray()
    mav.buf_index = 0
    mav.expected_length = mavlink.HEADER_LEN_V1 + 2
    mav.have_prefix_error = False


SIGNING_KEY_BYTES = 32
SIGNING_EPOCH_UNIX_S = 1420070400  # 1 January 2015 GMT
NEW_STREAM_LAG = 6_000_000  # a new stream may start at most a minute behind our own timestamp [10 us]
SIGNATURE_REFUSED = "Invalid signature"  # pymavlink's reason (BAD_DATA) for a frame its signing refused


UNIX_TIME_LATEST_S = 4102444800  # 1 January 2100 GMT


def plausible_unix_us(time_unix_usec: int) -> bool:
    """A Unix time [us] a flight controller may take as its clock (SYSTEM_TIME): from 2015 (no GPS
    time comes earlier) to 2100, so every stamp made from it fits its field for the life of the
    process (``time_unix_usec = 2**64 - 1`` would overflow the next SYSTEM_TIME sent)."""
    return SIGNING_EPOCH_UNIX_S * 1_000_000 <= time_unix_usec < UNIX_TIME_LATEST_S * 1_000_000


def signing_key(data: bytes, source: str) -> bytes:
    """The key in a signing key file's content ``data``: the 32 bytes of secret, either as they are
    (a 32-byte binary file) or as 64 hexadecimal digits (a text file; surrounding white space is
    ignored). ValueError (one sentence, naming ``source``, the file) for anything else, and for the
    all-zero key, which means "no signing" in MAVLink. (Reading the file is the caller's:
    ``companion.state.read_signing_key``.)"""
    key = data if len(data) == SIGNING_KEY_BYTES else _hex_key(data.strip())
    if key is None:
        raise ValueError(f"{source}: not a signing key: expected {SIGNING_KEY_BYTES} bytes, or "
                         f"{2 * SIGNING_KEY_BYTES} hexadecimal digits (the file has {len(data)} bytes)")
    if not any(key):
        raise ValueError(f"{source}: the all-zero signing key means no signing; make a random one")
    return key


def _hex_key(text: bytes) -> bytes | None:
    if len(text) != 2 * SIGNING_KEY_BYTES:
        return None
    try:
        return bytes.fromhex(text.decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        return None


def signing_timestamp(unix_s: float) -> int:
    """A signing timestamp: 10 us units since 1 January 2015 GMT."""
    return max(0, int((unix_s - SIGNING_EPOCH_UNIX_S) * 1e5))


class Signing(mavlink.MAVLinkSigning):
    """pymavlink's signing state, with two changes to how it treats timestamps:

    * ours never fall behind the Unix clock (pymavlink starts from the clock, then only adds one
      per frame, so a quiet link's lag behind the clock grows until its peers refuse it as an old
      stream after a restart);
    * a stream's last timestamp moves only once a frame's signature is good (pymavlink moves it
      first, so one forged frame with a timestamp far ahead would shut the real sender out).

    Frames refused are counted in ``counters`` by reason: ``refused_unsigned``, ``refused_bad_signature``
    (signed with another key, or altered), ``refused_replay`` (a good signature, but a timestamp not
    newer than the last of its stream (link id, system, component), or for a new stream, more than a
    minute behind our own).

    ``clock``: the Unix time in seconds (``time.time`` in a companion or a ground station), which
    our timestamps never fall behind.
    """

    def __init__(self, allow_unsigned: Callable[[int], bool] | None, counters: MutableMapping[str, int], *,
                 clock: Callable[[], float]) -> None:
        super().__init__()
        self.clock = clock
        self.allow_unsigned = allow_unsigned
        self.counters = counters
        self._failed: str | None = None  # why the frame being decoded failed its check

    @property
    def timestamp(self) -> int:
        return max(self._timestamp, signing_timestamp(self.clock()))

    @timestamp.setter
    def timestamp(self, value: int) -> None:
        self._timestamp = value

    def check(self, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        """MAVLink.check_signature: the signature, then the timestamp."""
        expected = hashlib.sha256(self.secret_key + bytes(msgbuf[:-6])).digest()[:6]
        if not hmac.compare_digest(expected, bytes(msgbuf[-6:])):
            self._failed = "bad_signature"
            return False
        low, high = struct.unpack_from("<IH", msgbuf, len(msgbuf) - 12)
        stamp = low | high << 32
        stream = (msgbuf[-13], src_system, src_component)
        last = self.stream_timestamps.get(stream)
        stale = stamp + NEW_STREAM_LAG < self.timestamp if last is None else stamp <= last
        if stale:
            self._failed = "replay"
            return False
        self.stream_timestamps[stream] = stamp
        self.timestamp = max(self.timestamp, stamp)  # as the specification asks
        return True

    def streams(self) -> dict[str, int]:
        """Each stream's last timestamp, keyed "link,system,component" (to keep across a restart)."""
        return {f"{link},{sysid},{compid}": stamp for (link, sysid, compid), stamp in self.stream_timestamps.items()}

    def restore(self, saved: dict) -> int:
        """Take back streams kept by ``streams`` (the newer timestamp wins); entries that are not
        three small integers and a timestamp are skipped. Returns how many were taken."""
        taken = 0
        for key, stamp in saved.items():
            try:
                stream = tuple(int(x) for x in key.split(","))
                if len(stream) != 3 or not all(0 <= x <= 255 for x in stream) or not 0 <= int(stamp) < 2**48:
                    continue
            except (AttributeError, TypeError, ValueError):
                continue
            self.stream_timestamps[stream] = max(int(stamp), self.stream_timestamps.get(stream, 0))
            taken += 1
        return taken

    def accept(self, mav, msg_id: int) -> bool:
        """MAVLink.signing.allow_unsigned_callback: called for every frame that did not pass
        ``check`` (or carried no signature). Only unsigned frames may pass, if ``allow_unsigned``
        says so; a wrong signature or a replay never does."""
        reason, self._failed = self._failed or "unsigned", None
        if reason == "unsigned" and self.allow_unsigned is not None and self.allow_unsigned(msg_id):
            return True
        self.counters[f"refused_{reason}"] += 1
        return False


def setup_signing(codec: "mavlink.MAVLink", key: bytes, link_id: int, allow_unsigned: Callable[[int], bool] | None = None,
                  counters: MutableMapping[str, int] | None = None, *, clock: Callable[[], float]) -> None:
    """Sign every frame ``codec`` packs (as link ``link_id``) and check every frame it parses:
    frames refused become BAD_DATA with reason SIGNATURE_REFUSED, counted by reason (see Signing)
    in ``counters`` (a new Counter by default). ``allow_unsigned(msg_id)``: which unsigned frames
    may pass (default: none). ``clock``: the Unix time in seconds, for the timestamps (the
    caller's ``time.time``: this module reads no clock)."""
    signing = Signing(allow_unsigned, Counter() if counters is None else counters, clock=clock)
    signing.secret_key, signing.link_id, signing.sign_outgoing = key, link_id, True
    signing.allow_unsigned_callback = signing.accept
    codec.signing = signing
    codec.check_signature = signing.check


@dataclass
class ActuatorDecode:
    omega_rad_s: np.ndarray | None
    alpha_rad: np.ndarray | None
    clamped: int = 0
    dropped_non_finite: bool = False


def encode_actuators(omega_rad_s, alpha_rad, max_rotor_speed_rad_s: float, servo_limit_rad: float) -> list[float]:
    """Rotor speeds [rad/s] and servo angles [rad] (3 each) to controls[8]."""
    w = [min(max(float(x) / max_rotor_speed_rad_s, 0.0), 1.0) for x in omega_rad_s]
    a = [min(max(float(x) / servo_limit_rad, -1.0), 1.0) for x in alpha_rad]
    return w + a + [0.0, 0.0]


def decode_actuators(controls, max_rotor_speed_rad_s: float, servo_limit_rad: float) -> ActuatorDecode:
    """controls[8] to rotor speeds and servo angles; clamps and counts out-of-range values, drops
    the whole command if any of the six values is not finite."""
    c = [float(x) for x in list(controls)[:6]]  # (plain floats: numpy's overhead would dominate six values)
    if len(c) != 6 or not all(math.isfinite(x) for x in c):
        return ActuatorDecode(None, None, 0, True)
    w = [min(max(x, 0.0), 1.0) for x in c[0:3]]
    a = [min(max(x, -1.0), 1.0) for x in c[3:6]]
    clamped = sum(x != y for x, y in zip(w + a, c))
    return ActuatorDecode(np.array(w) * max_rotor_speed_rad_s, np.array(a) * servo_limit_rad, clamped, False)


def attitude_to_paper(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """ATTITUDE (FRD in NED) to the paper's Euler angles."""
    return frames.euler_flip([roll, pitch, yaw])


def rates_to_paper(rollspeed: float, pitchspeed: float, yawspeed: float) -> np.ndarray:
    return frames.flip([rollspeed, pitchspeed, yawspeed])


def local_ned_to_paper(x: float, y: float, z: float) -> np.ndarray:
    return frames.flip([x, y, z])

