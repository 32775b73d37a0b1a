"""The one angle wrap of the project (plain Python and numpy; no numba, so light importers such as the
telemetry can use it)."""
from __future__ import annotations

import math

TWO_PI = 2.0 * math.pi


def wrap_angle(a):
    """a wrapped into [-pi, pi) (rad); floats and numpy arrays alike (alpha residuals, errors, telemetry)."""
    return (a + math.pi) % TWO_PI - math.pi
