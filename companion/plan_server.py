"""The MAVLink mission protocol of component 191: plans go up, come down and are cleared as missions
of triswarm's plan items (``protocol/plan_transfer.py``).

Upload (one partner at a time; a new MISSION_COUNT restarts it):
    GCS MISSION_COUNT -> MISSION_REQUEST_INT(0) -> MISSION_ITEM_INT(0) -> ... -> MISSION_ACK
An item that does not come within ``timeout_s`` is asked for again, ``retries`` times; then the
upload is cancelled (MISSION_ACK OPERATION_CANCELLED). Only a whole, valid plan reaches
``on_plan``; anything less leaves the companion's plans as they were.

Download: MISSION_REQUEST_LIST -> MISSION_COUNT, then MISSION_REQUEST_INT / MISSION_REQUEST(seq)
answered with MISSION_ITEM_INT / MISSION_ITEM (the fields are exact either way).
Clear: MISSION_CLEAR_ALL -> MISSION_ACK with what ``on_clear`` answers.
"""

from __future__ import annotations

import asyncio

import logging
from collections import Counter
from dataclasses import dataclass
from typing import Callable

from triswarm.protocol.mavlink import mavlink
from triswarm.protocol.plan_transfer import MAX_ITEMS, PlanItem, PlanTransferError, field_value

log = logging.getLogger("triswarm.companion")

MISSION = mavlink.MAV_MISSION_TYPE_MISSION


@dataclass
class _Upload:
    link: object
    partner: tuple[int, int]
    total: int
    items: list
    deadline_s: float = 0.0
    tries: int = 0
    checking: bool = False
    """Every item is in and the plan is being checked (off the loop): its answer waits for that."""

    @property
    def next_seq(self) -> int:
        return len(self.items)


class PlanServer:
    """``on_plan(items)`` answers (MISSION_ACK code, reason) for a whole upload, or a future of it
    (a check that takes longer than the loop can wait)."""

    def __init__(self, on_plan: Callable[[list[PlanItem]], tuple[int, str] | asyncio.Future],
                 on_clear: Callable[[], tuple[int, str]],
                 held_items: Callable[[], list[PlanItem]], say: Callable[[str, int], None], timeout_s: float = 1.0, retries: int = 5) -> None:
        self.on_plan, self.on_clear, self.held_items, self.say = on_plan, on_clear, held_items, say
        self.timeout_s, self.retries = timeout_s, retries
        self.upload: _Upload | None = None
        self.counters: Counter = Counter()

    # -- dispatch -------------------------------------------------------------------------------

    def handle(self, link, msg, now_s: float) -> bool:
        """Act on a message addressed to this component; False if it is not a mission message."""
        t = msg.get_type()
        handler = {"MISSION_COUNT": self._count, "MISSION_ITEM_INT": self._item, "MISSION_ITEM": self._item,
                   "MISSION_REQUEST_LIST": self._list, "MISSION_REQUEST_INT": self._request,
                   "MISSION_REQUEST": self._request, "MISSION_CLEAR_ALL": self._clear,
                   "MISSION_ACK": self._ack}.get(t)
        if handler is None:
            return False
        if getattr(msg, "mission_type", MISSION) != MISSION:
            self._send_ack(link, msg, mavlink.MAV_MISSION_UNSUPPORTED, getattr(msg, "mission_type", MISSION))
            return True
        handler(link, msg, now_s)
        return True

    def poll(self, now_s: float) -> None:
        """Ask again for an item that is late; give up after ``retries``."""
        up = self.upload
        if up is None or up.checking or now_s < up.deadline_s:
            return
        if up.tries >= self.retries:
            self.upload = None
            self.counters["upload_timeouts"] += 1
            self.say(f"plan upload timed out at item {up.next_seq}/{up.total}; "
                     f"plans unchanged", mavlink.MAV_SEVERITY_WARNING)
            up.link.send(mavlink.MAVLink_mission_ack_message(*up.partner, mavlink.MAV_MISSION_OPERATION_CANCELLED,
                                                             MISSION))
            return
        up.tries += 1
        self.counters["item_rerequests"] += 1
        self._request_next(up, now_s)

    # -- upload ---------------------------------------------------------------------------------

    def _count(self, link, msg, now_s: float) -> None:
        partner = (msg.get_srcSystem(), msg.get_srcComponent())
        if msg.count == 0:
            self._clear(link, msg, now_s)
            return
        if msg.count > MAX_ITEMS:
            self._send_ack(link, msg, mavlink.MAV_MISSION_NO_SPACE)
            self.say(f"plan upload refused: {msg.count} items, at most {MAX_ITEMS}", mavlink.MAV_SEVERITY_WARNING)
            return
        if self.upload is not None:
            self.counters["uploads_restarted"] += 1
        self.upload = _Upload(link, partner, msg.count, [])
        self.counters["uploads_started"] += 1
        self._request_next(self.upload, now_s)

    def _request_next(self, up: _Upload, now_s: float) -> None:
        up.deadline_s = now_s + self.timeout_s
        up.link.send(mavlink.MAVLink_mission_request_int_message(*up.partner, up.next_seq, MISSION))

    def _item(self, link, msg, now_s: float) -> None:
        up = self.upload
        if up is None or (msg.get_srcSystem(), msg.get_srcComponent()) != up.partner:
            self.counters["items_unexpected"] += 1
            return
        if up.checking:  # (the station sent its last item again: the answer comes with the check's end)
            self.counters["items_while_checking"] += 1
            return
        if msg.seq != up.next_seq:  # a duplicate or one out of order: ask for the one we need
            self.counters["items_out_of_order"] += 1
            self._request_next(up, now_s)
            return
        try:
            fields = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z)
            item = PlanItem(int(msg.command), tuple(field_value(v, f"item {msg.seq} field {k + 1}")
                                                    for k, v in enumerate(fields)))
        except PlanTransferError as exc:
            self._end_upload(up, exc.ack_code, f"plan refused: {exc}")
            return
        up.items.append(item)
        up.tries = 0
        if up.next_seq < up.total:
            self._request_next(up, now_s)
            return
        result = self.on_plan(up.items)
        if isinstance(result, tuple):
            self._end_upload(up, *result)
            return
        up.checking = True
        result.add_done_callback(lambda done: self._checked(up, done))

    def _checked(self, up: _Upload, done: asyncio.Future) -> None:
        if self.upload is not up:  # another upload began meanwhile: this one's answer is moot
            self.counters["checks_superseded"] += 1
            return
        self._end_upload(up, *done.result())

    def _end_upload(self, up: _Upload, code: int, reason: str) -> None:
        self.upload = None
        self.counters["uploads_accepted" if code == mavlink.MAV_MISSION_ACCEPTED else "uploads_refused"] += 1
        if reason:
            self.say(reason, mavlink.MAV_SEVERITY_INFO if code == mavlink.MAV_MISSION_ACCEPTED else mavlink.MAV_SEVERITY_WARNING)
        up.link.send(mavlink.MAVLink_mission_ack_message(*up.partner, code, MISSION))

    def _ack(self, link, msg, now_s: float) -> None:
        up = self.upload
        if up is not None and (msg.get_srcSystem(), msg.get_srcComponent()) == up.partner:
            self.upload = None  # the ground station gave up
            self.counters["uploads_cancelled"] += 1

    # -- download and clear ---------------------------------------------------------------------

    def _list(self, link, msg, now_s: float) -> None:
        link.send(mavlink.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                                        len(self.held_items()), MISSION))

    def _request(self, link, msg, now_s: float) -> None:
        items = self.held_items()
        if not 0 <= msg.seq < len(items):
            self._send_ack(link, msg, mavlink.MAV_MISSION_INVALID_SEQUENCE)
            return
        item = items[msg.seq]
        p = item.fields
        dest = (msg.get_srcSystem(), msg.get_srcComponent())
        if msg.get_type() == "MISSION_REQUEST_INT":
            out = mavlink.MAVLink_mission_item_int_message(*dest, msg.seq, mavlink.MAV_FRAME_MISSION, item.command, 0, 0,
                                                           *map(float, p[:4]), p[4], p[5], float(p[6]), MISSION)
        else:
            out = mavlink.MAVLink_mission_item_message(*dest, msg.seq, mavlink.MAV_FRAME_MISSION, item.command, 0, 0,
                                                       *map(float, p), MISSION)
        link.send(out)
        self.counters["items_sent"] += 1

    def _clear(self, link, msg, now_s: float) -> None:
        code, reason = self.on_clear()
        if reason:
            self.say(reason, mavlink.MAV_SEVERITY_INFO if code == mavlink.MAV_MISSION_ACCEPTED else mavlink.MAV_SEVERITY_WARNING)
        self._send_ack(link, msg, code)

    def _send_ack(self, link, msg, code: int, mission_type: int = MISSION) -> None:
        link.send(mavlink.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(), code, mission_type))
