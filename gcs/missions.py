"""The ground station's side of the mission protocol, for triswarm plans on component 191:
upload, download and clear, with timeouts and retries (see companion/plan_server.py)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink
from triswarm.protocol.plan_transfer import PlanItem, field_value

from .errors import GcsError
from .link import GroundLink

MISSION = mavlink.MAV_MISSION_TYPE_MISSION


@dataclass
class Outcome:
    drone: int
    ok: bool
    detail: str
    code: int | None = None
    """MAV_MISSION_RESULT of the answer (None: no answer)."""


def result_name(code: int | None) -> str:
    if code is None:
        return "no answer"
    entry = mavlink.enums["MAV_MISSION_RESULT"].get(code)
    return entry.name.removeprefix("MAV_MISSION_") if entry else str(code)


def upload(link: GroundLink, drone: int, items: list[PlanItem], progress: Callable[[int], None] = lambda k: None,
           timeout_s: float = 1.0, retries: int = 5) -> Outcome:
    """MISSION_COUNT, then every item the companion asks for, until its MISSION_ACK. A request
    that does not come in time makes us send again what it answers (the count or the item)."""
    texts: list[str] = []
    with link.subscribe(drone, COMP_ONBOARD, "MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK", "STATUSTEXT") as sub:
        last = mavlink.MAVLink_mission_count_message(drone, COMP_ONBOARD, len(items), MISSION)
        link.send(drone, last)
        tries, deadline = 0, time.monotonic() + timeout_s
        while True:
            msg = sub.get(deadline - time.monotonic())
            if msg is None:
                if tries >= retries:
                    return Outcome(drone, False, "; ".join(texts + [f"no answer after {retries} retries"]))
                tries += 1
                link.send(drone, last)
                deadline = time.monotonic() + timeout_s
                continue
            t = msg.get_type()
            if t == "STATUSTEXT":
                texts.append(msg.text)
            elif t == "MISSION_ACK":
                if msg.mission_type != MISSION:
                    continue
                time.sleep(0.02)
                while (more := sub.get(0.0)) is not None:
                    if more.get_type() == "STATUSTEXT":
                        texts.append(more.text)
                ok = msg.type == mavlink.MAV_MISSION_ACCEPTED
                return Outcome(drone, ok, "; ".join(texts) or result_name(msg.type), msg.type)
            elif 0 <= msg.seq < len(items):
                item = items[msg.seq]
                p = item.fields
                if t == "MISSION_REQUEST_INT":
                    last = mavlink.MAVLink_mission_item_int_message(
                        drone, COMP_ONBOARD, msg.seq, mavlink.MAV_FRAME_MISSION, item.command, 0, 0,
                        *map(float, p[:4]), p[4], p[5], float(p[6]), MISSION)
                else:
                    last = mavlink.MAVLink_mission_item_message(
                        drone, COMP_ONBOARD, msg.seq, mavlink.MAV_FRAME_MISSION, item.command, 0, 0, *map(float, p), MISSION)
                link.send(drone, last)
                progress(msg.seq + 1)
                tries, deadline = 0, time.monotonic() + timeout_s


def download(link: GroundLink, drone: int, timeout_s: float = 1.0, retries: int = 5) -> list[PlanItem]:
    """The items the companion holds (MISSION_REQUEST_LIST, then MISSION_REQUEST_INT each)."""
    with link.subscribe(drone, COMP_ONBOARD, "MISSION_COUNT", "MISSION_ITEM_INT") as sub:
        count = _ask(link, drone, sub, "MISSION_COUNT", lambda: mavlink.MAVLink_mission_request_list_message(
            drone, COMP_ONBOARD, MISSION), lambda m: True, timeout_s, retries).count
        items = []
        for seq in range(count):
            m = _ask(link, drone, sub, "MISSION_ITEM_INT", lambda: mavlink.MAVLink_mission_request_int_message(
                drone, COMP_ONBOARD, seq, MISSION), lambda m: m.seq == seq, timeout_s, retries)
            fields = (m.param1, m.param2, m.param3, m.param4, m.x, m.y, m.z)
            items.append(PlanItem(m.command, tuple(field_value(v, f"drone {drone} item {seq}") for v in fields)))
        link.send(drone, mavlink.MAVLink_mission_ack_message(drone, COMP_ONBOARD, mavlink.MAV_MISSION_ACCEPTED, MISSION))
    return items


def clear(link: GroundLink, drone: int, timeout_s: float = 1.0, retries: int = 5) -> Outcome:
    with link.subscribe(drone, COMP_ONBOARD, "MISSION_ACK", "STATUSTEXT") as sub:
        texts: list[str] = []
        for _ in range(retries + 1):
            link.send(drone, mavlink.MAVLink_mission_clear_all_message(drone, COMP_ONBOARD, MISSION))
            deadline = time.monotonic() + timeout_s
            while (msg := sub.get(deadline - time.monotonic())) is not None:
                if msg.get_type() == "STATUSTEXT":
                    texts.append(msg.text)
                else:
                    ok = msg.type == mavlink.MAV_MISSION_ACCEPTED
                    return Outcome(drone, ok, "; ".join(texts) or result_name(msg.type), msg.type)
    return Outcome(drone, False, f"no answer after {retries} retries")


class NoAnswer(GcsError, TimeoutError):
    """A drone that did not answer a mission request, however often asked (one sentence)."""


def _ask(link, drone, sub, type_, make, accept, timeout_s, retries):
    for _ in range(retries + 1):
        link.send(drone, make())
        deadline = time.monotonic() + timeout_s
        while (msg := sub.get(deadline - time.monotonic())) is not None:
            if msg.get_type() == type_ and accept(msg):
                return msg
    raise NoAnswer(f"drone {drone}: no {type_} after {retries} retries")
