"""Liveliness on the flight's clock (``companion/liveliness.py``): in lockstep a token that went
counts as gone only after the grace, in plan time; in real time at once."""

from triswarm.companion.liveliness import LOCKSTEP_GRACE_S, Liveliness


def test_a_token_gone_is_kept_for_the_grace_of_plan_time_then_let_go():
    live = Liveliness()
    changes = 0
    assert live.update({1, 2, 3}, changes, 10.0, LOCKSTEP_GRACE_S) == frozenset()
    changes += 1  # 2's lease expired on the wall clock
    assert live.update({1, 3}, changes, 10.0, LOCKSTEP_GRACE_S) == {2}
    # the clock stands (the starved process is awaited): however many looks, still kept
    for _ in range(100):
        assert live.update({1, 3}, changes, 10.0, LOCKSTEP_GRACE_S) == {2}
    assert live.update({1, 3}, changes, 10.0 + 0.99 * LOCKSTEP_GRACE_S, LOCKSTEP_GRACE_S) == {2}
    assert live.update({1, 3}, changes, 10.0 + LOCKSTEP_GRACE_S, LOCKSTEP_GRACE_S) == frozenset()
    changes += 1  # back: and a second going has a grace of its own, from when it is seen
    assert live.update({1, 2, 3}, changes, 12.0, LOCKSTEP_GRACE_S) == frozenset()
    changes += 1
    assert live.update({1, 3}, changes, 12.5, LOCKSTEP_GRACE_S) == {2}
    assert live.update({1, 3}, changes, 12.5 + LOCKSTEP_GRACE_S, LOCKSTEP_GRACE_S) == frozenset()


def test_in_real_time_a_token_gone_is_gone_and_one_never_seen_is_never_kept():
    live = Liveliness()
    live.update({1, 2}, 0, 5.0, 0.0)
    assert live.update({1}, 1, 5.0, 0.0) == frozenset()
    assert live.update({1}, 1, 5.0, LOCKSTEP_GRACE_S) == {2}  # (the same going, seen in lockstep)
    fresh = Liveliness()
    assert fresh.update(set(), 0, 0.0, LOCKSTEP_GRACE_S) == frozenset()  # (not yet come is not kept)
    assert fresh.update({3}, 1, 0.5, LOCKSTEP_GRACE_S) == frozenset()
