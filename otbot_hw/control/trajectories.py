"""Desired trajectories p_d(t) = (x_d, y_d, alpha_d) (m, m, rad; ground frame) with their
first and second time derivatives, for the tracking controller.

Every trajectory implements ``sample(t) -> (P, PD, PDD)`` on an array of times (s), each
(N, 3), and ``duration`` (s). Before t = 0 and after ``duration`` the trajectory rests at
its first / last point.

* ``PolylineTrajectory``  — straight segments at constant speed (velocity jumps at the
  corners, as in the paper's corridor); with ``smoothing`` > 0 the velocity profile is
  convolved with a compact biweight kernel, giving a rest-to-rest motion with continuous
  velocity and acceleration that rounds each corner within ``smoothing`` seconds.
* ``PathTrajectory``      — a tangent-continuous path of ``Line`` and ``Arc`` sections
  traversed at constant speed after a smooth (quintic) rest-to-rest speed ramp; see
  ``figure_eight``.
* ``SampledTrajectory``   (``sampled_trajectory``) — samples loaded from CSV (format below), interpolated by a
  C^2 cubic spline or, when velocities are given, a cubic Hermite spline, so p, p_dot
  and p_dd are the exact derivatives of one interpolant (mutually consistent).
* ``StopTrajectory``      — from a pose moving at a given velocity to rest on a straight
  line, velocity decaying smoothly (zero acceleration at both ends) within acceleration
  limits; with zero velocity a hold of the pose. The daemon's ``hold``/``stop``/deadman.
* ``PlacedTrajectory``    — any trajectory moved rigidly (turned about its start, then
  shifted) so it starts at a given pose: a scenario run from where the robot stands.

Sampled trajectories and their CSV files: ``sampled_trajectory``.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Sequence

import numpy as np


class TrajectoryError(ValueError):
    """A trajectory definition or file is unusable; the message names what and where."""


class DesiredTrajectory(ABC):
    """p_d(t) with derivatives; ``duration`` in s."""

    duration: float

    @abstractmethod
    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(P, PD, PDD), each (len(t), 3): position (m, m, rad), velocity, acceleration."""

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        P, PD, PDD = self.sample(np.array([float(t)]))
        return P[0], PD[0], PDD[0]


# ---------------------------------------------------------------- stop and hold
class StopTrajectory(DesiredTrajectory):
    """From pose ``p0`` (m, m, rad) moving at ``v0`` (m/s, m/s, rad/s) to rest, on the straight line
    along v0: p_dot(t) = v0 (1 - 3 s^2 + 2 s^3), s = t / T, so the acceleration starts and ends at
    zero and peaks at 1.5 |v0| / T. T is the shortest time keeping the peak within
    ``max_acceleration`` (m/s^2, of |(x_dd, y_dd)|) and ``max_angular_acceleration`` (rad/s^2);
    the rest pose is p0 + v0 T / 2. With v0 = 0 (T = 0) it holds p0. Before t = 0 it moves at v0
    (the motion it takes over); after T it rests."""

    def __init__(self, p0, v0=(0.0, 0.0, 0.0), max_acceleration: float = 0.5,
                 max_angular_acceleration: float = 1.0):
        self.p0 = np.asarray(p0, dtype=float).reshape(3).copy()
        self.v0 = np.asarray(v0, dtype=float).reshape(3).copy()
        if not (np.all(np.isfinite(self.p0)) and np.all(np.isfinite(self.v0))):
            raise TrajectoryError(f"stop trajectory from a non-finite state: p0 {self.p0.tolist()}, "
                                  f"v0 {self.v0.tolist()}")
        if not (max_acceleration > 0 and max_angular_acceleration > 0):
            raise TrajectoryError("stop trajectory: acceleration limits must be > 0")
        self.stop_time = 1.5 * max(math.hypot(self.v0[0], self.v0[1]) / max_acceleration,
                                   abs(self.v0[2]) / max_angular_acceleration)
        self.duration = self.stop_time
        self.rest = self.p0 + 0.5 * self.v0 * self.stop_time

    def sample(self, t):
        t = np.atleast_1d(np.asarray(t, dtype=float))[:, None]
        T = self.stop_time
        if T == 0.0:
            n = len(t)
            return np.tile(self.p0, (n, 1)), np.zeros((n, 3)), np.zeros((n, 3))
        s = np.clip(t / T, 0.0, 1.0)
        before = t < 0
        P = np.where(before, self.p0 + self.v0 * t, self.p0 + self.v0 * T * (s - s ** 3 + 0.5 * s ** 4))
        PD = np.where(before, self.v0, self.v0 * (1.0 - 3.0 * s ** 2 + 2.0 * s ** 3))
        PDD = np.where(before | (t > T), 0.0, self.v0 * (6.0 * s ** 2 - 6.0 * s) / T)
        return P, PD, PDD


class PlacedTrajectory(DesiredTrajectory):
    """``reference`` moved rigidly so that its start pose p_d(0) becomes ``start`` (x, y m, alpha
    rad): turned by start_alpha - alpha_d(0) about its start point, then shifted. Velocities and
    accelerations turn with it; alpha keeps its own changes. The dynamics are the same in any
    ground frame (a level floor), so the robot tracks the placed trajectory as it would the
    original from its start."""

    def __init__(self, reference: DesiredTrajectory, start):
        self.reference = reference
        self.start = np.asarray(start, dtype=float).reshape(3).copy()
        p0 = reference.sample(np.zeros(1))[0][0]
        self.origin = p0
        self.turn = float(self.start[2] - p0[2])
        c, s = math.cos(self.turn), math.sin(self.turn)
        self._R = np.array([[c, -s], [s, c]])
        self.duration = reference.duration
        for attr in ("corner_times", "end"):
            if hasattr(reference, attr):
                setattr(self, attr, getattr(reference, attr))

    def _turn(self, V):
        out = V.copy()
        out[:, :2] = V[:, :2] @ self._R.T
        return out

    def sample(self, t):
        P, PD, PDD = self.reference.sample(t)
        Q = self._turn(P - self.origin)
        Q[:, :2] += self.start[:2]
        Q[:, 2] = P[:, 2] + self.turn
        return Q, self._turn(PD), self._turn(PDD)


# ---------------------------------------------------------------- polylines
def _kernel_terms(s: np.ndarray, w: float):
    """Biweight kernel K (integral 1, support [-w, w]), its CDF and the ramp R = ramp * K.

    Returns (R, R', R'') at s = t - t_jump; R(s) = 0 for s <= -w and s for s >= w.
    """
    u = np.clip(s / w, -1.0, 1.0)
    K = 15.0 / 16.0 * (1 - u * u) ** 2 / w
    F = 15.0 / 16.0 * (u - 2 * u ** 3 / 3 + u ** 5 / 5) + 0.5
    G = 15.0 / 16.0 * (u ** 2 / 2 - u ** 4 / 6 + u ** 6 / 30) + u / 2 + 0.15625
    R = np.where(s >= w, s, w * G)
    return R, F, np.where(np.abs(s) < w, K, 0.0)


class PolylineTrajectory(DesiredTrajectory):
    """Pivot along waypoints (n, 2) m at constant ``speed`` (m/s), alpha fixed (rad).

    ``smoothing`` = 0: the reference starts at full speed at t = 0 (the robot starts at rest)
    and stops dead at the last waypoint. ``smoothing`` = w > 0: rest-to-rest, the piecewise
    constant velocity convolved with a biweight kernel of half-width w (s): continuous
    velocity and acceleration, the same cruise speed, corners rounded, motion starting at
    t = 0 and ending at rest exactly on the last waypoint at t = travel + 2 w.
    ``hold`` (s) is added at the end (rest at the last waypoint).
    """

    def __init__(self, waypoints: Sequence[Sequence[float]], speed: float, alpha: float = 0.0,
                 hold: float = 0.0, smoothing: float = 0.0):
        W = np.asarray(waypoints, dtype=float)
        if W.ndim != 2 or W.shape[1] != 2 or len(W) < 2 or not np.all(np.isfinite(W)):
            raise TrajectoryError(f"waypoints must be >= 2 finite (x, y) pairs, got shape {W.shape}")
        if not (speed > 0 and math.isfinite(speed)):
            raise TrajectoryError(f"speed must be > 0 m/s, got {speed}")
        if smoothing < 0 or hold < 0:
            raise TrajectoryError("smoothing and hold must be >= 0 s")
        seg = np.diff(W, axis=0)
        lengths = np.linalg.norm(seg, axis=1)
        if np.any(lengths <= 0):
            raise TrajectoryError(f"waypoint {int(np.argmin(lengths)) + 1} repeats the previous one")
        self.waypoints, self.speed, self.alpha, self.smoothing = W, float(speed), float(alpha), float(smoothing)
        self.velocities = seg / lengths[:, None] * speed            # (n-1, 2)
        self.corner_times = np.concatenate([[0.0], np.cumsum(lengths / speed)]) + smoothing
        self.travel_time = float(self.corner_times[-1] - smoothing)
        self.duration = self.travel_time + 2 * smoothing + hold
        v = np.vstack([[0.0, 0.0], self.velocities, [0.0, 0.0]])
        self._jumps = np.diff(v, axis=0)                             # velocity jump at each corner_time

    def sample(self, t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        P = np.zeros((len(t), 3))
        PD = np.zeros((len(t), 3))
        PDD = np.zeros((len(t), 3))
        P[:, :2] = self.waypoints[0]
        P[:, 2] = self.alpha
        if self.smoothing == 0.0:
            tt = np.clip(t, 0.0, self.travel_time)
            idx = np.clip(np.searchsorted(self.corner_times, tt, side="right") - 1, 0, len(self.velocities) - 1)
            P[:, :2] = self.waypoints[idx] + self.velocities[idx] * (tt - self.corner_times[idx])[:, None]
            moving = (t >= 0) & (t < self.travel_time)
            PD[moving, :2] = self.velocities[idx[moving]]
            return P, PD, PDD
        for tj, dv in zip(self.corner_times, self._jumps):
            R, R1, R2 = _kernel_terms(t - tj, self.smoothing)
            P[:, :2] += R[:, None] * dv
            PD[:, :2] += R1[:, None] * dv
            PDD[:, :2] += R2[:, None] * dv
        return P, PD, PDD


def corridor(speed: float = 0.6, hold: float = 5.0, smoothing: float = 0.0) -> PolylineTrajectory:
    """The paper's narrow corridor: five 3 m segments with 90 deg turns from (0, 0) to (9, 0) m, alpha = 0."""
    pts = [(0, 0), (3, 0), (3, 3), (6, 3), (6, 0), (9, 0)]
    return PolylineTrajectory(pts, speed, alpha=0.0, hold=hold, smoothing=smoothing)


# ---------------------------------------------------------------- lines and arcs
@dataclass(frozen=True)
class Line:
    """Straight section from ``start`` to ``end`` (m)."""

    start: tuple[float, float]
    end: tuple[float, float]

    @property
    def length(self) -> float:
        return float(np.hypot(self.end[0] - self.start[0], self.end[1] - self.start[1]))

    def geometry(self, s):
        """Point, unit tangent and curvature vector d2/ds2 at arc lengths s (m) in [0, length]."""
        a, b = np.asarray(self.start, float), np.asarray(self.end, float)
        d = (b - a) / self.length
        return a + s[:, None] * d, np.tile(d, (len(s), 1)), np.zeros((len(s), 2))


@dataclass(frozen=True)
class Arc:
    """Circular section about ``center`` (m), ``radius`` (m), from polar angle ``start`` (rad),
    turning ``sweep`` rad (positive = counterclockwise)."""

    center: tuple[float, float]
    radius: float
    start: float
    sweep: float

    @property
    def length(self) -> float:
        return abs(self.sweep) * self.radius

    def geometry(self, s):
        sgn = math.copysign(1.0, self.sweep)
        ang = self.start + sgn * s / self.radius
        c, sn = np.cos(ang), np.sin(ang)
        pos = np.asarray(self.center, float) + self.radius * np.column_stack([c, sn])
        tan = sgn * np.column_stack([-sn, c])
        curv = -np.column_stack([c, sn]) / self.radius
        return pos, tan, curv


def _quintic_ramp(tau):
    """Smooth 0 -> 1 speed ramp on tau in [0, 1] (C^2) and its integral and derivative."""
    tau = np.clip(tau, 0.0, 1.0)
    S = 10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5
    I = 2.5 * tau ** 4 - 3 * tau ** 5 + tau ** 6
    D = 30 * tau ** 2 - 60 * tau ** 3 + 30 * tau ** 4
    return S, I, D


class PathTrajectory(DesiredTrajectory):
    """Sections traversed back to back in ``duration`` s (rest-to-rest), alpha fixed (rad).

    Speed profile: quintic ramp up over ``ramp`` s, cruise, quintic ramp down; the cruise
    speed is set so the path is covered in ``duration``. ``hold`` s of rest are appended.
    """

    def __init__(self, sections: Sequence[Line | Arc], duration: float, ramp: float = 1.5,
                 alpha: float = 0.0, hold: float = 0.0):
        if not sections:
            raise TrajectoryError("a path needs at least one section")
        if not (duration > 2 * ramp and ramp > 0):
            raise TrajectoryError(f"duration {duration} s must exceed twice the ramp {ramp} s")
        self.sections = list(sections)
        for i in range(len(self.sections) - 1):
            a, b = self.sections[i], self.sections[i + 1]
            pa, ta, _ = a.geometry(np.array([a.length]))
            pb, tb, _ = b.geometry(np.array([0.0]))
            if np.hypot(*(pa[0] - pb[0])) > 1e-9 or np.hypot(*(ta[0] - tb[0])) > 1e-6:
                raise TrajectoryError(f"section {i + 1} does not continue section {i} "
                                      "(position and direction must match)")
        self.lengths = np.array([s.length for s in self.sections])
        self.starts = np.concatenate([[0.0], np.cumsum(self.lengths)])
        self.length = float(self.starts[-1])
        self.motion_time, self.ramp, self.alpha = float(duration), float(ramp), float(alpha)
        self.cruise_speed = self.length / (duration - ramp)
        self.duration = self.motion_time + hold

    def _timing(self, t):
        """Arc length s (m), speed (m/s) and its rate (m/s^2) at times t.

        speed = V (S(t/Tr) + S((T - t)/Tr) - 1) with S the quintic ramp, so
        s(t) = V (J(t) + J(T) - J(T - t) - t) where J(x) = integral_0^x S(tau/Tr) dtau.
        """
        V, Tr, T = self.cruise_speed, self.ramp, self.motion_time
        t = np.clip(t, 0.0, T)

        def J(x):
            return Tr * _quintic_ramp(x / Tr)[1] + np.maximum(x - Tr, 0.0)

        S1, _, D1 = _quintic_ramp(t / Tr)
        S2, _, D2 = _quintic_ramp((T - t) / Tr)
        s = V * (J(t) + J(np.array(T)) - J(T - t) - t)
        return s, V * (S1 + S2 - 1), V * (D1 - D2) / Tr

    def sample(self, t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        s, sd, sdd = self._timing(t)
        s = np.clip(s, 0.0, self.length)
        idx = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.sections) - 1)
        P = np.zeros((len(t), 3))
        PD = np.zeros((len(t), 3))
        PDD = np.zeros((len(t), 3))
        P[:, 2] = self.alpha
        for i, sec in enumerate(self.sections):
            m = idx == i
            if not m.any():
                continue
            pos, tan, curv = sec.geometry(np.clip(s[m] - self.starts[i], 0.0, sec.length))
            P[m, :2] = pos
            PD[m, :2] = tan * sd[m, None]
            PDD[m, :2] = curv * (sd[m] ** 2)[:, None] + tan * sdd[m, None]
        return P, PD, PDD


def figure_eight(duration: float = 18.0, radius: float = 1.0, center_distance: float = 2.0,
                 ramp: float = 1.5, hold: float = 0.0) -> PathTrajectory:
    """Figure-8 through the origin: two crossing straights tangent to two circles of ``radius`` (m)
    centred at (+-center_distance, 0) m; right loop clockwise, left loop counterclockwise."""
    R, d = float(radius), float(center_distance)
    if not d > R > 0:
        raise TrajectoryError("figure-8 needs center_distance > radius > 0")
    b = math.asin(R / d)
    k = d * math.cos(b)
    T1 = (k * math.cos(b), k * math.sin(b))
    T2 = (k * math.cos(b), -k * math.sin(b))
    T3 = (-k * math.cos(b), k * math.sin(b))
    T4 = (-k * math.cos(b), -k * math.sin(b))
    sweep = math.pi + 2 * b
    sections = [Line((0.0, 0.0), T1), Arc((d, 0.0), R, math.pi / 2 + b, -sweep), Line(T2, T3),
                Arc((-d, 0.0), R, math.pi / 2 - b, sweep), Line(T4, (0.0, 0.0))]
    return PathTrajectory(sections, duration, ramp=ramp, hold=hold)
