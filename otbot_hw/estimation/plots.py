"""PNG plots of an EKF run over a recording (``otbot estimate --plot``): the path, the innovations
against their gates, and -- where the recording knows the truth -- the errors with their 2-sigma band."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from otbot_hw.estimation.replay import EstimationRun
from otbot_hw.model.angles import wrap_angle
from otbot_hw.recording import Recording


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_path(path: Path, rec: Recording, run: EstimationRun, odometry: np.ndarray | None = None) -> Path:
    """x-y path of the pivot (m): the estimate, the truth and wheel odometry where given."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 6))
    if rec.truth_q is not None:
        ax.plot(rec.truth_q[:, 0], rec.truth_q[:, 1], "k-", lw=2.5, alpha=0.35, label="truth")
    if odometry is not None:
        ax.plot(odometry[:, 0], odometry[:, 1], "C2--", lw=1, label="wheel odometry")
    ax.plot(run.pose[:, 0], run.pose[:, 1], "C0-", lw=1, label=f"EKF ({run.prediction} prediction)")
    still = run.standstill
    if still.any():
        ax.plot(run.pose[still, 0], run.pose[still, 1], "C1.", ms=3, label="standstill (zero-velocity update)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("pivot path")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_innovations(path: Path, run: EstimationRun) -> Path:
    """Normalized innovation squared of every update kind used, its gate, and the rejected updates."""
    plt = _plt()
    kinds = [k for k in run.gate if any(kind == k for _, kind, _, _ in run.innovations)]
    fig, axes = plt.subplots(max(1, len(kinds)), 1, figsize=(9, 2.2 * max(1, len(kinds))), sharex=True,
                             squeeze=False)
    for ax, kind in zip(axes[:, 0], kinds):
        rows = np.array([(t, d2, ok) for t, k, d2, ok in run.innovations if k == kind])
        t, d2, ok = rows[:, 0], np.maximum(rows[:, 1], 1e-6), rows[:, 2].astype(bool)
        ax.semilogy(t[ok], d2[ok], ".", ms=2, color="C0", label="accepted")
        if (~ok).any():
            ax.semilogy(t[~ok], d2[~ok], "x", ms=4, color="C3", label=f"rejected ({int((~ok).sum())})")
        ax.axhline(run.gate[kind], color="k", ls="--", lw=0.8, label=f"gate {run.gate[kind]:.1f}")
        ax.set_ylabel(f"NIS {kind}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("t (s)")
    axes[0, 0].set_title("innovations: squared Mahalanobis distance and chi-square gate")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_errors(path: Path, rec: Recording, run: EstimationRun) -> Path:
    """Estimate minus truth of x, y (mm) and alpha (mrad) with the filter's own 2-sigma band."""
    plt = _plt()
    e = run.pose - rec.truth_q[:, :3]
    e[:, 2] = wrap_angle(e[:, 2])
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for i, (ax, name, unit) in enumerate(zip(axes, ("x", "y", "alpha"), ("mm", "mm", "mrad"))):
        ax.fill_between(run.t, -2e3 * run.std[:, i], 2e3 * run.std[:, i], color="C0", alpha=0.2, label="2 sigma")
        ax.plot(run.t, 1e3 * e[:, i], "C0-", lw=0.8, label="estimate - truth")
        ax.set_ylabel(f"{name} error ({unit})")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("t (s)")
    axes[0].set_title("estimation error against the recorded truth")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
