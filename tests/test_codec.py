"""The estimate codec agents speak over Zenoh: exact round trip, a fixed layout, one clear reason
for every payload it refuses."""

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from triswarm.protocol.codec import (ESTIMATE_SIZE, AgentStatus, CodecError, Estimate, agent_of_key, alive_key,
                                     decode_estimate, decode_header, encode_estimate, estimate_key, plan_id)

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


def sample(**kw) -> Estimate:
    base = dict(agent=3, plan_id=0xDEADBEEF, seq=7, stamp_s=1.79e9 + 0.123456, t_plan_s=31.005,
                status=AgentStatus.FLYING, xi=np.arange(12.0) - 5.5)
    base.update(kw)
    return Estimate(**base)


@settings(max_examples=200, deadline=None)
@given(agent=st.integers(1, 65535), plan=st.integers(0, 2**32 - 1), seq=st.integers(0, 2**32 - 1),
       stamp=finite, t_plan=finite, status=st.sampled_from(list(AgentStatus)),
       xi=st.lists(finite, min_size=12, max_size=12))
def test_round_trip_is_exact(agent, plan, seq, stamp, t_plan, status, xi):
    e = Estimate(agent, plan, seq, stamp, t_plan, status, np.array(xi))
    data = encode_estimate(e)
    assert len(data) == ESTIMATE_SIZE == 124
    d = decode_estimate(data)
    assert (d.agent, d.plan_id, d.seq, d.stamp_s, d.t_plan_s, d.status) == (agent, plan, seq, stamp, t_plan, status)
    np.testing.assert_array_equal(d.xi, np.array(xi))


def test_layout_is_the_documented_one():
    """Independent of the codec's own structs: the offsets of the module docstring."""
    e = sample()
    data = encode_estimate(e)
    assert data[0] == 1 and data[1] == int(AgentStatus.FLYING)
    assert struct.unpack_from("<H", data, 2)[0] == 3
    assert struct.unpack_from("<I", data, 4)[0] == 0xDEADBEEF
    assert struct.unpack_from("<I", data, 8)[0] == 7
    assert struct.unpack_from("<d", data, 12)[0] == e.stamp_s
    assert struct.unpack_from("<d", data, 20)[0] == e.t_plan_s
    np.testing.assert_array_equal(struct.unpack_from("<12d", data, 28), e.xi)


@pytest.mark.parametrize("mutate, reason", [
    (lambda b: b[:-1], "size 123"),
    (lambda b: b + b"\0", "size 125"),
    (lambda b: b"", "size 0"),
    (lambda b: bytes([2]) + b[1:], "version 2"),
    (lambda b: b[:1] + bytes([9]) + b[2:], "unknown status 9"),
    (lambda b: b[:2] + struct.pack("<H", 0) + b[4:], "agent number 0"),
    (lambda b: b[:12] + struct.pack("<d", math.nan) + b[20:], "non-finite"),
    (lambda b: b[:20] + struct.pack("<d", math.inf) + b[28:], "non-finite"),
    (lambda b: b[:28 + 8 * 5] + struct.pack("<d", math.nan) + b[28 + 8 * 6:], "non-finite"),
])
def test_refuses_bad_payloads_with_a_reason(mutate, reason):
    data = mutate(encode_estimate(sample()))
    with pytest.raises(CodecError, match=reason):
        decode_estimate(data)


def test_header_decodes_without_touching_xi():
    data = bytearray(encode_estimate(sample()))
    data[28 + 8 * 3:28 + 8 * 4] = struct.pack("<d", math.nan)
    status, agent, plan, seq, stamp, t_plan = decode_header(bytes(data))
    assert (status, agent, plan, seq) == (AgentStatus.FLYING, 3, 0xDEADBEEF, 7)


def test_keys_name_the_agent():
    assert estimate_key("paper-hexagon", 4) == "triswarm/paper-hexagon/agent/4/estimate"
    assert agent_of_key(estimate_key("s", 12)) == 12
    assert agent_of_key(alive_key("s", 3)) == 3
    for bad in ("triswarm/s/agent/x/estimate", "other/s/agent/3/estimate", "triswarm/s", "", "triswarm/s/agent/-1/a"):
        assert agent_of_key(bad) is None


def test_plan_id_is_a_function_of_content(paper_spec):
    a = plan_id(paper_spec)
    assert a == plan_id(dict(reversed(list(paper_spec.items()))))  # key order does not matter
    changed = {**paper_spec, "formation": {**paper_spec["formation"], "radius_m": 9.0}}
    assert plan_id(changed) != a
    assert 0 <= a < 2**32
