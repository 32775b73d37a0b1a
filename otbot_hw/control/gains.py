"""Computed-torque gains from a stabilization time (paper §5.2).

Per axis p in (x, y, alpha) the closed-loop error obeys e_dd + k_v e_d + k_p e = 0
with real poles s1 = -4 / T_stab and s2 = 10 s1, so that the slow mode has decayed
to e^-4 ~ 1.8 % after T_stab seconds: k_p = s1 s2 (1/s^2), k_v = -(s1 + s2) (1/s).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

AXES = ("x", "y", "alpha")
POLE_RATIO = 10.0  # s2 / s1


@dataclass(frozen=True)
class Gains:
    """Diagonal gains per task axis (x, y, alpha): kp (3,) 1/s^2, kv (3,) 1/s."""

    kp: np.ndarray
    kv: np.ndarray

    def __post_init__(self):
        for name in ("kp", "kv"):
            v = np.asarray(getattr(self, name), dtype=float).reshape(-1)
            if v.shape != (3,) or not np.all(np.isfinite(v)) or np.any(v <= 0):
                raise ValueError(f"gains: {name} must be 3 finite numbers > 0 (x, y, alpha), got {v}")
            object.__setattr__(self, name, v)

    def poles(self) -> np.ndarray:
        """(3, 2) closed-loop error poles per axis (1/s), slow pole first."""
        out = np.empty((3, 2))
        for i in range(3):
            r = np.roots([1.0, self.kv[i], self.kp[i]])
            out[i] = np.sort(r.real)[::-1]
        return out

    def to_dict(self) -> dict:
        return {"kp": dict(zip(AXES, self.kp.tolist())), "kv": dict(zip(AXES, self.kv.tolist()))}


def axis_gains(t_stab: float) -> tuple[float, float]:
    """(k_p, k_v) for one axis from its stabilization time T_stab (s)."""
    if not (isinstance(t_stab, (int, float)) and math.isfinite(t_stab) and t_stab > 0):
        raise ValueError(f"T_stab must be a finite number of seconds > 0, got {t_stab!r}")
    s1 = -4.0 / t_stab
    s2 = POLE_RATIO * s1
    return s1 * s2, -(s1 + s2)


def gains_from_tstab(t_stab: float | Sequence[float] = 3.0) -> Gains:
    """Gains from one T_stab (s) for all axes or three values for (x, y, alpha)."""
    ts = [float(t_stab)] * 3 if np.ndim(t_stab) == 0 else [float(v) for v in t_stab]
    if len(ts) != 3:
        raise ValueError(f"T_stab needs 1 or 3 values (x, y, alpha), got {len(ts)}")
    kk = [axis_gains(v) for v in ts]
    return Gains(kp=np.array([k[0] for k in kk]), kv=np.array([k[1] for k in kk]))
