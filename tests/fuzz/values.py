"""Valid MAVLink messages carrying hostile values: what a peer may legally send and a receiver must
still represent and act on for the life of its process (``time_unix_usec = 2**64 - 1``, an interval
of NaN, a message id of 65536, a string with no NUL).

``HostileValues`` makes them, seeded: every message of the dialect in turn, so that a short run sends
each one, with one field at one of its boundaries (the field and the boundary move on each time the
dialect comes round) and every other field at a boundary or neutral at random:

- integers: 0, 1, -1 where signed, the type's minimum and maximum;
- floats: 0, -0, NaN, +-inf, the largest and smallest finite, a denormal;
- strings: empty, full with no NUL, full of bytes that are not UTF-8;
- arrays: every element at one such value.

So that the handlers behind the message ids are reached too, commands the receivers act on are
sent with every parameter at a boundary ("command"), and their parameters set to values no
parameter takes ("param_set", NaN, infinities, the largest floats).

Most are addressed to the face's target (system and component) so that they reach its handlers;
the rest to no one, or to another system. And sequences: the previous input again (a command
repeated), and bursts of the mission protocol with counts and sequence numbers out of order and two
transfers interleaved.
"""

from __future__ import annotations

import math
import random

from triswarm.protocol.mavlink import mavlink as M

from .mav import INT_LIMITS

FLOATS = (math.nan, math.inf, -math.inf, 3.4028235e38, -3.4028235e38, 1e-45, 1.1754944e-38, 0.0, -0.0)
DOUBLES = (math.nan, math.inf, -math.inf, 1.7976931348623157e308, -1.7976931348623157e308, 5e-324, 0.0, -0.0)
COMMANDS = (M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAV_CMD_GET_MESSAGE_INTERVAL, M.MAV_CMD_REQUEST_MESSAGE,
            M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, M.MAV_CMD_DO_SET_MODE, M.MAV_CMD_COMPONENT_ARM_DISARM,
            M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_NAV_LAND, M.MAV_CMD_TRISWARM_PLAN_START, M.MAV_CMD_TRISWARM_LEADER_GOTO,
            M.MAV_CMD_TRISWARM_LEADER_HOLD)
"""Commands a vehicle or its companion acts on: sent with hostile parameters ("command")."""
COMPANION_PARAMS = ("NB_WAIT_MS", "NB_TIMEOUT_S", "GCS_TLM_HZ", "REJOIN_S", "REJOIN_ACCEL", "CTRL_RATE_HZ", "PLAN_T_S")
"""Some of the companion's parameters ("param_set"; an unknown name is refused the same way)."""
HOSTILE_SETTINGS = (math.nan, math.inf, -math.inf, 3.4028235e38, -3.4028235e38)
"""Values a parameter set must refuse, whatever the parameter ("param_set")."""
MISSION = ("MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_REQUEST_INT", "MISSION_ACK", "MISSION_REQUEST_LIST",
           "MISSION_CLEAR_ALL", "MISSION_SET_CURRENT")
KINDS = ("one_boundary", "command", "param_set", "repeat", "mission_burst")


def boundaries(ftype: str, length: int) -> list:
    """A field's boundary values, the most hostile first (arrays: every element at one of them)."""
    if ftype == "char":
        return [b"\xff" * length, b"", b"A" * length, bytes(0x80 + k % 0x40 for k in range(length))]
    if ftype == "float":
        scalars = list(FLOATS)
    elif ftype == "double":
        scalars = list(DOUBLES)
    else:
        lo, hi = INT_LIMITS[ftype]
        scalars = [hi, lo] + ([-1] if lo < 0 else [hi - 1]) + [0, 1]
    return [[v] * length for v in scalars] if length else scalars


def neutral(ftype: str, length: int):
    if ftype == "char":
        return b""
    value = 0.0 if ftype in ("float", "double") else 0
    return [value] * length if length else value


class HostileValues:
    """Frames for one face: packed by ``codec``, addressed mostly to ``target`` (system, component)."""

    def __init__(self, rng: random.Random, codec, target: tuple[int, int], param_names: tuple[str, ...] = (),
                 weights: dict[str, float] | None = None) -> None:
        self.rng, self.codec, self.target, self.param_names = rng, codec, target, param_names
        self.classes = [M.mavlink_map[k] for k in sorted(M.mavlink_map)]
        self.calls = 0
        self.previous: bytes | None = None
        self.kinds = list(KINDS)
        self.weights = [(weights or {"one_boundary": 0.7, "command": 0.12, "param_set": 0.08, "repeat": 0.05,
                                    "mission_burst": 0.05}).get(k, 0.0)
                        for k in self.kinds]

    def __call__(self) -> tuple[str, bytes]:
        kind = self.rng.choices(self.kinds, self.weights)[0] if self.calls else "one_boundary"
        if kind == "repeat" and self.previous is not None:
            return kind, self.previous * self.rng.randint(1, 3)
        if kind == "command":
            cls = M.MAVLink_command_long_message if self.rng.random() < 0.5 else M.MAVLink_command_int_message
            msg = self.message(cls)
            msg.command = self.rng.choice(COMMANDS)
            return kind, msg.pack(self.codec)
        if kind == "param_set" and self.param_names:
            msg = M.MAVLink_param_set_message(*self.target, self.rng.choice(self.param_names).encode(),
                                              self.rng.choice(HOSTILE_SETTINGS), M.MAV_PARAM_TYPE_REAL32)
            return kind, msg.pack(self.codec)
        if kind == "mission_burst":
            data = b"".join(self.message(self._by_name(self.rng.choice(MISSION)), around=True).pack(self.codec)
                            for _ in range(self.rng.randint(2, 6)))
            return kind, data
        cls = self.classes[self.calls % len(self.classes)]
        turn = self.calls // len(self.classes)
        self.calls += 1
        self.previous = self.message(cls, turn=turn).pack(self.codec)
        return "one_boundary", self.previous

    @staticmethod
    def _by_name(name: str):
        return getattr(M, f"MAVLink_{name.lower()}_message")

    def message(self, cls, turn: int | None = None, around: bool = False):
        """An instance of ``cls``: at ``turn``, field ``turn`` (mod the fields) at its boundary
        ``turn // fields`` (mod the boundaries); ``around``: counts and sequence numbers small and
        out of order (a mission transfer), not at their limits."""
        rng = self.rng
        lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths))
        types = dict(zip(cls.fieldnames, cls.fieldtypes))
        values = {}
        for name in cls.fieldnames:
            ftype, length = types[name], lengths[name]
            if around and name in ("count", "seq", "start_index", "end_index"):
                values[name] = rng.choice((0, 1, 2, 3, 5, 17, 65535))
            elif rng.random() < 0.5:
                values[name] = neutral(ftype, length)
            else:
                values[name] = rng.choice(boundaries(ftype, length))
        if "target_system" in values:
            r = rng.random()
            values["target_system"] = self.target[0] if r < 0.8 else (0 if r < 0.9 else rng.randrange(256))
        if "target_component" in values:
            r = rng.random()
            values["target_component"] = self.target[1] if r < 0.8 else (0 if r < 0.9 else rng.randrange(256))
        if turn is not None and cls.fieldnames:
            name = cls.fieldnames[turn % len(cls.fieldnames)]
            choices = boundaries(types[name], lengths[name])
            values[name] = choices[(turn // len(cls.fieldnames)) % len(choices)]
        return cls(*[values[n] for n in cls.fieldnames])
