"""Run-time torque limiting between the controller and the plant (a safety layer).

Every command passes through ``TorqueLimiter.apply``: torques beyond the motor limits
(``config/robot.yaml``) are clamped, and every saturation episode — consecutive ticks
with a motor clamped — is recorded with its start, end, motor and the largest torque
requested. Nothing is clamped silently: ``episodes`` is part of every run's summary and an
optional ``on_saturation`` callback fires when an episode starts.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from otbot_hw.motors import MOTORS, MotorLimits


@dataclass
class SaturationEpisode:
    """Motor ``motor`` clamped from t_start to t_end (s); ``peak_request`` the largest |u| asked (N m)."""

    motor: str
    t_start: float
    t_end: float
    peak_request: float
    limit: float
    ticks: int = 1

    def to_dict(self) -> dict:
        return {"motor": self.motor, "t_start": self.t_start, "t_end": self.t_end,
                "peak_request_Nm": self.peak_request, "limit_Nm": self.limit, "ticks": self.ticks}


class TorqueLimiter:
    """Clamp commands to ``limits`` and report every saturation episode."""

    def __init__(self, limits: MotorLimits, on_saturation: Callable[[SaturationEpisode], None] | None = None):
        self.limits = limits
        self._max = np.asarray(limits.max_torque, dtype=float)
        self._maxl = self._max.tolist()
        self.on_saturation = on_saturation
        self.episodes: list[SaturationEpisode] = []
        self._open: list[SaturationEpisode | None] = [None, None, None]
        self.saturated_ticks = 0

    def apply(self, u: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(torques within the limits (3,) N m, mask (3,) of the clamped motors) for the command at t (s)."""
        u = np.asarray(u, dtype=float)
        ul = u.tolist()
        if not all(map(math.isfinite, ul)):
            raise ValueError(f"limiter: non-finite torque command {u} at t = {t:.4f} s")
        m = self._maxl
        if (abs(ul[0]) <= m[0] and abs(ul[1]) <= m[1] and abs(ul[2]) <= m[2]
                and self._open[0] is None and self._open[1] is None and self._open[2] is None):
            return u, np.zeros(3, bool)  # the common case, on plain floats (runs every control cycle)
        mask = np.abs(u) > self._max
        out = np.clip(u, -self._max, self._max)
        if mask.any():
            self.saturated_ticks += 1
        for i in range(3):
            ep = self._open[i]
            if mask[i]:
                if ep is None:
                    ep = SaturationEpisode(MOTORS[i], float(t), float(t), float(abs(u[i])), float(self._max[i]))
                    self._open[i] = ep
                    self.episodes.append(ep)
                    if self.on_saturation is not None:
                        self.on_saturation(ep)
                else:
                    ep.t_end = float(t)
                    ep.ticks += 1
                    ep.peak_request = max(ep.peak_request, float(abs(u[i])))
            elif ep is not None:
                self._open[i] = None
        return out, mask

    def report(self) -> list[dict]:
        return [e.to_dict() for e in self.episodes]
