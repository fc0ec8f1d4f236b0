"""TIMESYNC against a real `triswarm sitl up` whose clock runs 100 ppm fast, over loopback MAVLink,
through the companion's own flight-controller face (``companion.flight_controller.FlightController``).

TIMESYNC holds one physical clock against another, so it is judged on the wall clock: the SITL runs
in real time, its autopilot stamping each answer with its clock on arrival, (1 + 100e-6) times
simulated time, which in real time is CLOCK_MONOTONIC from its start. The companion's clock is
CLOCK_MONOTONIC too, so the truth is 100 ppm exactly, and the flight controller's boot in Unix
time is what its SYSTEM_TIME says (Unix time minus boot time, to the millisecond).

Bounds: an exchange errs by at most half its round trip (loopback, well under a millisecond when
answered promptly; refused above 10 ms). Over 20 s of exchanges the drift is within 10 ppm (about
1 ppm measured) and the boot time within 2 ms (SYSTEM_TIME's millisecond plus the fit's error).
"""

from __future__ import annotations

import asyncio
import logging
import time

import pytest

from triswarm.companion.flight_controller import FlightController
from triswarm.companion.timesync import EVERY_S
from triswarm.protocol.mavlink import mavlink

from .sitl_helpers import sitl_process

pytestmark = pytest.mark.realtime

SPAN_S = 20.0
DEADLINE_S = 90.0


async def _measure(url: str) -> dict:
    loop = asyncio.get_running_loop()
    ap = FlightController(1, url, logging.getLogger("test"), lambda: None)
    ap.link.open(loop, lambda link, msgs, t_rx: [ap.take(m, t_rx) for m in msgs])
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
    try:
        deadline = time.monotonic() + DEADLINE_S
        k = 0
        while time.monotonic() < deadline:
            if k % max(1, round(1.0 / EVERY_S)) == 0:
                ap.send(hb)  # (the SITL answers whoever has spoken in the last seconds)
            k += 1
            ap.timesync.request()  # (as often as the companion asks: the fit's window spans 128 of them)
            await asyncio.sleep(EVERY_S)
            fit = ap.timesync.fit
            if fit is not None and fit.span_ns >= SPAN_S * 1e9 and fit.used >= 100:
                break
        assert ap.clock.known, "no SYSTEM_TIME from the SITL"
        return dict(ap.timesync.report(), system_time_boot_unix_s=ap.clock.offset_us / 1e6)
    finally:
        ap.link.close()


def test_drift_and_offset_of_a_100_ppm_clock(tmp_path):
    with sitl_process(tmp_path, 1, "--clock-drift-ppm", "100", "--physics-hz", "200", "--rate-hz", "0") as (manifest, _):
        url = manifest["vehicles"][0]["links"]["companion"]["pymavlink"]
        report = asyncio.run(_measure(url))
    print(report)
    assert report["fc_clock_span_s"] >= SPAN_S, report
    assert abs(report["fc_clock_drift_ppm"] - 100.0) < 10.0, report
    assert abs(report["fc_boot_unix_s"] - report["system_time_boot_unix_s"]) < 0.002, report
