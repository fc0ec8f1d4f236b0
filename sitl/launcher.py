"""`triswarm sitl up`: N simulated flight controllers in one process until SIGINT or SIGTERM.

One process for the whole swarm: the physics of every vehicle is one batched numba step, all
vehicles share one clock (so ``--speedup`` keeps their timestamps consistent with each other), and
there is exactly one process to stop and no inter-process synchronisation to get wrong.
"""

from __future__ import annotations

import asyncio
import signal
from collections.abc import Callable
from dataclasses import dataclass
from triswarm.protocol.airframe import ParameterError
from triswarm.protocol.frames import DEFAULT_HOME, LocalProjection
from triswarm.protocol.wind import Wind

from .estimator import profile as estimator_profile
from .fc import LINK_PREFIX
from .lockstep import LockstepOptions
from .profiles import profile
from .server import SitlServer
from .swarm import SitlSwarm


@dataclass(frozen=True)
class SitlOptions:
    n: int
    home: tuple[float, float, float] = DEFAULT_HOME
    speedup: float = 1.0
    rate_hz: float | None = None
    """ATTITUDE and LOCAL_POSITION_NED rate on every companion link [Hz] (None: the profile's defaults)."""
    fc_profile: str = "triswarm"
    """How the companion links stream, as which autopilot (``profiles.py``)."""
    physics_hz: float = 1000.0
    base_port: int = 14600
    bind: str = "127.0.0.1"
    spacing_m: float = 2.5
    seed: int = 0
    duration_s: float | None = None
    """Stop by itself after this much simulated time (tests, benchmarks)."""
    first_id: int = 1
    """System id of the first vehicle: vehicle i (from 1) is system first_id + i - 1 (a swarm split over
    several hosts); its resting place follows its id (``swarm.ground_grid``)."""
    params: tuple[tuple[str, float], ...] = ()
    """Parameter values every vehicle starts with (e.g. sensor noise), as (name, value)."""
    lockstep: LockstepOptions | None = None
    """Step the clock by the companions' answers instead of the wall clock (``lockstep.py``)."""
    wind: Wind | None = None
    """The air the vehicles fly in (``protocol.wind``), its turbulence seeded by ``seed``; None: no air."""
    clock_drift_ppm: float = 0.0
    """The flight controllers' clocks run this much faster than simulated time [ppm] (``fc.clock_s``)."""
    estimator: str | None = None
    """The flight controllers' estimator profile (``sitl.estimator.PROFILES``); None: the truth."""


async def run_sitl(opts: SitlOptions, on_ready: Callable[[dict], None] | None = None,
                   say: Callable[..., None] = lambda text, warning=False: print(text)) -> dict:
    """Open every link, hand the manifest to ``on_ready``, fly until a signal (or duration of
    simulated time); return the stats. ``say`` gets the lockstep's news."""
    if opts.n < 1:
        raise ValueError(f"-n must be at least 1, got {opts.n}")
    swarm = SitlSwarm(opts.n, LocalProjection(*opts.home), physics_hz=opts.physics_hz, spacing_m=opts.spacing_m,
                      seed=opts.seed, first_id=opts.first_id, wind=opts.wind, profile=profile(opts.fc_profile),
                      estimator=None if opts.estimator is None else estimator_profile(opts.estimator))
    for i, fc in enumerate(swarm.fcs):
        fc.clock_ppm = opts.clock_drift_ppm
        for code in ("ATT", "LPOS") if opts.rate_hz is not None else ():
            problem = fc.set_param(f"{LINK_PREFIX['companion']}_{code}_HZ", opts.rate_hz)
            if problem:
                raise ParameterError(f"--rate-hz: {problem}")
        for name, value in opts.params:
            problem = fc.set_param(name, value)
            if problem:
                raise ParameterError(f"--param {name}={value:g}: {problem}")
        swarm.apply_airframe(i)
    server = SitlServer(swarm, opts.bind, opts.base_port, opts.speedup, opts.lockstep, say=say)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await server.open()
        if on_ready is not None:
            on_ready(server.manifest())
        await server.run(stop, opts.duration_s)
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        server.close()
    return server.stats()
