"""Filter consistency (Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and
Navigation*, §5.4): normalized estimation error squared (NEES) against the truth, normalized innovation
squared (NIS), and the two-sided chi-square bounds of their averages over independent runs."""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from otbot_hw.model.angles import wrap_angle

#: Angle components of pose/twist error vectors are wrapped before normalizing.
def pose_twist_error(pose, twist, truth_pose, truth_twist) -> np.ndarray:
    """Estimate minus truth (N, 6): x, y (m), alpha wrapped to [-pi, pi) (rad), twist (m/s, rad/s)."""
    e = np.hstack([np.asarray(pose) - truth_pose, np.asarray(twist) - truth_twist])
    e[:, 2] = wrap_angle(e[:, 2])
    return e


def nees(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """e_k^T P_k^-1 e_k (N,) for errors (N, n) and covariances (N, n, n)."""
    return np.einsum("ki,ki->k", err, np.linalg.solve(cov, err[..., None])[..., 0])


def average_bounds(dof: int, runs: int, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided bounds of the average over ``runs`` independent chi-square(dof) values: the average of
    a consistent filter's NEES/NIS falls inside with ``probability``."""
    lo, hi = (1 - probability) / 2, 1 - (1 - probability) / 2
    return float(chi2.ppf(lo, dof * runs) / runs), float(chi2.ppf(hi, dof * runs) / runs)
