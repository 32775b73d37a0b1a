"""Standstill detection for the pose EKF's zero-velocity update (``zupt``).

The robot stands still when no joint moved more than ``standstill_angle`` (rad) for
``standstill_window`` (s) and the gyro agrees (its z rate less the estimated bias within 5 sigma of
zero). The update then measures twist = 0 with the sigma that window allows (standstill_angle r /
window for the velocities, standstill_angle / window for the turn rate).
"""
from __future__ import annotations

import math

import numpy as np

from otbot_hw.estimation.config import EstimatorConfig


class StandstillDetector:
    """Joint angles held within ``config.standstill_angle`` for ``config.standstill_window``."""

    def __init__(self, config: EstimatorConfig):
        self.config = config
        self._ref: list[float] | None = None  # the joint angles (rad) the window started at
        self._since = 0.0

    def reset(self, t: float, phi: np.ndarray) -> None:
        """Start watching at t (s) from the joint angles ``phi`` (3,) rad."""
        self._ref = [float(v) for v in phi]
        self._since = float(t)

    def still(self, t: float, phi: np.ndarray, gyro_z: float | None, gyro_bias: float, gyro_bias_var: float) -> bool:
        """Whether the robot stands still at t (s): joints ``phi`` (3,) rad; the newest gyro z rate
        (rad/s, None: no IMU yet) with the estimated bias (rad/s) and its variance (rad^2/s^2)."""
        cfg = self.config
        ref = self._ref
        p0, p1, p2 = phi.tolist() if isinstance(phi, np.ndarray) else phi  # floats: numpy scalars are slow
        if max(abs(p0 - ref[0]), abs(p1 - ref[1]), abs(p2 - ref[2])) > cfg.standstill_angle:
            self._ref = [p0, p1, p2]
            self._since = t
            return False
        if t - self._since < cfg.standstill_window - 1e-9:
            return False
        if gyro_z is not None and abs(gyro_z - gyro_bias) > 5.0 * math.sqrt(cfg.gyro_sigma ** 2 + gyro_bias_var):
            return False
        return True
