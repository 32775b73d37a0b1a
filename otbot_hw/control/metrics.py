"""Tracking-error figures of a closed-loop run: maxima, RMS, torque peaks and event settle times.

An *event* (a corner of the reference, a force on the pivot) starts at ``t``; its peak is the
largest error norm between ``t`` and the next event (or the end of the run). Its settle time
is the time from ``settle_from`` (the corner itself, or the end of the force) until the
position-error norm |(e_x, e_y)| and the velocity-error norm |(e_x_dot, e_y_dot)| both stay
below ``fraction`` (2 %) of their peaks for the rest of that window. ``None`` means they did
not within the window.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from otbot_hw.motors import MOTORS, MotorLimits

ERROR_NAMES = ("x", "y", "alpha")
RATE_NAMES = ("x_dot", "y_dot", "alpha_dot")
SETTLE_FRACTION = 0.02


@dataclass(frozen=True)
class Event:
    """Something the controller must recover from: ``kind`` at ``t`` (s), settle measured from ``settle_from``."""

    t: float
    kind: str
    settle_from: float


def error_summary(e_p: np.ndarray, e_v: np.ndarray) -> dict:
    """``max_abs_error`` and ``rms_error`` maps for x, y, alpha (m, rad) and the rates (m/s, rad/s)."""
    out = {"max_abs_error": {}, "rms_error": {}}
    for i, (n, nd) in enumerate(zip(ERROR_NAMES, RATE_NAMES)):
        out["max_abs_error"][n] = float(np.max(np.abs(e_p[:, i])))
        out["max_abs_error"][nd] = float(np.max(np.abs(e_v[:, i])))
        out["rms_error"][n] = float(np.sqrt(np.mean(e_p[:, i] ** 2)))
        out["rms_error"][nd] = float(np.sqrt(np.mean(e_v[:, i] ** 2)))
    return out


def peak_torques(u: np.ndarray, limits: MotorLimits) -> dict:
    """Per motor: the largest |torque| applied (N m), its limit and the time index of the peak."""
    return {m: {"peak_Nm": float(np.max(np.abs(u[:, i]))), "limit_Nm": float(limits.max_torque[i])}
            for i, m in enumerate(MOTORS)}


def settle_time(t: np.ndarray, err: np.ndarray, t_from: float, t_to: float, fraction: float = SETTLE_FRACTION,
                peak_from: float | None = None) -> tuple[float | None, float]:
    """(seconds after ``t_from`` until |err| stays below fraction * peak up to ``t_to``, peak).

    ``err`` (N,) is a non-negative error signal; the peak is taken over [peak_from, t_to).
    """
    win = (t >= (t_from if peak_from is None else peak_from)) & (t < t_to)
    if not win.any():
        return None, 0.0
    peak = float(np.max(err[win]))
    after = (t >= t_from) & (t < t_to)
    ta, ea = t[after], err[after]
    above = np.flatnonzero(ea > fraction * peak)
    if above.size == 0:
        return 0.0, peak
    last = above[-1]
    if last == len(ea) - 1:
        return None, peak
    return float(ta[last + 1] - t_from), peak


def event_summary(t: np.ndarray, e_p: np.ndarray, e_v: np.ndarray, events: list[Event],
                  fraction: float = SETTLE_FRACTION) -> list[dict]:
    """One dict per event: t, kind, settle_time_s (max of position and velocity), peaks."""
    pos = np.linalg.norm(e_p[:, :2], axis=1)
    vel = np.linalg.norm(e_v[:, :2], axis=1)
    out = []
    ev = sorted(events, key=lambda e: e.t)
    for i, e in enumerate(ev):
        t_to = ev[i + 1].t if i + 1 < len(ev) else t[-1] + 1e-9
        sp, pp = settle_time(t, pos, e.settle_from, t_to, fraction, peak_from=e.t)
        sv, pv = settle_time(t, vel, e.settle_from, t_to, fraction, peak_from=e.t)
        settle = None if sp is None or sv is None else max(sp, sv)
        out.append({"t": e.t, "kind": e.kind, "settle_time_s": settle, "settle_from_s": e.settle_from,
                    "window_s": float(t_to - e.settle_from), "position_settle_s": sp, "velocity_settle_s": sv,
                    "peak_position_error_m": pp, "peak_velocity_error_mps": pv})
    return out


def fraction_within(e_p: np.ndarray, e_v: np.ndarray) -> dict:
    """Share of samples with |(e_x, e_y)| < 1 mm, |(e_x_dot, e_y_dot)| < 1 cm/s, |e_alpha| < 1e-3 rad
    and |e_alpha_dot| < 5e-3 rad/s (the paper's figures for the planned trajectory)."""
    return {"position_below_1mm": float(np.mean(np.hypot(e_p[:, 0], e_p[:, 1]) < 1e-3)),
            "velocity_below_1cm_per_s": float(np.mean(np.hypot(e_v[:, 0], e_v[:, 1]) < 1e-2)),
            "alpha_below_1e-3rad": float(np.mean(np.abs(e_p[:, 2]) < 1e-3)),
            "alpha_rate_below_5e-3rad_per_s": float(np.mean(np.abs(e_v[:, 2]) < 5e-3))}
