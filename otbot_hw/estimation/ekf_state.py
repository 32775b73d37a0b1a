"""The pose EKF's state layout, its output record and its input checks (``otbot_hw.estimation.ekf``).

State (14,), ground frame B unless said otherwise: the indices ``X`` ... ``NAY`` below, named by
``STATE_NAMES`` (the module docstring of ``ekf`` says what each is).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from otbot_hw.estimation import kernels

N_STATE = 14
X, Y, A, VX, VY, VA, BG, BAX, BAY, KAPPA, EP, DA, NAX, NAY = range(N_STATE)
STATE_NAMES = ("x", "y", "alpha", "x_dot", "y_dot", "alpha_dot", "gyro_bias", "accel_bias_x", "accel_bias_y",
               "kappa", "pivot_quantization", "alpha_dd_unmodelled", "accel_noise_x", "accel_noise_y")
#: Update kinds and their dimensions.
UPDATE_KINDS = {"encoders": 3, "heading": 1, "zupt": 3, "gyro": 1, "accel": 2, "fix": 3}
#: Default std of the start pose (m, m, rad): the start defines the frame. Prior std of the twist.
INITIAL_POSE_STD = (1e-6, 1e-6, 1e-6)
INITIAL_TWIST_STD = (0.01, 0.01, 0.01)
#: A wheel heading that disagrees this long (s) while the joint rates agree has moved (re-anchor it); a gyro
#: rejected this long has lost the yaw prediction (re-anchor alpha_dot on it).
REANCHOR_AFTER = 0.02


class EstimatorFault(RuntimeError):
    """NaN or stale sensor data, non-monotonic time, a diverged filter. str() says which, in words."""


@dataclass(frozen=True)
class Estimate:
    """What the EKF believes at t (s), after using that sample's sensors.

    pose (3,) x, y (m), alpha (rad) of the pivot P / platform in B; twist (3,) m/s, m/s, rad/s;
    std (6,) their standard deviations; cov (14, 14) the full covariance (state order of the module
    docstring); gyro_bias (rad/s); standstill: a zero-velocity update was applied; nis: normalized
    innovation squared of each update kind this step (nan: none); rejected / updates: cumulative gate
    rejections / accepted updates per kind; accel_bias (2,) m/s^2 in B''.
    """

    t: float
    pose: np.ndarray
    twist: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    gyro_bias: float
    standstill: bool
    nis: dict
    rejected: dict
    updates: dict
    accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(2))


def check_vector(v, n: int, name: str, t) -> np.ndarray:
    """``v`` as a float array (n,): ValueError for another shape, ``EstimatorFault`` for a non-finite value."""
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (n,):
        a = a.reshape(-1)
        if a.shape != (n,):
            raise ValueError(f"{name} must have {n} values, got shape {np.shape(v)}")
    if not kernels.all_finite(a):
        raise EstimatorFault(f"non-finite {name} at t = {t} s: {a.tolist()}")
    return a
