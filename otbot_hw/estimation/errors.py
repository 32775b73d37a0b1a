"""The estimation error against the truth, computed in one place and described by one function (the
``estimation_error`` block of ``otbot estimate``, ``otbot track`` and ``otbot demo``)."""
from __future__ import annotations

import numpy as np

from otbot_hw.model.angles import wrap_angle

NAMES = ("x", "y", "alpha")


def estimation_error(pose, truth_pose) -> dict:
    """{'max': {x, y, alpha}, 'rms': {...}} of estimate - truth over the samples of (N, 3) poses (m, m, rad;
    the alpha difference wrapped to [-pi, pi): alpha is continuous, never wrapped, in both)."""
    e = np.asarray(pose, dtype=float)[:, :3] - np.asarray(truth_pose, dtype=float)[:, :3]
    e[:, 2] = wrap_angle(e[:, 2])
    return {"max": {n: float(np.abs(e[:, i]).max()) for i, n in enumerate(NAMES)},
            "rms": {n: float(np.sqrt(np.mean(e[:, i] ** 2))) for i, n in enumerate(NAMES)}}


def describe_estimation_error(e: dict) -> str:
    """One line: max (rms) of each component in mm and mrad."""
    m, r = e["max"], e["rms"]
    return (f"estimation error (estimate - truth), max (rms): x {1e3 * m['x']:.2f} ({1e3 * r['x']:.2f}) mm, "
            f"y {1e3 * m['y']:.2f} ({1e3 * r['y']:.2f}) mm, alpha {1e3 * m['alpha']:.3f} ({1e3 * r['alpha']:.3f}) mrad")
