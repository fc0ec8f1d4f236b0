"""The ports a stack picks for its companions' listeners (which peers must know before they start):
free for TCP and UDP, below the kernel's ephemeral range, and never one picked twice."""

from triswarm.gcs.stack import _below_ephemeral, free_ports


def test_ports_are_free_below_the_ephemeral_range_and_apart():
    lo, hi = _below_ephemeral()
    for _ in range(20):
        zenoh = free_ports(200, contiguous=True)
        assert zenoh == list(range(zenoh[0], zenoh[0] + 200))
        gcs = free_ports(200, exclude=frozenset(zenoh))
        assert len(set(gcs)) == 200 and not set(gcs) & set(zenoh)
        assert all(lo <= p < hi for p in zenoh + gcs)
