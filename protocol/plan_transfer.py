"""A plan as MAVLink mission items (the commands of ``dialect/triswarm.xml``), and back.

Pure functions, no I/O. The payload is the canonical JSON of the plan's dict (what the TOML file
holds), zlib-compressed, cut into 21-byte items: seven fields of three bytes, each an integer in
[0, 2^24) and so exact in a float32. The header item carries the version, the payload length, the
number of drones and the plan id, which the receiver checks against the payload it rebuilt.
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass

from .codec import plan_id
from .errors import ProtocolError

VERSION = 1
CMD_PLAN_HEADER = 31900
CMD_PLAN_DATA = 31901
FIELDS = 7
BYTES_PER_FIELD = 3
BYTES_PER_ITEM = FIELDS * BYTES_PER_FIELD
MAX_PAYLOAD_BYTES = 64 * 1024
MAX_ITEMS = 1 + -(-MAX_PAYLOAD_BYTES // BYTES_PER_ITEM)

# MAV_MISSION_RESULT codes (common.xml), so this module needs no MAVLink import
MISSION_UNSUPPORTED = 3
MISSION_NO_SPACE = 4
MISSION_INVALID = 5


class PlanTransferError(ProtocolError):
    """Items that do not make a plan, with the MISSION_ACK code to answer."""

    def __init__(self, reason: str, ack_code: int = MISSION_INVALID) -> None:
        super().__init__(reason)
        self.ack_code = ack_code


@dataclass(frozen=True)
class PlanItem:
    command: int
    fields: tuple[int, ...]
    """param1..4, x, y, z: integers in [0, 2^24)."""


def canonical_payload(spec: dict) -> bytes:
    try:
        text = json.dumps(spec, sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise PlanTransferError(f"the plan holds a value that cannot be sent ({exc})") from None
    return zlib.compress(text.encode(), 9)


def encode_plan(spec: dict) -> list[PlanItem]:
    """The mission items of a plan dict: the header, then the payload."""
    payload = canonical_payload(spec)
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise PlanTransferError(f"the plan is {len(payload)} bytes compressed, more than {MAX_PAYLOAD_BYTES}",
                                MISSION_NO_SPACE)
    pid = plan_id(spec)
    drones = spec.get("drones", 0)
    header = PlanItem(CMD_PLAN_HEADER, (VERSION, len(payload), int(drones) if isinstance(drones, int) else 0, 0,
                                        pid >> 16, pid & 0xFFFF, 0))
    padded = payload + bytes(-len(payload) % BYTES_PER_ITEM)
    items = [header]
    for k in range(0, len(padded), BYTES_PER_ITEM):
        chunk = padded[k:k + BYTES_PER_ITEM]
        items.append(PlanItem(CMD_PLAN_DATA, tuple(int.from_bytes(chunk[f:f + BYTES_PER_FIELD], "big")
                                                   for f in range(0, BYTES_PER_ITEM, BYTES_PER_FIELD))))
    return items


def field_value(value: float, where: str) -> int:
    """A received field (float or int) back to its integer, or PlanTransferError."""
    if not 0 <= value < 1 << 24 or value != int(value):  # (NaN and the infinities fail the range)
        raise PlanTransferError(f"{where}: {value!r} is not an integer in [0, 2^24)")
    return int(value)


def decode_plan(items: list[PlanItem]) -> tuple[dict, int]:
    """The plan dict and its id; PlanTransferError if the items are not one whole plan."""
    if not items or items[0].command != CMD_PLAN_HEADER:
        raise PlanTransferError("item 0 is not a triswarm plan header (MAV_CMD 31900)", MISSION_UNSUPPORTED)
    version, length, _drones, _, id_hi, id_lo, _ = items[0].fields
    if version != VERSION:
        raise PlanTransferError(f"plan format version {version} is not supported (this companion reads {VERSION})",
                                MISSION_UNSUPPORTED)
    expected = 1 + -(-length // BYTES_PER_ITEM)
    if len(items) != expected:
        raise PlanTransferError(f"the header announces {length} bytes in {expected - 1} items, "
                                f"{len(items) - 1} came")
    data = bytearray()
    for seq, item in enumerate(items[1:], start=1):
        if item.command != CMD_PLAN_DATA:
            raise PlanTransferError(f"item {seq} is command {item.command}, not plan data (31901)", MISSION_UNSUPPORTED)
        for value in item.fields:
            data += value.to_bytes(BYTES_PER_FIELD, "big")
    try:
        spec = json.loads(zlib.decompress(bytes(data[:length])))
    except (zlib.error, ValueError) as exc:
        raise PlanTransferError(f"the plan payload does not decode ({exc.__class__.__name__})") from None
    if not isinstance(spec, dict):
        raise PlanTransferError("the plan payload is not a table")
    pid = plan_id(spec)
    if pid != (id_hi << 16 | id_lo):
        raise PlanTransferError(f"the plan id {id_hi << 16 | id_lo:08x} does not match the content ({pid:08x})")
    return spec, pid
