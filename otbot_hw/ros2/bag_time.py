"""Time for ``otbot import`` (``bag_import``): the checks of a topic's stamps (clock jumps, gaps),
the grid rate, wrapped encoders, and the interpolation error estimate."""
from __future__ import annotations

import math

import numpy as np

from otbot_hw.ros2 import BagError
from otbot_hw.ros2.bag_series import Series


def nominal_rate(step_ns: float) -> float:
    """The rate of a median step (ns), snapped to a whole Hz within 0.1 %."""
    r = 1e9 / step_ns
    return float(round(r)) if abs(r - round(r)) < 1e-3 * r else r


def uniform(stamps: np.ndarray) -> bool:
    d = np.diff(stamps)
    return len(d) > 0 and int(d.max() - d.min()) <= 2


def check_clock(s: Series, use_header: bool) -> None:
    d = np.diff(s.stamps)
    back = np.nonzero(d <= 0)[0]
    if len(back):
        k = int(back[0]) + 1
        what = (f"the stamp goes back by {-d[k - 1] * 1e-9:.6f} s" if d[k - 1] < 0
                else "the stamp repeats the one before")
        raise BagError(f"{s.topic}: clock jump at message {k}: {what} ({len(back)} such step(s)); stamps must "
                       "increase")
    if use_header and len(d):
        dl = np.diff(s.log)
        med = float(np.median(d))
        jump = np.nonzero(np.abs(d - dl) > max(1e9, 10 * med))[0]
        if len(jump):
            k = int(jump[0]) + 1
            raise BagError(f"{s.topic}: clock jump at message {k}: the header stamp moves {d[k - 1] * 1e-9:.3f} s "
                           "while "
                           f"the bag's receive time moves {dl[k - 1] * 1e-9:.3f} s (the sensor clock was reset or "
                           "synchronized mid-run); import the part before or after it (--start/--end)")


def check_gaps(s: Series, grid: np.ndarray, period_ns: float, notices: list[str]) -> None:
    inside = s.stamps[(s.stamps >= grid[0] - 2 * period_ns) & (s.stamps <= grid[-1] + 2 * period_ns)]
    pts = np.concatenate([[grid[0]], inside, [grid[-1]]]) if len(inside) else np.array([grid[0], grid[-1]])
    d = np.diff(np.sort(pts))
    big = np.nonzero(d > 2 * period_ns)[0]
    if len(big):
        k = int(big[0])
        t0 = (np.sort(pts)[k] - grid[0]) * 1e-9
        raise BagError(f"{s.topic}: gap of {d[k] * 1e-9:.3f} s at t = {t0:.3f} s (no message for more than two "
                       f"sample periods; {len(big)} gap(s)): the samples across it would be invented; import the part "
                       "before or after it (--start/--end, s after the first joint state)")
    med = float(np.median(np.diff(s.stamps))) if len(s.stamps) > 1 else period_ns
    dropped = int(np.sum(np.diff(inside) > 1.5 * med)) if len(inside) > 1 else 0
    if dropped:
        notices.append(f"{s.topic}: {dropped} dropped message(s) (steps over 1.5 periods, none over two sample "
                       "periods): interpolated across")


def loo_error(x: np.ndarray, v: np.ndarray) -> tuple[float, float]:
    """(rms, max) over channels of predicting each interior sample from its two neighbours."""
    w = ((x[1:-1] - x[:-2]) / (x[2:] - x[:-2]))[:, None]
    pred = v[:-2] + w * (v[2:] - v[:-2])
    e = pred - v[1:-1]
    e = e[np.isfinite(e)]
    if not len(e):
        return math.nan, math.nan
    return float(np.sqrt(np.mean(e ** 2))), float(np.max(np.abs(e)))


def unwrap_joints(joints: Series, names, vel_from_angles: bool, velocity_field: str, notices: list[str]) -> None:
    """Joint angles that wrap at +-pi made continuous in place (the velocity says which way; without
    velocities the rates are differentiated from the unwrapped angles); BagError when an angle
    jumps and its velocity does not explain it (docs/recording-format.md §3)."""
    t_first = int(joints.stamps[0])
    pos = joints.values["position"]
    unwrapped = pos.copy()
    dts = np.diff(joints.stamps) * 1e-9
    for j, name in enumerate(("right wheel", "left wheel", "pivot")):
        d = np.diff(pos[:, j])
        wraps = np.nonzero(np.abs(d) > math.pi)[0]
        if not len(wraps):
            continue
        uw = np.unwrap(pos[:, j])
        if not vel_from_angles:
            v = joints.values["velocity"][:, j]
            pred = 0.5 * (v[:-1] + v[1:]) * dts
            bad = wraps[np.abs(np.diff(uw)[wraps] - pred[wraps]) > math.pi / 2]
            if len(bad):
                k = int(bad[0]) + 1
                raise BagError(f"{joints.topic}: {names[j]} ({name}) position jumps by {d[k - 1]:.3f} rad at message "
                               f"{k} and its velocity does not say which way it wrapped: not a continuous angle "
                               "(docs/recording-format.md §3)")
        unwrapped[:, j] = uw
        notices.append(f"{names[j]} ({name}) position wraps at +-pi {len(wraps)} time(s) (first at "
                       f"{(joints.stamps[wraps[0] + 1] - t_first) * 1e-9:.3f} s): unwrapped to a continuous angle")
    joints.values["position"] = unwrapped
    if vel_from_angles:
        ts_ = (joints.stamps - t_first) * 1e-9
        joints.values["velocity"] = np.gradient(unwrapped, ts_, axis=0)
        notices.append(f"{joints.topic} has no {velocity_field}: joint rates differentiated from the angles "
                       "(central differences)")
