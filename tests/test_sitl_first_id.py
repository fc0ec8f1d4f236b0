"""`sitl up --first-id K`: a host's share of a swarm split over several machines flies system ids
K .. K+n-1, resting where one process flying 1 .. K+n-1 would put them."""

import asyncio

import numpy as np
import pytest

from triswarm.protocol import frames
from triswarm.sitl.launcher import SitlOptions, run_sitl
from triswarm.sitl.swarm import SitlSwarm, ground_grid


def manifest(n: int, first_id: int = 1) -> dict:
    got = {}
    asyncio.run(run_sitl(SitlOptions(n=n, base_port=0, first_id=first_id, duration_s=0.01),
                         on_ready=lambda m: got.update(m)))
    return got


def starts(m: dict) -> np.ndarray:
    return np.array([frames.flip(np.array(v["start_ned_m"])) for v in m["vehicles"]])


def test_one_process_rests_on_a_centred_grid():
    # by hand: rows of ceil(sqrt(n)) vehicles, north then west, the grid's box centred on the origin
    np.testing.assert_allclose(ground_grid(1, 2.5), [[0.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(ground_grid(2, 2.5), [[0.0, 1.25, 0.0], [0.0, -1.25, 0.0]], atol=1e-12)
    np.testing.assert_allclose(ground_grid(3, 2.5), [[-1.25, 1.25, 0.0], [-1.25, -1.25, 0.0], [1.25, 1.25, 0.0]],
                               atol=1e-12)
    for n in range(2, 31):
        p = ground_grid(n, 2.0)
        assert p.shape == (n, 3) and np.all(p[:, 2] == 0.0)
        gaps = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2) + np.eye(n) * 1e9
        assert gaps.min() == pytest.approx(2.0), n  # neighbours exactly one spacing apart
        cols = int(np.ceil(np.sqrt(n)))
        assert np.ptp(p[:, 1]) == pytest.approx(2.0 * (cols - 1)), n  # a full first row
        assert p[:, 1].max() == pytest.approx(-p[:, 1].min()), n  # centred east-west
        assert p[:, 0].max() == pytest.approx(-p[:, 0].min()), n  # and north-south
    m = manifest(3)
    assert [v["sysid"] for v in m["vehicles"]] == [1, 2, 3]
    np.testing.assert_allclose(starts(m), ground_grid(3), atol=1e-12)


def test_three_hosts_of_two():
    hosts = {1: manifest(2, 1), 3: manifest(2, 3), 5: manifest(2, 5)}
    for k, m in hosts.items():
        assert [v["sysid"] for v in m["vehicles"]] == [k, k + 1]
        # where one process of K+1 vehicles puts vehicles K and K+1
        np.testing.assert_allclose(starts(m), ground_grid(k + 1)[k - 1:], atol=1e-12)
    everyone = np.concatenate([starts(m) for m in hosts.values()])
    gaps = np.linalg.norm(everyone[:, None, :2] - everyone[None, :, :2], axis=2) + np.eye(6) * 1e9
    assert gaps.min() >= 2.5 / 2 - 1e-9, gaps  # no two of the six on top of each other


def test_ids_out_of_range():
    with pytest.raises(ValueError):
        ground_grid(2, first_id=0)
    with pytest.raises(ValueError, match="1..255"):
        SitlSwarm(2, first_id=255)
