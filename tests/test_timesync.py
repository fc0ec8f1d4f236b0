"""The TIMESYNC filter against a remote clock in closed form: remote = (1 + 100e-6) local + offset,
with random one-way delays, outliers (mis-stamped answers) and exchanges too slow to use."""

from __future__ import annotations

import numpy as np
import pytest

from triswarm.protocol.timesync import MAX_RTT_NS, Exchange, TimesyncFilter, fit_exchanges

DRIFT = 100e-6
OFFSET_NS = -1_723_456_789_012_345_678  # a boot clock against Unix time: a large negative offset


def remote_clock(local_ns: float) -> int:
    return int(round(local_ns * (1.0 + DRIFT) + OFFSET_NS))


def exchanges(n: int, seed: int, outlier_every: int = 0, slow_every: int = 0) -> list[Exchange]:
    """One request every 0.2 s of local time from a Unix-like local clock; delays 50-400 us each way."""
    rng = np.random.default_rng(seed)
    out = []
    t0 = 1_750_000_000_000_000_000
    for k in range(n):
        sent = t0 + k * 200_000_000
        d_out, d_back = rng.uniform(50e3, 400e3, 2)
        if slow_every and k % slow_every == 3:
            d_back += 15e6  # a round trip above MAX_RTT_NS
        stamp = remote_clock(sent + d_out)
        if outlier_every and k % outlier_every == 5:
            stamp += int(rng.choice([-1, 1]) * rng.uniform(2e6, 30e6))  # answered with a wrong time
        out.append(Exchange(sent, int(sent + d_out + d_back), stamp))
    return out


def test_clean_exchanges_give_the_drift_and_offset():
    fit = fit_exchanges(exchanges(128, seed=1))
    assert fit is not None and fit.used == 128 and fit.outliers == 0
    # Each exchange errs by (d_out - d_back)/2, within +-175 us: over 25.6 s the slope's error is
    # about 1 ppm at one sigma; the offset at the newest exchange about 15 us.
    assert abs(fit.drift_ppm - 100.0) < 3.0
    truth = remote_clock(fit.ref_local_ns) - fit.ref_local_ns
    assert abs(fit.offset_ns - truth) < 60e3
    assert abs(fit.remote_at(fit.ref_local_ns + 10**9) - remote_clock(fit.ref_local_ns + 10**9)) < 70e3
    assert abs(fit.local_at(remote_clock(fit.ref_local_ns)) - fit.ref_local_ns) < 60e3


def test_outliers_and_slow_exchanges_are_left_out():
    f = TimesyncFilter(window=128)
    for ex in exchanges(200, seed=2, outlier_every=10, slow_every=17):
        f.add(ex)
    fit = f.fit()
    assert f.refused == len(range(3, 200, 17))  # every slow one refused for its round trip
    assert all(ex.rtt_ns <= MAX_RTT_NS for ex in f.exchanges)
    bad = sum(1 for ex in f.exchanges if abs(ex.remote_ns - remote_clock((ex.sent_ns + ex.received_ns) / 2)) > 1e6)
    assert bad >= 10 and fit.outliers >= bad  # every mis-stamped one out
    assert abs(fit.drift_ppm - 100.0) < 3.0
    assert abs(fit.offset_ns - (remote_clock(fit.ref_local_ns) - fit.ref_local_ns)) < 60e3


def test_too_few_exchanges_give_no_fit():
    assert fit_exchanges(exchanges(7, seed=3)) is None
    with pytest.raises(ValueError):
        TimesyncFilter(window=4)


def test_start_clock_check():
    from triswarm.protocol.timesync import START_CLOCK_MAX_ERROR_S, start_clock_problem

    assert "not synchronised" in start_clock_problem(False, 16.0, 0.0)
    assert "no TIMESYNC" in start_clock_problem(True, 0.001, None)
    assert start_clock_problem(True, 0.001, -0.003) is None  # 4 ms: within 5
    assert "6.0 ms off" in start_clock_problem(True, 0.001, 0.005)
    assert "over 5 ms" in start_clock_problem(True, START_CLOCK_MAX_ERROR_S + 1e-6, 0.0)


def test_a_plan_start_is_refused_on_a_bad_clock(tmp_path):
    """The plan-start command gets the check's reason in one line, and nothing is scheduled."""
    import logging

    from triswarm.companion.clock import FcClock
    from triswarm.companion.plans import Plans
    from triswarm.protocol.mavlink import mavlink

    scheduled = []
    plans = Plans(1, None, FcClock(), logging.getLogger("test"), lambda reopen: None, lambda: scheduled.append(1),
                  lambda: False, clock_check=lambda: "the companion's clock is not synchronised")
    result, reason = plans.start(0x1234, 4e9)
    assert result == mavlink.MAV_RESULT_DENIED
    assert reason == "plan start refused: the companion's clock is not synchronised"
    assert plans.mission is None and not scheduled
