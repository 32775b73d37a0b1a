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
* ``PayloadAdapter``: online payload adaptation (``otbot_hw.estimation.payload``) attached to a law
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


class PayloadAdapter:
    """Online payload adaptation for the computed-torque ``law`` (attach with ``law.adapter = adapter``).

    Fed by every ``TrackingController`` on the law (hold, velocity, track: ``observe(feedback)``), it runs
    a ``PayloadEstimator`` on the fed-back motion and the torques that caused it. The law keeps the
    parameter file's platform values until an estimate is confident (std below ``AdaptationConfig``'s
    thresholds; I_p needs the platform to turn, else the file's or last confident I_p stays);
    from then on the law's theta follows the estimate through a first-order blend of time constant
    ``ramp`` s, so the torque changes continuously (no step at the switch). Each of m_p, x_F, y_F, I_p is taken
    once its own std is below the threshold (the mass is known long before the centre when the robot
    first drives straight). A detected load change resets the estimator; the law keeps its last
    parameters until the new estimates are confident.

    An estimate that leaves the physical bounds by more than 3 std (mass in (0, ``max_mass``] kg, centre
    within the platform ``radius`` m, I_p > 0) restores the file's values in the law at once and latches:
    ``fault`` holds the reason, ``on_fault(Violation)`` is called (the runner's ``trip``: quick stop), no
    further adaptation until ``reset()``. ``on_event(t, kind, text)`` records what happens (the runner's
    ``event``). Times are robot time (s)."""

    def __init__(self, law: ComputedTorqueController, config, period: float, radius: float | None = None,
                 on_fault=None, on_event=None):
        from otbot_hw.estimation.payload import PayloadEstimator

        self.law = law
        self.file = law.params
        self.config = config
        self.period = float(period)
        self.radius = float(radius if radius is not None else self.file.radius)
        self.on_fault = on_fault
        self.on_event = on_event
        self.estimator = PayloadEstimator(self.file, config, period)
        self.estimator.observe(0.0, 0.0, 0.0, np.zeros(3), np.zeros(3))  # compile before any bus opens
        self.estimator.observe(self.period, 0.0, 0.0, np.zeros(3), np.zeros(3))
        self.reset()

    def reset(self) -> None:
        """Back to the parameter file (law included); clears a latched bounds fault."""
        from otbot_hw.estimation.payload import theta_from_payload

        f = self.file
        self.estimator.reset()
        self.theta_file = theta_from_payload(f.m_p, f.I_p, f.x_F, f.y_F)
        self.theta_law = self.theta_file.copy()
        self.target: np.ndarray | None = None
        self.use = {"m_p": f.m_p, "I_p": f.I_p, "x_F": f.x_F, "y_F": f.y_F}  # what the law is blended towards
        self.active = False
        self.converged_s: float | None = None
        self.switched_s: float | None = None
        self.changes: list[dict] = []
        self.fault: str | None = None
        self._u_last = None
        self._updates = -1
        self._est = self.estimator.estimate()
        self.t = None
        self.law.set_platform(f.m_p, f.I_p, f.x_F, f.y_F)

    @property
    def state(self) -> str:
        """file (the law uses the file's values), adapting (blending to or following the estimate),
        reestimating (after a detected change; the law keeps its last values), fault."""
        if self.fault is not None:
            return "fault"
        if not self.active:
            return "file"
        return "reestimating" if self.changes and self.changes[-1]["reconverged_s"] is None else "adapting"

    def _say(self, t: float, kind: str, text: str) -> None:
        if self.on_event is not None:
            self.on_event(t, kind, text)

    def observe(self, feedback) -> None:
        """One cycle's feedback (``Feedback``: state at feedback.t, u_held acting from then on)."""
        from otbot_hw.estimation.payload import bounds_violation, theta_from_payload

        if self.fault is not None:
            return
        t = float(feedback.t)
        self.t = t
        s = feedback.state
        if self._u_last is not None:
            if self.estimator.observe(t, float(s.p[2]), float(s.phi_p), s.p_dot, self._u_last):
                self.changes.append({"detected_s": t, "reconverged_s": None})
                self._say(t, "adaptation", "payload change detected (residual CUSUM): re-estimating; the law keeps "
                                           "its last parameters until the new estimate is confident")
        # the torque the paper's model sees: the command less what the law added for compensated effects
        # (its last evaluation made the command now held)
        self._u_last = np.array(feedback.u_held, dtype=float) - self.law.compensation
        est = self._est
        synced = False
        if self.estimator.updates != self._updates:
            synced = True
            self._updates = self.estimator.updates
            self._est = est = self.estimator.estimate()
            c = est.confident
            if c["m_p"] or c["x_F"] or c["y_F"]:
                std = np.where([c[n] for n in ("m_p", "I_p", "x_F", "y_F")], est.std, np.inf)
                why = bounds_violation(est.value, std, self.config.max_mass, self.radius)
                if why is not None:
                    self._latch(t, why)
                    return
                for i, n in enumerate(("m_p", "I_p", "x_F", "y_F")):  # each parameter once it is confident
                    if c[n]:
                        self.use[n] = float(est.value[i])
                self.target = theta_from_payload(self.use["m_p"], self.use["I_p"], self.use["x_F"], self.use["y_F"])
                if not self.active:
                    self.active = True
                    self.switched_s = t
                    self._say(t, "adaptation", "the law starts using the estimate (" + ", ".join(
                        n for n in ("m_p", "x_F", "y_F", "I_p") if c[n]) + f"; blend {self.config.ramp:g} s): "
                        + self.describe(est))
                if c["m_p"] and c["x_F"] and c["y_F"]:
                    if self.converged_s is None:
                        self.converged_s = t
                        self._say(t, "adaptation", "payload estimate converged: " + self.describe(est))
                    elif self.changes and self.changes[-1]["reconverged_s"] is None:
                        self.changes[-1]["reconverged_s"] = t
                        self._say(t, "adaptation", "payload re-estimated: " + self.describe(est))
        if self.target is not None:
            d = self.target - self.theta_law
            if np.any(np.abs(d) > 1e-9 * (1.0 + np.abs(self.target))):
                self.theta_law = self.theta_law + d * min(1.0, self.period / self.config.ramp)
                m, mx, my, jp = (float(v) for v in self.theta_law)
                x, y = mx / m, my / m
                # law.params (a validated copy) is synced at each estimator update, the array every cycle
                self.law.set_platform(m, jp - m * (x * x + y * y), x, y, sync=synced)

    def _latch(self, t: float, why: str) -> None:
        from otbot_hw.runtime.supervisor import Violation

        f = self.file
        self.law.set_platform(f.m_p, f.I_p, f.x_F, f.y_F)
        self.theta_law = self.theta_file.copy()
        self.target = None
        self.use = {"m_p": f.m_p, "I_p": f.I_p, "x_F": f.x_F, "y_F": f.y_F}
        self.fault = (f"payload estimate outside the physical bounds: {why} (daemon.adaptation in config/robot.yaml, "
                      f"platform radius in the parameter file); the file's platform parameters restored")
        self._say(t, "adaptation", self.fault)
        if self.on_fault is not None:
            self.on_fault(Violation("payload", t, self.fault))

    def describe(self, est=None) -> str:
        """The estimate in words: m_p, I_p, x_F, y_F ± std."""
        e = est or self._est
        v, s = e.value, e.std
        return (f"m_p {v[0]:.1f} ± {s[0]:.1f} kg, I_p {v[1]:.2f} ± {s[1]:.2f} kg m^2, x_F {v[2]:.3f} ± {s[2]:.3f} m, "
                f"y_F {v[3]:.3f} ± {s[3]:.3f} m")

    def used(self) -> dict:
        """What the law uses now: {m_p, I_p, x_F, y_F}."""
        from otbot_hw.estimation.payload import payload_from_theta

        v = payload_from_theta(self.theta_law)[0]
        return {n: float(v[i]) for i, n in enumerate(("m_p", "I_p", "x_F", "y_F"))}

    def payload_estimate(self) -> dict:
        """{m_p, I_p, x_F, y_F: {value, std, confident}} of platform + load (kg, kg m^2, m). An I_p the motion
        could not tell (the platform did not turn enough) is the value the law uses with the prior's std."""
        e = self._est
        out = e.to_dict()
        for n, d in out.items():
            d["confident"] = bool(e.confident[n])
        if not e.confident["I_p"]:
            out["I_p"].update(value=float(self.use["I_p"]), std=float(self.config.prior_inertia_std))
        return out

    def summary(self, origin: float = 0.0) -> dict:
        """The ``adaptation`` block: converged_s, switched_s (s after ``origin``, None if never), state, the
        load changes detected, the parameters the law uses, the bounds fault (None)."""
        sh = (lambda v: None if v is None else float(v - origin))  # noqa: E731
        return {"converged_s": sh(self.converged_s), "switched_s": sh(self.switched_s), "state": self.state,
                "changes": [{"detected_s": sh(c["detected_s"]), "reconverged_s": sh(c["reconverged_s"])}
                            for c in self.changes],
                "law": self.used(), "updates": int(self.estimator.updates), "fault": self.fault}

    def message(self, t: float) -> dict:
        """The ``/otbot/payload`` recording message at sample time t (s)."""
        e = self._est
        u = self.used()
        return {"t": t, "value": [float(v) for v in e.value], "std": [float(v) for v in e.std],
                "used": [u["m_p"], u["I_p"], u["x_F"], u["y_F"]], "state": self.state}
