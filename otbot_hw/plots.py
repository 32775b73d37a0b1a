"""Matplotlib figures (PNG) shared by the commands: robot drawing, paths, time series."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from otbot_hw.params import OtbotParams


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def draw_robot(ax, q: np.ndarray, p: OtbotParams, color: str = "k", alpha: float = 1.0) -> None:
    """Draw Otbot at configuration q: platform disc, chassis axle with wheels, pivot P and M."""
    x, y, a = q[0], q[1], q[2]
    th = q[2] - q[5]
    c, s = np.cos(th), np.sin(th)
    P = np.array([x, y])
    M = P - p.l1 * np.array([c, s])
    side = np.array([-s, c]) * p.l2
    ax.add_patch(_plt().Circle(P, p.radius, fill=False, color=color, alpha=0.5 * alpha, lw=1))
    ax.plot(*np.array([M - side, M + side]).T, color=color, alpha=alpha, lw=1.5)
    ax.plot(*np.array([M, P]).T, color=color, alpha=alpha, lw=1)
    for w in (M + side, M - side):
        d = np.array([c, s]) * p.r
        ax.plot(*np.array([w - d, w + d]).T, color=color, alpha=alpha, lw=4, solid_capstyle="butt")
    ax.plot(*(P + p.radius * np.array([np.cos(a), np.sin(a)]) * np.array([[0], [1]])).T,
            color="tab:red", alpha=alpha, lw=1)
    ax.plot(*P, "o", color=color, ms=3, alpha=alpha)


def robot_legend_handles(p: OtbotParams, color: str = "k") -> list:
    """Legend entries for the symbols ``draw_robot`` draws (proxy artists)."""
    plt = _plt()
    from matplotlib.lines import Line2D

    return [plt.Circle((0, 0), 1, fill=False, color=color, alpha=0.5, label=f"platform footprint (r = {p.radius:g} m)"),
            Line2D([], [], color="tab:red", lw=1, label="platform heading (alpha)"),
            Line2D([], [], color=color, lw=4, label="chassis: wheels and axle"),
            Line2D([], [], color=color, marker="o", ms=3, lw=0, label="pivot P")]


def legend_with_robot(ax, p: OtbotParams, **kw) -> None:
    """``ax.legend`` with the plotted lines' labels and the robot symbols' meaning."""
    handles, _ = ax.get_legend_handles_labels()
    ax.legend(handles=handles + robot_legend_handles(p), **kw)


def plot_xy_path(path: str | Path, q: np.ndarray, p: OtbotParams, title: str = "",
                 reference: np.ndarray | None = None, snapshots: int = 5,
                 obstacles: Sequence[tuple[float, float, float]] = ()) -> Path:
    """XY path of the pivot with the robot drawn at ``snapshots`` instants; returns the PNG path."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 6))
    if reference is not None:
        ax.plot(reference[:, 0], reference[:, 1], "--", color="tab:green", label="desired")
    ax.plot(q[:, 0], q[:, 1], color="tab:blue", label="pivot path")
    for cx, cy, rad in obstacles:
        ax.add_patch(plt.Circle((cx, cy), rad, color="0.6"))
    for i in np.linspace(0, len(q) - 1, snapshots).astype(int):
        draw_robot(ax, q[i], p, alpha=0.4 + 0.6 * i / max(1, len(q) - 1))
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or "Pivot path (robot drawn at a few instants)")
    ax.grid(True, alpha=0.3)
    legend_with_robot(ax, p, loc="best", fontsize=8)
    out = Path(path)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out


def plot_series(path: str | Path, t: np.ndarray, series: dict[str, tuple[np.ndarray, str]],
                title: str = "", overlay: dict[str, np.ndarray] | None = None) -> Path:
    """One subplot per entry ``name -> (values (N,), unit)``; ``overlay`` adds a second line per name."""
    plt = _plt()
    n = len(series)
    fig, axes = plt.subplots(n, 1, figsize=(8, 1.8 * n + 0.6), sharex=True, squeeze=False)
    for ax, (name, (vals, unit)) in zip(axes[:, 0], series.items()):
        ax.plot(t, vals, lw=1, label="measured" if overlay else None)
        if overlay and name in overlay:
            ax.plot(t, overlay[name], lw=1, label="predicted")
            ax.legend(loc="best", fontsize=7)
        ax.set_ylabel(f"{name}\n({unit})", fontsize=8)
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("t (s)")
    if title:
        axes[0, 0].set_title(title)
    out = Path(path)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out


def plot_states(path: str | Path, t: np.ndarray, x: np.ndarray, title: str = "") -> Path:
    """The 12 state components over time."""
    names = [("x", "m"), ("y", "m"), ("alpha", "rad"), ("phi_r", "rad"), ("phi_l", "rad"), ("phi_p", "rad")]
    series = {n: (x[:, i], u) for i, (n, u) in enumerate(names)}
    series.update({f"d{n}/dt": (x[:, 6 + i], f"{u}/s") for i, (n, u) in enumerate(names)})
    return plot_series(path, t, series, title=title or "State over time")
