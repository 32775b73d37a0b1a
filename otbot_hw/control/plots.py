"""PNG figures and GIF animations of tracking runs (paths, errors, torques against limits)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from otbot_hw.motors import MOTORS, MotorLimits
from otbot_hw.params import OtbotParams
from otbot_hw.plots import _plt, draw_robot, legend_with_robot, plot_series


def _draw_surroundings(ax, spec, legend: bool = True) -> None:
    """Obstacles (grey discs) and corridor walls (dark lines) of a scenario."""
    for i, (cx, cy, r) in enumerate(spec.obstacles):
        ax.add_patch(_plt().Circle((cx, cy), r, color="0.6", label="obstacle" if legend and i == 0 else None))
    for i, wall in enumerate(getattr(spec, "walls", ())):
        ax.plot(wall[:, 0], wall[:, 1], color="0.25", lw=2.5, label="corridor wall" if legend and i == 0 else None)


def _xy_axes(ax, spec, run, params, open_loop=None, snapshots=6):
    _draw_surroundings(ax, spec)
    ax.plot(run.p_ref[:, 0], run.p_ref[:, 1], "--", color="tab:green", lw=1.5, label="desired")
    if open_loop is not None:
        ax.plot(open_loop[1][:, 0], open_loop[1][:, 1], ":", color="tab:red", lw=1.5, label="open loop")
    ax.plot(run.x[:, 0], run.x[:, 1], color="tab:blue", lw=1, label="closed loop")
    if spec.forces is not None:
        for f in spec.forces.forces:
            k = int(round(f.start * run.rate_hz))
            if k < len(run.x):
                mag = float(np.hypot(f.fx, f.fy)) or 1.0
                ax.annotate(f"{mag:g} N", xy=run.x[k, :2], xytext=run.x[k, :2] - 0.6 * np.array([f.fx, f.fy]) / mag,
                            arrowprops={"arrowstyle": "->", "color": "tab:purple"}, color="tab:purple", fontsize=8)
    for i in np.linspace(0, len(run.x) - 1, snapshots).astype(int):
        draw_robot(ax, run.x[i, :6], params, alpha=0.3 + 0.7 * i / max(1, len(run.x) - 1))
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.3)
    legend_with_robot(ax, params, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7)


def scenario_plots(out_dir: Path, spec, run, params: OtbotParams, limits: MotorLimits,
                   open_loop=None) -> list[str]:
    """XY path with the robot drawn, errors in x, y, alpha and their rates, torques vs limits."""
    plt = _plt()
    out_dir.mkdir(parents=True, exist_ok=True)
    files = []
    fig, ax = plt.subplots(figsize=(7, 6))
    _xy_axes(ax, spec, run, params, open_loop)
    ax.set_title(f"{spec.name}: pivot path (platform footprint drawn)")
    p = out_dir / f"{spec.name}_xy.png"
    fig.savefig(p, dpi=110, bbox_inches="tight")
    plt.close(fig)
    files.append(str(p))
    e_p, e_v = run.e_p, run.e_v
    series = {"e_x": (e_p[:, 0], "m"), "e_y": (e_p[:, 1], "m"), "e_alpha": (e_p[:, 2], "rad"),
              "e_x_dot": (e_v[:, 0], "m/s"), "e_y_dot": (e_v[:, 1], "m/s"), "e_alpha_dot": (e_v[:, 2], "rad/s")}
    files.append(str(plot_series(out_dir / f"{spec.name}_errors.png", run.t, series,
                                 title=f"{spec.name}: tracking errors (actual - desired)")))
    fig, axes = plt.subplots(3, 1, figsize=(8, 6.5), sharex=True)
    tk = run.t[:-1]
    for i, ax in enumerate(axes):
        ax.plot(tk, run.u_cmd[:, i], lw=0.8, color="tab:orange", label="commanded (feedforward + feedback)")
        ax.plot(tk, run.u[:, i], lw=1, color="tab:blue", label="applied (after the limiter)")
        ax.plot(tk, run.u_traj[:, i], lw=0.8, color="tab:green", alpha=0.7, label="feedforward")
        ax.plot(tk, run.u_corr[:, i], lw=0.8, color="tab:purple", alpha=0.7, label="feedback")
        lim = limits.max_torque[i]
        ax.axhline(lim, color="tab:red", ls="--", lw=1)
        ax.axhline(-lim, color="tab:red", ls="--", lw=1, label="limit")
        ax.set_ylabel(f"{MOTORS[i]}\n(N m)", fontsize=8)
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="best", fontsize=6, ncol=3)
    axes[0].set_title(f"{spec.name}: motor torques against limits")
    axes[-1].set_xlabel("t (s)")
    p = out_dir / f"{spec.name}_torques.png"
    fig.savefig(p, dpi=110, bbox_inches="tight")
    plt.close(fig)
    files.append(str(p))
    return files


def animate_run(path: Path, spec, run, params: OtbotParams, fps: int = 10, max_frames: int = 200) -> Path:
    """GIF of the robot moving along the run (matplotlib's PillowWriter)."""
    plt = _plt()
    from matplotlib.animation import FuncAnimation, PillowWriter

    path.parent.mkdir(parents=True, exist_ok=True)
    n = len(run.t)
    step = max(1, int(round(run.rate_hz / fps)))
    frames = np.arange(0, n, step)
    if len(frames) > max_frames:
        frames = frames[np.linspace(0, len(frames) - 1, max_frames).astype(int)]
    fig, ax = plt.subplots(figsize=(6, 5))
    pad = params.radius + 0.3
    xs = np.concatenate([run.x[:, 0], run.p_ref[:, 0]])
    ys = np.concatenate([run.x[:, 1], run.p_ref[:, 1]])

    def draw(k):
        ax.clear()
        _draw_surroundings(ax, spec, legend=False)
        ax.plot(run.p_ref[:, 0], run.p_ref[:, 1], "--", color="tab:green", lw=1)
        ax.plot(run.x[:k + 1, 0], run.x[:k + 1, 1], color="tab:blue", lw=1)
        draw_robot(ax, run.x[k, :6], params)
        ax.set_xlim(xs.min() - pad, xs.max() + pad)
        ax.set_ylim(ys.min() - pad, ys.max() + pad)
        ax.set_aspect("equal")
        ax.set_title(f"{spec.name}  t = {run.t[k]:.1f} s")

    anim = FuncAnimation(fig, draw, frames=frames)
    anim.save(str(path), writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path
