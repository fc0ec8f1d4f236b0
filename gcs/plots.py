"""Figures like the paper's Figs. 7, 9 and 10, and the formation error against time."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from triswarm.protocol.metrics import Performance, formation_errors  # noqa: E402
from triswarm.protocol.plan import Plan  # noqa: E402


def _colors(n: int):
    cmap = plt.get_cmap("tab10" if n <= 10 else "viridis")
    return [cmap(i % 10 if n <= 10 else i / max(n - 1, 1)) for i in range(n)]


def make_figures(out_dir: Path, plan: Plan, t_s: np.ndarray, position_m: np.ndarray, euler_rad: np.ndarray,
                 performance: Performance | None = None, max_lines: int = 24) -> list[Path]:
    """Write the figures into out_dir; returns their paths."""
    out_dir = Path(out_dir)
    n = position_m.shape[1]
    shown = np.linspace(0, n - 1, min(n, max_lines)).round().astype(int)
    colors = _colors(n)
    ref = np.stack([plan.reference(float(t))[0] for t in t_s])
    x0 = plan.leader_state(float(t_s[-1]))[0][9:12]
    paths = []

    fig = plt.figure(figsize=(7.5, 6.5))
    ax = fig.add_subplot(projection="3d")
    for i in shown:
        ax.plot(position_m[:, i, 0], position_m[:, i, 1], position_m[:, i, 2], color=colors[i], lw=1.0,
                label=f"drone {i + 1}")
        ax.scatter(*position_m[0, i], color=colors[i], marker="o", s=12)
        ax.scatter(*position_m[-1, i], color=colors[i], marker="^", s=25)
    ax.scatter(*x0, color="k", marker="x", s=60, label="target x0")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title(f"{plan.name}: 3D trajectories (o start, ^ end)")
    if len(shown) <= 12:
        ax.legend(loc="upper left", fontsize=7)
    paths.append(_save(fig, out_dir / "fig7_trajectories_3d.png"))

    for fname, title, series, refcols, labels, unit in (
        ("fig9_attitude.png", "attitude", euler_rad, slice(6, 9), ("roll φ", "pitch θ", "yaw ψ"), "rad"),
        ("fig10_position.png", "position", position_m, slice(9, 12), ("x", "y", "z"), "m"),
    ):
        fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
        for k, ax in enumerate(axes):
            for i in shown:
                ax.plot(t_s, series[:, i, k], color=colors[i], lw=1.0, label=f"drone {i + 1}")
                ax.plot(t_s, ref[:, i, refcols][:, k], color=colors[i], lw=0.8, ls="--", alpha=0.6)
            ax.set_ylabel(f"{labels[k]} [{unit}]")
            ax.grid(alpha=0.3)
        axes[0].set_title(f"{plan.name}: {title} (solid flown, dashed x0 + h_i)")
        axes[-1].set_xlabel("t [s]")
        if len(shown) <= 12:
            axes[0].legend(ncol=min(len(shown), 6), fontsize=7, loc="upper right")
        paths.append(_save(fig, out_dir / fname))

    pos_err, att_err = formation_errors(plan, t_s, position_m, euler_rad)
    fig, axes = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    floor = 1e-6
    for i in shown:
        axes[0].semilogy(t_s, np.maximum(pos_err[:, i], floor), color=colors[i], lw=1.0, label=f"drone {i + 1}")
        axes[1].semilogy(t_s, np.maximum(att_err[:, i].max(axis=1), floor), color=colors[i], lw=1.0)
    axes[0].set_ylabel("|position error| [m]")
    axes[1].set_ylabel("max |attitude error| [rad]")
    axes[1].set_xlabel("t [s]")
    if performance is not None:
        for ax, bound in ((axes[0], performance.position_bound_m), (axes[1], performance.attitude_bound_rad)):
            ax.axhline(bound, color="k", ls=":", lw=1.0, label="bound")
            ax.axvline(performance.window_start_s, color="grey", ls="--", lw=0.8)
    for ax in axes:
        ax.grid(alpha=0.3, which="both")
    axes[0].set_title(f"{plan.name}: formation error against x0 + h_i(t)")
    if len(shown) <= 12:
        axes[0].legend(ncol=min(len(shown), 6), fontsize=7, loc="upper right")
    paths.append(_save(fig, out_dir / "formation_error.png"))
    return paths


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
