"""``MotionCapture``: a simulated absolute pose source (motion capture, landmarks) for the loop's EKF.

It reads the simulated robot's true platform pose (``Robot.truth()``: pivot P and platform heading,
ground frame B) at its own rate and reports it with its own white noise, the heading wrapped to
[-pi, pi) as a tracking system reports it; the EKF takes it as an absolute pose fix with the stated
covariance (``otbot_hw.runtime.feedback.EkfFeedback``, ``PoseEKF.fix``). Honest limits: the fix is
delivered at the sample it describes (no latency), the noise is white and Gaussian with exactly the
stated sigma, and the ground frame is the run's (no registration error between the two frames).
"""
from __future__ import annotations

import math

import numpy as np

from drivers.robot import imu_due
from otbot_hw.model.angles import wrap_angle


class MotionCapture:
    """Absolute pose fixes at ``rate_hz`` (> 0) with noise std ``std`` = (x m, y m, alpha rad), seeded.

    ``poll(t, sample_index, period, robot)`` -> (pose (3,), cov (3, 3)) when a new fix is due at this
    sample (the same schedule as the IMU's: a fix when sample_index * period enters a new period of
    the source; none at sample 0, where the start pose is known), else None."""

    def __init__(self, rate_hz: float, std=(0.002, 0.002, 0.002), seed: int | None = 0):
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise ValueError(f"motion-capture rate must be a finite number of Hz > 0, got {rate_hz}")
        self.rate_hz = float(rate_hz)
        self.std = np.asarray(std, dtype=float).reshape(3)
        if not np.all(np.isfinite(self.std)) or np.any(self.std <= 0):
            raise ValueError(f"motion-capture std must be 3 numbers > 0 (m, m, rad), got {std!r}")
        self.cov = np.diag(self.std ** 2)
        self.rng = np.random.default_rng(seed)
        self.count = 0

    def poll(self, sample_index: int, period: float, robot):
        if sample_index == 0 or not imu_due(sample_index, period, self.rate_hz):
            return None
        x = robot.truth()
        if x is None:
            raise RuntimeError("the simulated motion capture needs a back end that knows the true pose")
        pose = np.asarray(x[:3], dtype=float) + self.std * self.rng.standard_normal(3)
        pose[2] = wrap_angle(pose[2])
        self.count += 1
        return pose, self.cov

    def describe(self) -> dict:
        return {"source": "simulated motion capture", "rate_hz": self.rate_hz, "std": self.std.tolist()}
