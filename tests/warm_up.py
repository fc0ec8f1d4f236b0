"""Compile protocol/'s numba kernels, or load them from numba's cache, before the tests need them.

On a fresh clone every process that needs the kernels would otherwise compile them at the same time,
and a whole-stack test's first seconds would go to the compiler. ``make test`` compiles them before its
two runs, in two processes at once, one per part (3 and 6 s of compiling on a fresh clone); a plain
``pytest`` does it at its start (tests/conftest.py).

    python -m tests.warm_up PART
"""

from __future__ import annotations

import sys
from pathlib import Path

PARTS = ("plant", "controller")


def warm_up(part: str) -> None:
    """Compile one part's kernels, and solve the paper plan's design (kept in the design cache)."""
    import tomllib

    import numpy as np

    from triswarm.companion.design_cache import keep_on_disk
    from triswarm.protocol import jit
    from triswarm.protocol.airframe import TABLE_1
    from triswarm.protocol.plan import plan_from_dict

    jit.cache_on_disk()
    keep_on_disk()
    if part == "plant":
        from triswarm.protocol.wind import Wind
        from triswarm.sitl.physics import Plant

        for wind in (None, Wind(turbulence_sigma_w_m_s=1.0)):  # the plant in no air and in wind: two compilations
            plant = Plant(TABLE_1, 1, wind=wind)
            plant.reset(np.zeros((1, 3)))
            plant.advance(1)
            plant.observe()
    elif part == "controller":
        from triswarm.protocol.controller import FormationController

        plan_file = Path(__file__).resolve().parents[1] / "examples" / "paper-hexagon.toml"
        FormationController.warm_up(plan_from_dict(tomllib.loads(plan_file.read_text())).design, 200.0)
    else:
        raise ValueError(f"no such part: {part!r} (the parts: {', '.join(PARTS)})")


if __name__ == "__main__":
    warm_up(sys.argv[1])
