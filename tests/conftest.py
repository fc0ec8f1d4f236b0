import os
import tomllib
from pathlib import Path

# pymavlink's own tools pick MAVLink 2 from the environment; set it before any test imports mavutil.
os.environ.setdefault("MAVLINK20", "1")

import numpy as np
import pytest

from triswarm.companion.design_cache import keep_on_disk
from triswarm.protocol import jit
from triswarm.protocol.airframe import TABLE_1
from triswarm.protocol.plan import plan_from_dict
from triswarm.protocol.rfl import RFL

from .warm_up import PARTS, warm_up

ROOT = Path(__file__).resolve().parents[1]
PAPER_PLAN_FILE = ROOT / "examples" / "paper-hexagon.toml"

jit.cache_on_disk()  # the tests are an edge: protocol/'s compiled code is kept in numba's cache, as the programs keep it
keep_on_disk()  # and the design's solved Riccati equations, as the programs keep them


def pytest_sessionstart(session) -> None:
    """Compile the numba kernels once, here, before any test (or xdist worker) starts (tests/warm_up.py;
    under ``make test`` they are compiled already, and this loads them from numba's cache)."""
    if hasattr(session.config, "workerinput"):  # an xdist worker: the controller has done it
        return
    for part in PARTS:
        warm_up(part)


def paper_plan_variant(tmp_path: Path, replace: list[tuple[str, str]], source: Path = PAPER_PLAN_FILE) -> Path:
    """examples/paper-hexagon.toml (or ``source``) with each (old, new) text replaced (each old must
    be there), written as tmp_path/plan.toml."""
    text = source.read_text()
    for old, new in replace:
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "plan.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="session")
def airframe():
    return TABLE_1


@pytest.fixture(scope="session")
def rfl():
    return RFL.from_airframe(TABLE_1)


@pytest.fixture(scope="session")
def paper_spec():
    return tomllib.loads(PAPER_PLAN_FILE.read_text())


@pytest.fixture(scope="session")
def paper_plan(paper_spec):
    return plan_from_dict(paper_spec, str(PAPER_PLAN_FILE))


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def random_states(rng, n, max_pitch=1.2):
    """Random x of (28) with |theta| < max_pitch."""
    x = np.empty((n, 12))
    x[:, 0:3] = rng.uniform(-5, 5, (n, 3))
    x[:, 3:6] = rng.uniform(-2, 2, (n, 3))
    x[:, 6] = rng.uniform(-np.pi, np.pi, n)
    x[:, 7] = rng.uniform(-max_pitch, max_pitch, n)
    x[:, 8] = rng.uniform(-np.pi, np.pi, n)
    x[:, 9:12] = rng.uniform(-20, 20, (n, 3))
    return x
