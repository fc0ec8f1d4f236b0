"""A plan for another number of drones (``triswarm sim --drones N``): the same formation, sized so
that neighbours keep their separation and the flight stays physical.

Rules, for a rotating polygon (the only formation defined for any N):

* radius: the plan's, or larger so that neighbours are NEIGHBOUR_SPACING times the plan's minimum
  separation apart (chord 2 R sin(pi / N));
* rate: scaled so that the tangential speed R w stays the plan's (the centripetal acceleration
  R w^2 then shrinks as R grows);
* entry: the blend into the formation lasts sqrt(R_new / R) times longer (rounded up to 0.1 s),
  which keeps its peak acceleration (about 5.8 D / T^2 for a quintic over a distance D that grows
  with R);
* topology: a plan that names its families keeps them (plan check refuses those the certificate
  cannot vouch for at the new size); one that names none gets ``graph.default_families(N)``.

Pure: dicts in, dict out.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from .errors import ProtocolError

NEIGHBOUR_SPACING = 1.5
"""Neighbours on a resized polygon are this many minimum separations apart (2.76 m for Table 1)."""


class SizingError(ProtocolError):
    """A plan that cannot be resized (one sentence, without the source)."""


def polygon_radius_m(n_agents: int, spacing_m: float) -> float:
    """The radius at which N agents evenly spaced on a circle are ``spacing_m`` from their neighbours."""
    if n_agents < 2:
        return 0.0
    return spacing_m / (2.0 * math.sin(math.pi / n_agents))


def resized_spec(spec: dict, n_agents: int, min_separation_m: float, blend_s: float) -> dict:
    """The plan dict for ``n_agents`` drones, from the plan's dict, its minimum separation and its
    entry blend duration. Raises SizingError when the plan cannot be resized."""
    out = copy.deepcopy(spec)
    out["drones"] = n_agents
    formation = out.get("formation", {})
    if formation.get("type") != "rotating-polygon":
        raise SizingError(f"only a rotating-polygon formation can be resized to {n_agents} drones")
    if "graphs" in out.get("topology", {}):
        raise SizingError("explicit topology graphs cannot be resized; use topology families")
    if isinstance(formation.get("attitude_rad"), list) and np.ndim(formation["attitude_rad"]) == 2:
        raise SizingError(f"per-drone attitudes cannot be resized to {n_agents} drones")
    radius, rate = formation.get("radius_m"), formation.get("rate_rad_s")
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in (radius, rate)):
        return out  # the parser says what is wrong with them
    needed = polygon_radius_m(n_agents, NEIGHBOUR_SPACING * min_separation_m)
    if needed > radius:
        formation["radius_m"] = needed
        formation["rate_rad_s"] = rate * radius / needed  # the same tangential speed
        if radius > 0:
            out.setdefault("entry", {})["blend_s"] = math.ceil(10.0 * blend_s * math.sqrt(needed / radius)) / 10.0
    return out
