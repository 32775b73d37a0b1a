"""Interval arithmetic on arrays (Jaulin et al. 2001), enough to bound the task-space model.

An ``Interval`` holds elementwise bounds ``lo <= hi`` (numpy arrays, e.g. one entry per time
sample). It supports +, -, * (with intervals or numbers), division by a number, and
``sin``/``cos`` as methods, so numpy object arrays of intervals pass through the model's
pure functions (``np.sin`` on an object array calls ``.sin()``) and give the natural
interval extension: a guaranteed enclosure of the function over the box (up to
floating-point rounding, which is not directed here — negligible at these magnitudes).
"""
from __future__ import annotations

import math

import numpy as np

_TWO_PI = 2.0 * math.pi


class Interval:
    __slots__ = ("lo", "hi")

    def __init__(self, lo, hi=None):
        lo = np.asarray(lo, dtype=float)
        hi = lo if hi is None else np.asarray(hi, dtype=float)
        if np.any(lo > hi):
            raise ValueError("interval with lo > hi")
        self.lo, self.hi = lo, hi

    @classmethod
    def around(cls, center, radius) -> "Interval":
        c, r = np.asarray(center, float), np.abs(np.asarray(radius, float))
        return cls(c - r, c + r)

    def __add__(self, o):
        if isinstance(o, np.ndarray) and o.dtype == object:
            return NotImplemented
        if isinstance(o, Interval):
            return Interval(self.lo + o.lo, self.hi + o.hi)
        return Interval(self.lo + o, self.hi + o)

    __radd__ = __add__

    def __neg__(self):
        return Interval(-self.hi, -self.lo)

    def __sub__(self, o):
        if isinstance(o, np.ndarray) and o.dtype == object:
            return NotImplemented
        if isinstance(o, Interval):
            return Interval(self.lo - o.hi, self.hi - o.lo)
        return Interval(self.lo - o, self.hi - o)

    def __rsub__(self, o):
        return (-self) + o

    def __mul__(self, o):
        if isinstance(o, np.ndarray) and o.dtype == object:
            return NotImplemented
        if isinstance(o, Interval):
            c = np.stack([self.lo * o.lo, self.lo * o.hi, self.hi * o.lo, self.hi * o.hi])
            return Interval(c.min(axis=0), c.max(axis=0))
        a, b = self.lo * o, self.hi * o
        return Interval(np.minimum(a, b), np.maximum(a, b))

    __rmul__ = __mul__

    def __truediv__(self, o):
        if isinstance(o, Interval):
            raise TypeError("division by an interval is not supported")
        return self * (1.0 / o)

    def sin(self) -> "Interval":
        lo, hi = self.lo, self.hi
        slo, shi = np.sin(lo), np.sin(hi)
        out_lo, out_hi = np.minimum(slo, shi), np.maximum(slo, shi)
        wide = (hi - lo) >= _TWO_PI
        has_max = wide | (np.ceil((lo - math.pi / 2) / _TWO_PI) <= np.floor((hi - math.pi / 2) / _TWO_PI))
        has_min = wide | (np.ceil((lo + math.pi / 2) / _TWO_PI) <= np.floor((hi + math.pi / 2) / _TWO_PI))
        return Interval(np.where(has_min, -1.0, out_lo), np.where(has_max, 1.0, out_hi))

    def cos(self) -> "Interval":
        return (self + math.pi / 2).sin()

    def contains(self, v, tol: float = 0.0) -> np.ndarray:
        v = np.asarray(v, float)
        return (v >= self.lo - tol) & (v <= self.hi + tol)

    def __repr__(self):
        return f"Interval({self.lo!r}, {self.hi!r})"


def as_box(center: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Object array of intervals: center (..., n) +- radius (n,) -> (n,) intervals over the leading axis."""
    center = np.asarray(center, float)
    radius = np.broadcast_to(np.asarray(radius, float), center.shape[-1:])
    out = np.empty(center.shape[-1], dtype=object)
    for i in range(center.shape[-1]):
        out[i] = Interval.around(center[..., i], radius[i])
    return out


def point(values: np.ndarray) -> np.ndarray:
    """Object array of degenerate intervals from values (..., n)."""
    return as_box(values, np.zeros(np.asarray(values).shape[-1]))


def bounds(arr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) arrays (..., n) from an object array (n,) of intervals or numbers."""
    lo = [a.lo if isinstance(a, Interval) else np.asarray(a, float) for a in arr]
    hi = [a.hi if isinstance(a, Interval) else np.asarray(a, float) for a in arr]
    return np.stack(np.broadcast_arrays(*lo), axis=-1), np.stack(np.broadcast_arrays(*hi), axis=-1)
