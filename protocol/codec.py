"""What agents say to each other over Zenoh: key expressions and the compact estimate codec.

An estimate is one agent's xi_i = xhat_i - h_i at plan time t_p (the time the prediction refers
to), 124 bytes, little endian:

    offset size  field
    0      1     version (1)
    1      1     status (AgentStatus)
    2      2     agent number (from 1)
    4      4     plan id (see plan_id)
    8      4     sequence number (per agent, increasing from 1 each time the companion starts)
    12     8     wall-clock time the estimate was published [s since the Unix epoch]
    20     8     plan time the estimate refers to [s]
    28     96    xi, 12 float64 in x_r order [lambda_dot, eta_dot, eta, lambda]

Decoding refuses anything else with a reason (never an exception other than CodecError).
"""

from __future__ import annotations

import enum
import hashlib
import json
import math
import struct
from dataclasses import dataclass

import numpy as np

from .errors import ProtocolError

ESTIMATE_VERSION = 1
_HEADER = struct.Struct("<BBHIIdd")
_FORMAT = struct.Struct(_HEADER.format + "12d")
ESTIMATE_SIZE = _FORMAT.size


class CodecError(ProtocolError):
    """A payload that is not a valid estimate (the reason names which check failed)."""


class AgentStatus(enum.IntEnum):
    FLYING = 0      # in formation: its estimate counts for its neighbours
    HOLDING = 1     # no path to the leader (or told to hold): neighbours ignore it
    IDLE = 2        # on the ground, no plan running


@dataclass(frozen=True)
class Estimate:
    agent: int
    plan_id: int
    seq: int
    stamp_s: float
    t_plan_s: float
    status: AgentStatus
    xi: np.ndarray


_MAX_STATUS = max(AgentStatus)


def encode_estimate(e: Estimate) -> bytes:
    return _FORMAT.pack(ESTIMATE_VERSION, int(e.status), e.agent, e.plan_id, e.seq, e.stamp_s, e.t_plan_s,
                        *np.asarray(e.xi, dtype=float).tolist())


def decode_header(data: bytes) -> tuple[AgentStatus, int, int, int, float, float]:
    """Everything but xi: (status, agent, plan id, seq, stamp, plan time). Cheap enough for every
    sample; xi is unpacked only for the estimates actually used (``decode_xi``)."""
    if len(data) != ESTIMATE_SIZE:
        raise CodecError(f"size {len(data)} bytes, expected {ESTIMATE_SIZE}")
    version, status, agent, plan, seq, stamp, t_plan = _HEADER.unpack_from(data)
    if version != ESTIMATE_VERSION:
        raise CodecError(f"version {version}, expected {ESTIMATE_VERSION}")
    if status > _MAX_STATUS:
        raise CodecError(f"unknown status {status}")
    if agent < 1:
        raise CodecError("agent number 0")
    if not (math.isfinite(stamp) and math.isfinite(t_plan)):
        raise CodecError("non-finite number")
    return AgentStatus(status), agent, plan, seq, stamp, t_plan


def decode_xi(data: bytes) -> np.ndarray:
    xi = np.frombuffer(data, dtype="<f8", count=12, offset=_HEADER.size)
    if not np.isfinite(xi).all():
        raise CodecError("non-finite number")
    return xi


def decode_estimate(data: bytes) -> Estimate:
    status, agent, plan, seq, stamp, t_plan = decode_header(data)
    return Estimate(agent, plan, seq, stamp, t_plan, status, decode_xi(data))


def estimate_key(swarm: str, agent: int) -> str:
    return f"triswarm/{swarm}/agent/{agent}/estimate"


def alive_key(swarm: str, agent: int | str = "*") -> str:
    return f"triswarm/{swarm}/agent/{agent}/alive"


def status_key(swarm: str, agent: int | str = "*") -> str:
    return f"triswarm/{swarm}/agent/{agent}/status"


def health_key(swarm: str, agent: int | str = "*") -> str:
    return f"triswarm/{swarm}/agent/{agent}/health"


def agent_of_key(key: str) -> int | None:
    """The agent number in ``triswarm/<swarm>/agent/<i>/...``, or None."""
    parts = str(key).split("/")
    if (len(parts) >= 4 and parts[0] == "triswarm" and parts[2] == "agent" and parts[3].isascii()
            and parts[3].isdigit() and len(parts[3]) <= 9):  # (not "²", nor a number of 5000 digits)
        return int(parts[3])
    return None


def plan_id(spec: dict) -> int:
    """A 32-bit id of a plan's content: equal plans have equal ids on every agent."""
    canonical = json.dumps(spec, sort_keys=True, separators=(",", ":"), default=str)
    return int.from_bytes(hashlib.sha256(canonical.encode()).digest()[:4], "little")
