"""Bench fixtures: the dynamics when the chassis is held fixed.

``floor``: the robot on the ground, the full model. ``stand``: the robot lifted
on a stand, chassis held, wheels spinning freely. ``locked``: both wheels locked
on the ground, so the chassis cannot move. In the last two the platform turns
about the pivot P with the inertia I_p + m_p |PF|^2 (Steiner), alpha follows
phi_p, and the wheels obey I_a phi_dd = tau - b_w phi_d on the stand.
"""
from __future__ import annotations

import numpy as np

from otbot_hw.params import OtbotParams

FIXTURES = ("floor", "stand", "locked")


def fixture_code(name: str) -> int:
    """Integer code used by the compiled model (0 floor, 1 stand, 2 locked)."""
    try:
        return FIXTURES.index(name)
    except ValueError:
        raise ValueError(f"unknown fixture '{name}' (known: {', '.join(FIXTURES)})") from None


def held_chassis_accelerations(qd: np.ndarray, u: np.ndarray, p: OtbotParams, fixture: str,
                               gen: np.ndarray | None = None) -> np.ndarray:
    """q_ddot (6,) for the ``stand`` or ``locked`` fixture; gen: extra generalized force (6,)."""
    g = np.zeros(6) if gen is None else gen
    out = np.zeros(6)
    ipp = p.I_p + p.m_p * (p.x_F ** 2 + p.y_F ** 2)
    out[5] = (u[2] + g[5] - p.b_p * qd[5]) / ipp
    out[2] = out[5]
    if fixture == "stand":
        out[3] = (u[0] + g[3] - p.b_w * qd[3]) / p.I_a
        out[4] = (u[1] + g[4] - p.b_w * qd[4]) / p.I_a
    elif fixture != "locked":
        raise ValueError(f"held_chassis_accelerations: fixture must be 'stand' or 'locked', got {fixture!r}")
    return out
