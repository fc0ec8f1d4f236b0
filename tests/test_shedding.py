"""The ground-station link's shedding (companion/shedding.py): token buckets against their closed
form, a bucket per sender, and floods told once when they begin and once when they end."""

from collections import Counter

from triswarm.companion.shedding import Episodes, Shedder, TokenBucket


def test_a_bucket_takes_its_burst_then_its_rate():
    b = TokenBucket(rate_per_s=10.0, burst=5.0)
    # 1000 frames a second for 3 s: the burst, then 10 a second (one each 100 ms)
    taken = sum(b.take(k / 1000.0) for k in range(3000))
    assert taken == 5 + 29  # 5 at once, then one at each 0.1 s step of [0.1, 2.999]
    # idle 10 s: full again, never beyond the burst
    assert sum(b.take(13.0) for _ in range(100)) == 5


def test_a_clock_that_goes_back_adds_no_token():
    b = TokenBucket(rate_per_s=1.0, burst=1.0)
    assert b.take(100.0) and not b.take(50.0) and not b.take(100.5) and b.take(101.6)


def test_each_sender_has_its_own_bucket_and_the_table_is_bounded():
    s = Shedder(rate_per_s=1.0, burst=2.0, max_senders=3)
    flood = [s.take(("10.0.0.9", 1), 0.0) for _ in range(1000)]
    assert sum(flood) == 2 and s.dropped[("10.0.0.9", 1)] == 998 and s.total_dropped == 998
    assert s.take(("10.0.0.1", 5), 0.0)  # another sender is not starved by the flood
    for port in range(10):  # new senders evict the ones heard longest ago
        s.take(("10.0.0.2", port), 1.0)
    assert len(s.buckets) == 3 and ("10.0.0.9", 1) not in s.dropped
    assert s.total_dropped == 998  # (the total stays)


def test_floods_are_told_once_when_they_begin_and_once_when_they_end():
    e = Episodes(quiet_s=0.0)  # (over at the first look that sees nothing more)
    counts = Counter()
    assert e.look(counts, 0.0) == ([], [])
    counts["a"] += 10
    assert e.look(counts, 1.0) == ([("a", 10)], [])
    counts["a"] += 500
    counts["b"] += 1
    assert e.look(counts, 2.0) == ([("b", 1)], [])  # a goes on: not said again
    counts["a"] += 5
    assert e.look(counts, 3.0) == ([], [("b", 1, 1.0)])
    assert e.look(counts, 4.0) == ([], [("a", 515, 3.0)])
    assert e.look(counts, 5.0) == ([], [])
    counts["a"] += 1  # a new flood of the same sender: said again
    assert e.look(counts, 6.0) == ([("a", 1)], [])
    del counts["a"]  # (its sender forgotten): its flood ends
    assert e.look(counts, 7.0) == ([], [("a", 1, 1.0)])


def test_a_flood_that_pauses_for_less_than_the_quiet_time_is_one_flood():
    e = Episodes(quiet_s=2.0)
    counts = Counter(a=10)
    assert e.look(counts, 1.0) == ([("a", 10)], [])
    assert e.look(counts, 2.0) == ([], [])  # paused: quiet since 2 s
    assert e.look(counts, 3.0) == ([], [])
    counts["a"] += 20  # on again within the quiet time: the same flood, not said again
    assert e.look(counts, 3.5) == ([], [])
    assert e.look(counts, 4.5) == ([], [])  # quiet since 4.5 s
    assert e.look(counts, 5.5) == ([], [])
    assert e.look(counts, 6.5) == ([], [("a", 30, 3.5)])  # 2 s quiet: over; it lasted from 1 s to 4.5 s
    assert e.look(counts, 7.5) == ([], [])
    counts["a"] += 1
    assert e.look(counts, 8.0) == ([("a", 1)], [])
    del counts["a"]  # forgotten while dropping: over at once
    assert e.look(counts, 9.0) == ([], [("a", 1, 1.0)])
