"""Online payload adaptation of the computed-torque law (``PayloadAdapter``): the platform + load's m_p,
I_p, x_F, y_F estimated (``otbot_hw.estimation.payload``) from what every ``TrackingController`` on the
law feeds it, blended into the law once confident, bounds-checked (docs/control.md "Online payload
adaptation").
"""
from __future__ import annotations

import numpy as np

from otbot_hw.control.computed_torque import ComputedTorqueController


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
