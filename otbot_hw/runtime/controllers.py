"""Controllers the loop runner drives: one small protocol, swappable between cycles.

The runner asks, once per cycle, for the command to hold from robot time ``t`` on
(``Controller.update(t, feedback, snapshot) -> ControlStep``). Behind a ``Robot`` that instant is
one period after the sample the feedback describes (``Feedback.t = t - period``): the command
computed now acts from the next sample, while ``Feedback.u_held`` (already written) acts until
then. Before the first sample the runner asks with ``feedback=None`` (the command held from t_0).

* ``TrackingController``: the computed-torque law (paper §5) tracking a ``DesiredTrajectory``;
  the reference starts (its time 0) at the first command computed from feedback, and the law is
  evaluated on the state predicted at the instant the command takes effect
  (``otbot_hw.control.prediction``), so the sample delay costs nothing with a good model.
* ``OpenLoopTorques``: a torque sequence held from given times (``otbot run``, identification
  experiments); no feedback needed.
* ``TwistReference``: an online reference for ``TrackingController`` that follows a commanded
  platform twist within acceleration limits (the daemon's velocity mode).
* ``PayloadAdapter`` (``runtime.payload_adapter``): online payload adaptation attached to a law
  (``law.adapter``): every ``TrackingController`` on that law feeds it and the law uses its estimate
  once confident, blended in without a torque step; an estimate outside the physical bounds restores
  the file's values and latches a fault.

A controller keeps no state the runner must know about, so the runner (the daemon) may replace it
between two cycles; a new tracking controller starts its reference at the next command (bumpless
when the reference starts where the robot is).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from otbot_hw.control.computed_torque import ComputedTorqueController, TaskState
from otbot_hw.control.prediction import TaskStatePredictor
from otbot_hw.control.trajectories import DesiredTrajectory
from otbot_hw.robot import Snapshot


@dataclass(slots=True)
class Reference:
    """Desired motion at one instant: p_d (m, m, rad), p_dot_d (m/s, m/s, rad/s), p_ddot_d (m/s^2, rad/s^2)."""

    p: np.ndarray
    pd: np.ndarray
    pdd: np.ndarray


@dataclass(slots=True)
class ControlStep:
    """One controller output: torques u (3,) N m to hold from the asked instant on, the reference it
    tracks there (None for open loop), and the law's parts u_traj, u_corr (N m, None if not a CTC)."""

    u: np.ndarray
    reference: Reference | None = None
    u_traj: np.ndarray | None = None
    u_corr: np.ndarray | None = None


@dataclass(slots=True)
class Feedback:
    """What the controller is told each cycle: the (estimated) task state at robot time t (s), the
    command u_held (3,) N m already acting on [t, t + period), the loop period (s)."""

    t: float
    state: TaskState
    u_held: np.ndarray
    period: float


class Controller(Protocol):
    """Anything that turns feedback into joint torques."""

    def update(self, t: float, feedback: Feedback | None, snapshot: Snapshot | None) -> ControlStep:
        """Command (3,) N m to hold from robot time t (s); ``feedback`` None before the first sample."""


class ReferenceSampler:
    """p_d, p_dot_d, p_ddot_d of a ``DesiredTrajectory`` on the grid tau = i * period, sampled in
    blocks (one vectorized call per ``block`` samples instead of one per cycle)."""

    def __init__(self, reference: DesiredTrajectory, period: float, block: int = 2000):
        self.reference = reference
        self.period = float(period)
        self.block = int(block)
        self._start = None
        self._P = self._PD = self._PDD = None

    def at_index(self, i: int) -> Reference:
        if self._start is None or not self._start <= i < self._start + self.block:
            self._start = i
            tau = (i + np.arange(self.block)) * self.period
            self._P, self._PD, self._PDD = (np.ascontiguousarray(a) for a in self.reference.sample(tau))
        j = i - self._start
        return Reference(self._P[j], self._PD[j], self._PDD[j])

    def at(self, tau: float) -> Reference:
        """The reference at any time tau (s): on the grid from the blocks, elsewhere sampled directly."""
        i = round(tau / self.period)
        if abs(i * self.period - tau) < 1e-9 * max(1.0, abs(tau)) and i >= 0:
            return self.at_index(i)
        P, PD, PDD = self.reference.sample(np.array([tau]))
        return Reference(np.ascontiguousarray(P[0]), np.ascontiguousarray(PD[0]), np.ascontiguousarray(PDD[0]))


class TwistReference:
    """An online reference that follows a commanded platform twist (x_dot, y_dot m/s, alpha_dot
    rad/s; ground frame), for ``TrackingController`` (anything with ``at(tau) -> Reference`` is a
    reference source). Starts at pose ``p0`` moving at ``v0``; ``command(v)`` sets the twist to
    reach. Asked at increasing times tau (s, reference time), it integrates exactly (piecewise
    constant acceleration, so p_d, p_dot_d, p_ddot_d are consistent) and picks for the next
    ``period`` the acceleration that approaches the commanded twist within ``max_acceleration``
    (m/s^2, of |(x_dd, y_dd)|, the change kept along one direction) and
    ``max_angular_acceleration`` (rad/s^2). ``p``, ``v``: the state at the last asked time."""

    duration = math.inf

    def __init__(self, p0, v0, period: float, max_acceleration: float, max_angular_acceleration: float):
        self.p = np.asarray(p0, dtype=float).reshape(3).copy()
        self.v = np.asarray(v0, dtype=float).reshape(3).copy()
        self.a = np.zeros(3)
        self.period = float(period)
        self.max_acceleration = float(max_acceleration)
        self.max_angular_acceleration = float(max_angular_acceleration)
        self.target = self.v.copy()
        self.tau = 0.0

    def command(self, twist) -> None:
        v = np.asarray(twist, dtype=float).reshape(3)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"twist must be finite, got {v.tolist()}")
        self.target = v.copy()

    def at(self, tau: float) -> Reference:
        dt = float(tau) - self.tau
        if dt < 0:  # runs forward only: an earlier time gets the current state
            return Reference(self.p.copy(), self.v.copy(), self.a.copy())
        if dt > 0:
            self.p = self.p + self.v * dt + 0.5 * self.a * dt * dt
            self.v = self.v + self.a * dt
            self.tau = float(tau)
        h = self.period
        dv = self.target - self.v
        a = np.empty(3)
        lin = math.hypot(dv[0], dv[1])
        scale = min(1.0, self.max_acceleration * h / lin) if lin > 0 else 0.0
        a[:2] = dv[:2] * scale / h
        a[2] = max(-self.max_angular_acceleration, min(self.max_angular_acceleration, dv[2] / h))
        self.a = a
        return Reference(self.p.copy(), self.v.copy(), a.copy())

    def at_rest(self, tol: float = 1e-9) -> bool:
        return bool(np.all(np.abs(self.v) <= tol) and np.all(np.abs(self.target) <= tol))


class TrackingController:
    """Computed-torque tracking of ``reference`` with ``law``: a ``DesiredTrajectory`` (sampled in
    blocks) or a reference source with ``at(tau) -> Reference`` (e.g. ``TwistReference``), tau the
    reference's own time (s, 0 at ``origin``).

    ``period`` s: the loop period; ``predict``: evaluate the law on the state predicted at the
    instant the command takes effect (default) or, without, on the fed-back state (one period
    late). ``origin``: robot time (s) where the reference starts; default: the instant of the first
    command computed from feedback. A daemon that swaps controllers passes the time of the acting
    reference it takes over, so the new reference continues it without a jump."""

    def __init__(self, law: ComputedTorqueController, reference, period: float,
                 predict: bool = True, origin: float | None = None):
        self.law = law
        self.reference = reference
        self.period = float(period)
        self.sampler = reference if not hasattr(reference, "sample") else ReferenceSampler(reference, period)
        self.predictor = TaskStatePredictor(law.model, period) if predict else None
        if self.predictor is not None and getattr(law, "adapter", None) is not None:
            self.predictor._prm = law.prm  # shared: the payload adapter changes the law's parameters in place
        self.origin = origin

    def _ref(self, t: float) -> Reference:
        return self.sampler.at(t - self.origin)

    def update(self, t: float, feedback: Feedback | None, snapshot: Snapshot | None) -> ControlStep:
        if feedback is None:  # before the first sample: nothing known, hold zero torque
            ref = self.sampler.at(-self.period) if self.origin is None else self._ref(t)
            return ControlStep(np.zeros(3), ref)
        if self.origin is None:
            self.origin = float(t)
        adapter = getattr(self.law, "adapter", None)
        if adapter is not None:
            adapter.observe(feedback)
        ref = self._ref(t)
        s = feedback.state
        p, pd, phi = s.p, s.p_dot, s.phi_p
        if self.predictor is not None:
            h = t - feedback.t
            p, pd, phi = self.predictor.predict(p, pd, phi, feedback.u_held,
                                                None if abs(h - self.period) < 1e-12 else h)
        out = self.law.update_fast(p, pd, float(phi), ref.p, ref.pd, ref.pdd)
        return ControlStep(out[0].copy(), ref, out[1].copy(), out[2].copy())

    def finished(self, t: float) -> bool:
        """Whether the reference has reached its end (rest) by robot time t (s)."""
        return self.origin is not None and t - self.origin >= getattr(self.reference, "duration", math.inf)


class OpenLoopTorques:
    """Torques (N, 3) N m, row k held from ``times[k]`` s after the first command (default: one row per
    ``period``, so row k is held on sample k); the last row holds after the end."""

    def __init__(self, torques, period: float | None = None, times=None):
        self.torques = np.asarray(torques, dtype=float).reshape(-1, 3)
        if not len(self.torques):
            raise ValueError("an open-loop torque sequence needs at least one row")
        if not np.all(np.isfinite(self.torques)):
            raise ValueError("open-loop torques contain NaN or inf")
        if times is None:
            if period is None:
                raise ValueError("give the period or the times of the torque rows")
            times = np.arange(len(self.torques)) * float(period)
        self.times = np.asarray(times, dtype=float).reshape(-1)
        if len(self.times) != len(self.torques) or np.any(np.diff(self.times) <= 0):
            raise ValueError("torque times must be increasing, one per row")
        self.origin: float | None = None

    def update(self, t: float, feedback: Feedback | None, snapshot: Snapshot | None) -> ControlStep:
        if self.origin is None:
            self.origin = float(t)
        k = int(np.searchsorted(self.times, t - self.origin + 1e-9, side="right")) - 1
        return ControlStep(self.torques[min(max(k, 0), len(self.torques) - 1)].copy())
