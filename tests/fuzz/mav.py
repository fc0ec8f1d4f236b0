"""MAVLink inputs for the fuzzers, and what a companion's datagram link must make of them.

``Mutator`` makes datagrams from valid template frames (what a face hears in flight), of these
kinds, drawn at random:

- ``garbage``: random bytes, 0 to 300 of them (0: an empty datagram);
- ``garbage_framed``: a MAVLink 2 magic byte and a plausible length, then random bytes;
- ``valid``: a template as it is (must be taken);
- ``bitflip``: 1 to 4 bits flipped anywhere in a valid frame (header, payload, checksum);
- ``truncated``: a valid frame cut short;
- ``bad_crc``: a valid frame with its checksum altered;
- ``wrong_crc_extra``: a frame checksummed with another message's CRC extra;
- ``wrong_length``: the length byte changed, the checksum recomputed;
- ``mutated_payload``: random payload bytes, a valid checksum (a valid frame of nonsense);
- ``extreme_fields``: 1 to 3 fields at their extremes (NaN, +-inf, the largest float, the
  integer limits, huge counts and sequence numbers, strings of non-UTF-8 bytes with no NUL);
- ``wrong_target``: another target system or component;
- ``unknown_id``: a well-formed frame of a message id the dialect does not know;
- ``mavlink1``: a valid frame in MAVLink 1;
- ``several``: two to five of the above in one datagram;
- ``hostile_values`` (with a ``target``): a valid message of any id of the dialect with hostile
  values in its fields, or a command or parameter set with them (``values.HostileValues``);

and, for a face with a signing key: ``signed`` (a good signature), ``signed_wrong_key``,
``signed_bad_signature`` (a signed frame with its signature altered), ``signed_replay`` (a frame
already taken, again) and ``signed_stale`` (a new stream an hour behind the clock). Every kind but
the signed ones makes unsigned frames.

``LinkModel`` restates, independently of ``companion/links.py``, what the companion's datagram
link counts for each datagram: the oracle the fuzzers compare the companion's counters with.
"""

from __future__ import annotations

import math
import random
import struct
import time
from collections import Counter, deque

from pymavlink.generator.mavcrc import x25crc

from triswarm.protocol.mavlink import SIGNATURE_REFUSED, mavlink as M, new_codec, reset_parser, setup_signing

FLOAT_EXTREMES = (math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 1e-45, -0.0)
DOUBLE_EXTREMES = (math.nan, math.inf, -math.inf, 1.7e308, -1.7e308, 5e-324, -0.0)
INT_LIMITS = {"uint8_t": (0, 255), "int8_t": (-128, 127), "uint16_t": (0, 65535), "int16_t": (-32768, 32767),
              "uint32_t": (0, 2**32 - 1), "int32_t": (-2**31, 2**31 - 1), "uint64_t": (0, 2**64 - 1),
              "int64_t": (-2**63, 2**63 - 1)}
KNOWN_IDS = frozenset(M.mavlink_map)
V2, V1 = 0xFD, 0xFE
SIGNED_KINDS = ("signed", "signed_wrong_key", "signed_bad_signature", "signed_replay", "signed_stale")
BASE_KINDS = ("garbage", "garbage_framed", "valid", "bitflip", "truncated", "bad_crc", "wrong_crc_extra", "wrong_length",
              "mutated_payload", "extreme_fields", "wrong_target", "unknown_id", "mavlink1", "several")


def recrc(frame: bytes | bytearray, crc_extra: int) -> bytes:
    """The frame with its checksum recomputed with ``crc_extra`` (MAVLink 1 or 2, signed or not)."""
    frame = bytearray(frame)
    if frame[0] == V1:
        header, signature = 6, 0
    else:
        header, signature = 10, 13 if frame[2] & M.MAVLINK_IFLAG_SIGNED else 0
    end = header + frame[1]
    if len(frame) < end + 2:
        return bytes(frame)
    crc = x25crc(bytes(frame[1:end]))
    crc.accumulate(bytes([crc_extra & 0xFF]))
    frame[end:end + 2] = struct.pack("<H", crc.crc)
    return bytes(frame[:end + 2 + signature])


def extreme_value(rng: random.Random, ftype: str, length: int):
    """An extreme value of a field of type ``ftype`` (an array of them if ``length``)."""
    if ftype == "char":
        n = rng.randint(0, length)
        return bytes(rng.choice((0xFF, 0xC3, 0x80, 0x00, rng.randrange(256))) for _ in range(n))
    if length:
        return [extreme_value(rng, ftype, 0) for _ in range(length)]
    if ftype == "float":
        return rng.choice(FLOAT_EXTREMES) if rng.random() < 0.8 else rng.uniform(-1e6, 1e6)
    if ftype == "double":
        return rng.choice(DOUBLE_EXTREMES) if rng.random() < 0.8 else rng.uniform(-1e12, 1e12)
    lo, hi = INT_LIMITS[ftype]
    return rng.choice((lo, hi, hi, 0, 1, rng.randint(lo, hi)))


def with_fields(msg, **values):
    """A copy of ``msg`` with some fields replaced."""
    cls = type(msg)
    args = [values[name] if name in values else getattr(msg, f"_{name}_raw", getattr(msg, name)) for name in cls.fieldnames]
    return cls(*args)


def extreme(rng: random.Random, msg):
    """``msg`` with one to three of its fields at their extremes."""
    cls = type(msg)
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths))
    types = dict(zip(cls.fieldnames, cls.fieldtypes))
    names = rng.sample(cls.fieldnames, min(len(cls.fieldnames), rng.randint(1, 3)))
    return with_fields(msg, **{n: extreme_value(rng, types[n], lengths[n]) for n in names})


class Mutator:
    """Datagrams for one face: ``templates`` are valid messages of what it hears, packed by
    ``codec`` (their source system and component). With ``key``, the signed kinds are made too
    (signed as link ``link_id``: a stream of its own for the companion)."""

    def __init__(self, rng: random.Random, templates: list, codec, *, key: bytes | None = None, link_id: int = 7,
                 weights: dict[str, float] | None = None, target: tuple[int, int] | None = None,
                 param_names: tuple[str, ...] = ()) -> None:
        from .values import HostileValues

        self.rng, self.templates, self.codec = rng, templates, codec
        self.kinds = (list(BASE_KINDS) + (list(SIGNED_KINDS) if key is not None else [])
                      + (["hostile_values"] if target is not None else []))
        self.hostile = None if target is None else HostileValues(rng, codec, target, param_names)
        self.weights = [(weights or {}).get(k, 1.0) for k in self.kinds]
        self.signed_sent: deque[bytes] = deque(maxlen=64)
        if key is not None:
            src = (codec.srcSystem, codec.srcComponent)
            self.signer = new_codec(*src)
            setup_signing(self.signer, key, link_id, clock=time.time)
            self.wrong = new_codec(*src)
            setup_signing(self.wrong, bytes(reversed(key)), link_id, clock=time.time)
            self.key = key

    def __call__(self) -> tuple[str, bytes]:
        kind = self.rng.choices(self.kinds, self.weights)[0]
        return kind, self.make(kind)

    def template(self):
        """A template: a message, or a callable that makes one now (a stamp on the peer's clock)."""
        chosen = self.rng.choice(self.templates)
        return chosen() if callable(chosen) else chosen

    def frame(self, msg=None, codec=None) -> bytes:
        return (msg or self.template()).pack(codec or self.codec)

    def make(self, kind: str) -> bytes:
        rng = self.rng
        if kind == "garbage":
            return rng.randbytes(rng.randint(0, 300))
        if kind == "garbage_framed":
            n = rng.randint(0, 255)
            return bytes([V2, n]) + rng.randbytes(rng.randint(0, n + 30))
        if kind == "valid":
            return self.frame()
        if kind == "bitflip":
            f = bytearray(self.frame())
            for _ in range(rng.randint(1, 4)):
                f[rng.randrange(len(f))] ^= 1 << rng.randrange(8)
            return bytes(f)
        if kind == "truncated":
            f = self.frame()
            return f[:rng.randint(1, len(f) - 1)]
        if kind == "bad_crc":
            f = bytearray(self.frame())
            f[-1 - rng.randrange(2)] ^= rng.randint(1, 255)
            return bytes(f)
        if kind == "wrong_crc_extra":
            msg = self.template()
            return recrc(self.frame(msg), (msg.crc_extra + rng.randint(1, 255)) & 0xFF)
        if kind == "wrong_length":
            msg = self.template()
            f = bytearray(self.frame(msg))
            f[1] = (f[1] + rng.choice((-3, -1, 1, 2, 40, 200))) % 256
            return recrc(f, msg.crc_extra)
        if kind == "mutated_payload":
            msg = self.template()
            f = bytearray(self.frame(msg))
            for _ in range(rng.randint(1, 6)):
                if f[1]:
                    f[10 + rng.randrange(f[1])] = rng.randrange(256)
            return recrc(f, msg.crc_extra)
        if kind == "extreme_fields":
            return self.frame(extreme(rng, self.template()))
        if kind == "wrong_target":
            msg = self.template()
            if not hasattr(msg, "target_system"):
                return self.frame(msg)
            return self.frame(with_fields(msg, target_system=rng.choice((0, 2, 42, 255, rng.randrange(256))),
                                          target_component=rng.choice((0, 1, 190, 191, 255, rng.randrange(256)))))
        if kind == "unknown_id":
            msg_id = rng.randrange(1 << 24)
            while msg_id in KNOWN_IDS:
                msg_id = rng.randrange(1 << 24)
            payload = rng.randbytes(rng.randint(0, 255))
            header = struct.pack("<BBBBBBBHB", V2, len(payload), 0, 0, rng.randrange(256), self.codec.srcSystem,
                                 self.codec.srcComponent, msg_id & 0xFFFF, msg_id >> 16)
            return recrc(header + payload + b"\0\0", rng.randrange(256))
        if kind == "mavlink1":
            msg = self.template()
            if msg.id > 255:  # (MAVLink 1 has one byte for the id)
                return self.frame(msg)
            if rng.random() < 0.5:
                msg = extreme(rng, msg)
            return msg.pack(self.codec, force_mavlink1=True)
        if kind == "hostile_values":
            return self.hostile()[1]
        if kind == "several":
            return b"".join(self.make(rng.choice(BASE_KINDS[:-1])) for _ in range(rng.randint(2, 5)))
        if kind == "signed":
            f = self.frame(codec=self.signer)
            self.signed_sent.append(f)
            return f
        if kind == "signed_wrong_key":
            return self.frame(codec=self.wrong)
        if kind == "signed_bad_signature":
            f = bytearray(self.frame(codec=self.signer))
            f[-1 - rng.randrange(6)] ^= rng.randint(1, 255)
            return bytes(f)
        if kind == "signed_replay":
            if not self.signed_sent:
                return self.make("signed")
            return rng.choice(self.signed_sent)
        if kind == "signed_stale":
            stale = new_codec(self.codec.srcSystem, self.codec.srcComponent)
            hour_ago = time.time() - 3600.0
            setup_signing(stale, self.key, rng.randint(100, 255), clock=lambda: hour_ago)
            return self.frame(codec=stale)
        raise ValueError(kind)


class LinkModel:
    """What ``companion/links.py`` counts for each datagram on a datagram link of system ``sysid``,
    component ``compid`` (with ``key``: signed, taking unsigned only the messages ``allow_unsigned``
    names), restated for the fuzzers:

    - ``rx``: every message taken (messages of ids the dialect does not know included);
    - ``drop_bad_data``: every piece the parser makes BAD_DATA of, but signature refusals (a
      datagram of garbage may make several);
    - ``refused_unsigned``, ``refused_bad_signature``, ``refused_replay``: frames the signing refused;
    - ``drop_partial_frame``: a datagram that ends in the middle of a frame (a truncated one);
    - ``drop_empty``: an empty datagram;
    - ``drop_unparseable``: a datagram the parser raised on.
    """

    def __init__(self, sysid: int, compid: int, key: bytes | None = None, allow_unsigned=None) -> None:
        self.codec = new_codec(sysid, compid)
        self.counters: Counter[str] = Counter()
        if key is not None:
            setup_signing(self.codec, key, 1, allow_unsigned, self.counters, clock=time.time)

    def feed(self, data: bytes) -> list:
        """Count one datagram; the messages taken."""
        if not data:
            self.counters["drop_empty"] += 1
            return []
        reset_parser(self.codec)
        good = []
        try:
            msgs = self.codec.parse_buffer(data) or []
        except Exception:  # (the link's parser gave up on the datagram)
            self.counters["drop_unparseable"] += 1
            return []
        for m in msgs:
            if m.get_type() != "BAD_DATA":
                good.append(m)
            elif m.reason != SIGNATURE_REFUSED:
                self.counters["drop_bad_data"] += 1
        if self.codec.buf_len() > 0:
            self.counters["drop_partial_frame"] += 1
        self.counters["rx"] += len(good)
        return good


def drops(counters: dict) -> int:
    """Everything a link's counters say it dropped or refused."""
    return sum(n for k, n in counters.items() if k.startswith(("drop_", "refused_")))
