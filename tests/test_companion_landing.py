"""The companion lands its drone (MAV_CMD_NAV_LAND to the companion, component 191): it leaves the
formation, brakes, descends on its own reference at a mean LAND_SPEED and disarms once its flight
controller says the vehicle is down. The way PX4, whose own controllers do not fly the tri-rotor,
is landed; judged here on triswarm's simulated flight controllers, the whole stack on simulated time.

Each bound is the landing's geometry (``companion.flight.landing``): the descent's quintic peaks at
1.875 times its mean speed, the braking stops within |v| T / 2 of where the command found the drone
(T = max(2 s, |v| / 2 m/s^2)), and the flight controller has LAND_DETECT_S after the descent's end to
say it is down."""

from __future__ import annotations

import re

import numpy as np
import pytest
import tomli_w

from triswarm.companion.flight import LAND_DETECT_S, LAND_SINK_M
from triswarm.gcs.link import GroundLink
from triswarm.gcs.recorder import Recorder
from triswarm.gcs.stack import Stack
from triswarm.gcs.swarm import command_all
from triswarm.protocol.mavlink import COMP_ONBOARD, mavlink

from .poll import poll
from .stack_helpers import flying, small_plan, wait_sim

pytestmark = pytest.mark.slow
LAND_SPEED = 0.5  # the companion's LAND_SPEED default [m/s]
TRACKING_M_S = 0.25
"""What the drones' speed may exceed their reference's by (tracking error, estimate noise) [m/s]."""
TRACKING_M = 0.15
"""What their position may be off their reference's end by [m]."""
LEAD_S = 0.02
"""The servo delay the companions' estimates are predicted over (0.01 s), rounded up to their ticks [s]."""


def _armed(link, i: int) -> bool:
    hb = link.autopilot(i).heartbeat
    return hb is None or bool(hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)


def test_the_companions_land_their_drones_and_disarm_them(tmp_path, paper_spec):
    plan_file = tmp_path / "pair.toml"
    plan_file.write_text(tomli_w.dumps(small_plan(paper_spec, 2, "pair")))
    with Stack(plan_file, tmp_path / "stack", 2, start_delay_s=5.0, lockstep=True, agents_per_process=0) as stack, \
            Recorder(stack.manifest) as rec, GroundLink(stack.endpoints()) as link:
        start = stack.start_at
        wait_sim(rec.now, start + 20.0, stack)  # (the entry is over at 15 s)
        assert flying(link, 1) and flying(link, 2)
        asked = rec.now() - start
        answers = command_all(link, [1, 2], COMP_ONBOARD, mavlink.MAV_CMD_NAV_LAND, [])
        assert all(ok for ok, _ in answers.values()), answers
        poll(lambda: not _armed(link, 1) and not _armed(link, 2), 240.0, "both drones disarmed", every_s=0.2)
        disarmed = rec.now() - start
        poll(lambda: all(link.companion(i).heartbeat.custom_mode == 0 for i in (1, 2)), 30.0,
             "both companions idle (their next heartbeat)")
        refused = command_all(link, [1], COMP_ONBOARD, mavlink.MAV_CMD_NAV_LAND, [])  # (down, the flight over)
        texts = {i: [text for _, _, text in link.companion(i).texts] for i in (1, 2)}
        tracks = rec.tracks(start)
        began = {i: float(re.findall(r"landing at t_plan ([-\d.]+)", stack.log(stack.process_of[i]))[-1]) for i in (1, 2)}
    assert not refused[1][0] and "not flying" in refused[1][1], refused
    for i in (1, 2):
        assert any("landed and disarmed" in text for text in texts[i]), texts[i]
        tr = tracks[i]
        t, p = tr.position_t_s, tr.position_m
        assert asked <= began[i] <= asked + 1.0, (asked, began)  # (the command's way, on a fast simulated clock)
        before = p[t <= began[i]][-1]
        dt = np.diff(t)
        v = np.diff(p, axis=0) / dt[:, None]
        v_at = v[t[1:] <= began[i]][-1]
        speed = float(np.linalg.norm(v_at))
        brake_s = max(2.0, speed / 2.0)
        height = before[2] - (-LAND_SINK_M)  # (the drones rested at 0 before their entry)
        descent_s = max(brake_s, height / LAND_SPEED)
        after = t > began[i]
        # down, never up, and no faster than the descent's peak
        assert p[after, 2].max() <= before[2] + abs(v_at[2]) * brake_s / 2.0 + TRACKING_M, (i, before, p[after, 2].max())
        assert (-v[after[1:], 2]).max() <= 1.875 * LAND_SPEED + TRACKING_M_S, (i, (-v[after[1:], 2]).max())
        # on the ground, where the braking stopped it
        assert p[-1, 2] < 0.05, (i, p[-1])
        drift_m = float(np.linalg.norm(p[-1, :2] - before[:2]))
        # (from its estimate of the instant after the servo delay, up to a sample period after this one)
        ahead_s = float(np.median(dt)) + LEAD_S
        assert drift_m <= float(np.linalg.norm(v_at[:2])) * (brake_s / 2.0 + ahead_s) + TRACKING_M, (i, drift_m, v_at)
        landed_at = t[np.argmax(after & (p[:, 2] < 0.05))]
        assert landed_at >= began[i] + height / (1.875 * LAND_SPEED) - 1.0, (i, began[i], landed_at)
    assert disarmed <= max(began.values()) + descent_s + LAND_DETECT_S + 2.0, (began, disarmed, descent_s)
