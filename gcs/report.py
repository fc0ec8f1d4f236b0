"""What a run leaves behind: summary.json and telemetry.csv, and reading them back."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from triswarm.protocol.design import Design
    from triswarm.protocol.metrics import Performance
    from triswarm.protocol.plan import Plan

TELEMETRY_COLUMNS = ["t_s", "drone", "x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad"]


def _complex_list(values) -> list:
    return [{"re": float(np.real(v)), "im": float(np.imag(v))} for v in values]


def design_summary(d: Design) -> dict:
    return {
        "c": d.c,
        "lambda_R": d.lambda_R,
        "eigenvalues_L_plus_G": {name: _complex_list(e) for name, e in zip(d.topology_names, d.eigenvalues)},
        "K": d.K.tolist(),
        "F": d.F.tolist(),
        "F_augmented": None if d.F_aug is None else d.F_aug.tolist(),
        "stability_margins": d.stability_margins(),
        "A_r": d.A_r.tolist(),
        "B_r": d.B_r.tolist(),
    }


def _clean(obj):
    """JSON has no NaN or infinity: write them as null."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    return obj


def write_summary(path: Path, *, plan: Plan, design: Design, performance: Performance, run: dict,
                  per_drone: list[dict], truth: dict | None = None) -> None:
    summary = {
        "scenario": plan.name,
        "drones": plan.n_agents,
        "plan": plan.spec,
        "run": run,
        "design": design_summary(design),
        "performance": performance.as_dict(),
        "per_drone": per_drone,
    }
    if truth is not None:
        summary["truth"] = truth
    path.write_text(json.dumps(_clean(summary), indent=2, default=_json_default) + "\n", encoding="utf-8")


def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if hasattr(obj, "__dataclass_fields__"):
        return asdict(obj)
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


def write_telemetry(path: Path, t_s: np.ndarray, position_m: np.ndarray, euler_rad: np.ndarray) -> None:
    """One row per (time, drone), drones numbered from 1, paper earth frame (z up)."""
    T, N, _ = position_m.shape
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(TELEMETRY_COLUMNS)
        for k in range(T):
            t = f"{t_s[k]:.4f}"
            for i in range(N):
                p, e = position_m[k, i], euler_rad[k, i]
                w.writerow([t, i + 1, f"{p[0]:.5f}", f"{p[1]:.5f}", f"{p[2]:.5f}",
                            f"{e[0]:.6f}", f"{e[1]:.6f}", f"{e[2]:.6f}"])


def read_telemetry(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_s (T,), position_m (T, N, 3), euler_rad (T, N, 3)) from a telemetry.csv; rows may come in
    any order and drones may miss samples (a gap is filled by the drone's previous sample)."""
    data = np.genfromtxt(path, delimiter=",", names=True, dtype=float)
    if data.size == 0:
        raise ValueError(f"{path}: no telemetry rows")
    missing = [c for c in TELEMETRY_COLUMNS if c not in data.dtype.names]
    if missing:
        raise ValueError(f"{path}: missing column {missing[0]}")
    data = np.atleast_1d(data)
    times = np.unique(data["t_s"])
    drones = np.unique(data["drone"]).astype(int)
    T, N = times.size, drones.size
    pos = np.full((T, N, 3), np.nan)
    eta = np.full((T, N, 3), np.nan)
    ti = np.searchsorted(times, data["t_s"])
    di = np.searchsorted(drones, data["drone"].astype(int))
    pos[ti, di] = np.stack([data["x_m"], data["y_m"], data["z_m"]], axis=1)
    eta[ti, di] = np.stack([data["roll_rad"], data["pitch_rad"], data["yaw_rad"]], axis=1)
    for arr in (pos, eta):
        for k in range(1, T):
            gap = np.isnan(arr[k])
            arr[k][gap] = arr[k - 1][gap]
    return times, pos, eta


def read_run(run_dir: Path) -> tuple[dict, Plan]:
    summary = json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))
    from triswarm.protocol.plan import plan_from_dict

    return summary, plan_from_dict(summary["plan"], str(run_dir / "summary.json"))
