"""A whole identification session: the paper's steps chained, gated, with honest uncertainties.

``identify_session(recordings_by_step, params_start)`` runs the steps present (in the
order wheel, pivot, chassis, platform), each as ``steps.identify_step`` does with the
earlier steps' estimates as its known parameters, checks each step's quality gates
(``gates``), and carries the earlier steps' uncertainty into the later ones
(``uncertainty``):

* ``method="joint"`` (default): a final joint fit of all recordings of all steps,
  started at the chained estimates; its covariance is the session's;
* ``method="propagate"``: the chained estimates kept, their covariance propagated
  step by step.

``benchmarks/bench_accuracy.py`` measures both on robots that differ from nominal
(docs/identification.md): both are honest (error within 3 sigma in >= 95 % of seeds);
the joint fit is chosen as default because it uses every recording for every
parameter (smaller sigma, e.g. for b_p, which the floor runs also inform) at a cost of
one extra fit of a few iterations. If the joint fit does not converge (a recording the
others contradict), the session falls back to propagation and says so.

Parameters a session does not estimate keep ``params_start``'s values; their std (from
``params_start.std``, e.g. a parameter file of an earlier session) and ``known_std``
(the parameters taken for granted: l1, l2, r, m_p0, x_F0, y_F0) are propagated too.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from otbot_hw.identification.errors import IdentificationError, NotIdentifiableError
from otbot_hw.identification.experiments import PAPER_EXPERIMENTS, STEPS, ExperimentSpec
from otbot_hw.identification.gates import GateLimits, StepGates, check_fit, check_step
from otbot_hw.identification.fit_result import FitResult
from otbot_hw.identification.steps import StepResult, identify_step
from otbot_hw.identification.uncertainty import (KNOWN_PARAMS, LOADED_STEPS, NUISANCE_PARAMS, SESSION_PARAMS,
                                                 STEP_PARAMS,
                                                 UNLOADED_PLATFORM, JointCovariance, SessionModel, add_known_uncertainty, joint_fit,
                                                 propagate_step, robot_params, session_vector)
from otbot_hw.params import UNITS, OtbotParams, ParameterError

METHODS = ("joint", "propagate")
#: units of the session symbols
SESSION_UNITS = {**UNITS, "I_p0": UNITS["I_p"], "m_p0": UNITS["m_p"], "x_F0": UNITS["x_F"], "y_F0": UNITS["y_F"]}


@dataclass
class SessionStep:
    """One step of a session: its own fit (``result``, earlier steps' estimates fixed), its gates, and the std
    of its parameters: alone (``step_std``, earlier steps taken as exact), with the earlier steps' uncertainty
    propagated (``propagated_std``) and from the joint fit of the session so far (``session_std``, whose
    residuals the gates judge; ``joint``)."""

    step: str
    result: StepResult
    gates: StepGates
    step_std: dict[str, float] = field(default_factory=dict)
    propagated_std: dict[str, float] = field(default_factory=dict)
    session_std: dict[str, float] = field(default_factory=dict)
    joint: FitResult | None = None

    @property
    def estimate(self) -> dict[str, float]:
        return {self.result.symbol(n): v for n, v in self.result.fit.estimate.items()}

    def to_dict(self) -> dict[str, Any]:
        fit = self.result.fit
        return {
            "step": self.step, "converged": bool(self.result.converged), "verdict": self.gates.verdict,
            "reasons": self.gates.reasons,
            "fit": {k: _num(v) for k, v in (self.joint or fit).fit_percent.items()
                    if k.split("/")[0] in {e.name for e in self.result.experiments}},
            "estimate": {s: {"value": v, "std": _num(self.step_std.get(s)),
                             "propagated_std": _num(self.propagated_std.get(s)),
                             "session_std": _num(self.session_std.get(s))} for s, v in self.estimate.items()},
            "recordings": [e.name for e in self.result.experiments],
            "gates": self.gates.to_dict(), "wall_time": self.result.wall_time,
        }


@dataclass
class SessionResult:
    """Outcome of ``identify_session``.

    values: every session symbol (``SESSION_PARAMS`` and ``KNOWN_PARAMS``), SI;
    covariance: joint covariance of the estimated parameters (and of the uncertain
    known ones); std: one standard deviation per symbol (0 for exact ones);
    chained / chained_std: the steps' estimates and their propagated std (before the
    joint fit); naive_std: each step's own std (earlier steps taken as exact); notices: what
    the session did that the caller should know and that does not fail it (a nuisance
    parameter these recordings cannot determine, held at the file's value).
    """

    steps: dict[str, SessionStep]
    method: str
    values: dict[str, float]
    covariance: JointCovariance
    chained: dict[str, float]
    chained_std: dict[str, float]
    naive_std: dict[str, float]
    template: OtbotParams
    estimated: list[str]
    joint: FitResult | None = None
    truth: dict[str, float] | None = None
    reasons: list[str] = field(default_factory=list)
    notices: list[str] = field(default_factory=list)
    wall_time: float = 0.0
    cpu_time: float = 0.0

    @property
    def std(self) -> dict[str, float]:
        held = self.covariance.std()
        out = {n: held.get(n, 0.0) for n in self.values}
        if not self.loaded:  # no platform step: the working platform is the unloaded one
            for n, u in UNLOADED_PLATFORM.items():
                out[n] = out.get(u, 0.0)
        return out

    @property
    def passed(self) -> bool:
        return not self.reasons and all(s.gates.passed for s in self.steps.values())

    @property
    def loaded(self) -> bool:
        return "platform" in self.steps

    def parameters(self) -> dict[str, dict[str, float]]:
        """``{symbol: {value, std}}`` for ``SESSION_PARAMS`` (the bench's ``--json`` ``parameters``)."""
        std = self.std
        return {n: {"value": float(self.values[n]), "std": float(std[n])} for n in SESSION_PARAMS}

    def params(self) -> OtbotParams:
        """The working parameter set (loaded platform when the platform step ran) with std."""
        return robot_params(self.values, self.template, loaded=True,
                            std={n: s for n, s in self.std.items() if s > 0})

    def save_params(self, path: str | Path) -> None:
        """Write ``params.yaml`` (layout of ``config/otbot.yaml``, each identified entry with its std)."""
        how = {"joint": "a joint fit of all recordings", "propagate": "the chained steps"}[self.method]
        ip0 = (f"I_p0 (unloaded platform) = {self.values['I_p0']:.6g} +- {self.std['I_p0']:.3g} kg m^2, "
               + ", ".join(f"{n} = {self.values[n]:.6g} +- {self.std.get(n, 0.0):.3g} {SESSION_UNITS[n]}"
                           for n in ("m_p0", "x_F0", "y_F0")) + ". ")
        self.params().save(path, header=(
            f"Identified by a bench session (steps {', '.join(self.steps)}; estimates from {how}).\n"
            "std = one standard deviation including the uncertainty of the earlier steps.\n"
            + ip0 + ("The platform entries are the loaded working platform." if self.loaded else "")))

    def combination(self, weights: Mapping[str, float]) -> dict[str, float]:
        """``{value, std}`` of sum_n w_n theta_n (session symbols), std from the full covariance: e.g. the
        floor runs' total mass {"m_c": 1, "m_p0": 1}, which the data identify even when neither term is."""
        value = float(sum(w * self.values[n] for n, w in weights.items()))
        names = list(weights)
        C = self.covariance.sub(names)
        w = np.array([weights[n] for n in names], dtype=float)
        return {"value": value, "std": float(np.sqrt(max(w @ C @ w, 0.0)))}

    def error_sigma(self) -> dict[str, float] | None:
        """(estimate - truth) / std per estimated symbol (simulated recordings only)."""
        if self.truth is None:
            return None
        std = self.std
        return {n: (self.values[n] - self.truth[n]) / std[n] for n in self.estimated
                if n in self.truth and std[n] > 0}

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "passed": self.passed, "method": self.method, "reasons": list(self.reasons),
            "notices": list(self.notices),
            "steps": {s: st.to_dict() for s, st in self.steps.items()},
            "parameters": {n: {k: _num(v) for k, v in d.items()} for n, d in self.parameters().items()},
            "correlation": {"names": list(self.covariance.names),
                            "matrix": [[_num(v) for v in row] for row in self.covariance.correlation()]},
            "units": {n: SESSION_UNITS[n] for n in SESSION_PARAMS},
            "wall_time": self.wall_time, "cpu_time": self.cpu_time,
        }
        if self.joint is not None:
            out["joint_fit"] = {"converged": self.joint.converged, "reasons": list(self.joint.reasons),
                                "nfev": self.joint.nfev, "wall_time": self.joint.wall_time}
        if self.truth is not None:
            out["truth"] = {n: self.truth[n] for n in SESSION_PARAMS if n in self.truth}
            out["error_sigma"] = {n: _num(v) for n, v in (self.error_sigma() or {}).items()}
        return out


def _num(v):
    return float(v) if v is not None and math.isfinite(v) else None


def _carried_std(params_start: OtbotParams, estimated: Sequence[str], known_std: Mapping[str, float]) -> dict[str, float]:
    """std of what the session does not estimate: ``params_start``'s own std (an unloaded robot's file,
    its I_p is I_p0) and ``known_std`` of the parameters taken for granted."""
    out: dict[str, float] = {}
    for n in SESSION_PARAMS:
        if n in estimated or n in STEP_PARAMS["platform"]:
            continue  # an absent platform step leaves no loaded platform to carry
        s = params_start.std.get("I_p" if n == "I_p0" else n, 0.0)
        if s > 0:
            out[n] = float(s)
    for n, s in known_std.items():
        if n not in KNOWN_PARAMS:
            raise IdentificationError(f"known_std: '{n}' is not a parameter taken for granted "
                                      f"(known: {', '.join(KNOWN_PARAMS)})")
        if isinstance(s, bool) or not (isinstance(s, (int, float)) and math.isfinite(s) and s >= 0):
            raise IdentificationError(f"known_std: std of {n} must be a finite number >= 0, got {s!r}")
        if s > 0:
            out[n] = float(s)
    return out


def _truth(steps: Mapping[str, SessionStep]) -> dict[str, float] | None:
    unloaded = loaded = None
    for s, st in steps.items():
        tp = next((e.truth_params for e in st.result.experiments if e.truth_params is not None), None)
        if tp is None:
            continue
        if s in LOADED_STEPS:
            loaded = tp
        else:
            unloaded = unloaded or tp
    if unloaded is None and loaded is None:
        return None
    v = session_vector(unloaded or loaded, loaded)
    if loaded is None:
        for n in ("m_p", "I_p", "x_F", "y_F"):
            v.pop(n)
    if unloaded is None:
        for n in SESSION_PARAMS:
            if n not in STEP_PARAMS["platform"]:
                v.pop(n, None)
    return v


def identify_session(recordings_by_step: Mapping[str, Sequence], params_start: OtbotParams, method: str = "joint",
                     known_std: Mapping[str, float] | None = None,
                     guesses: Mapping[str, Mapping[str, float]] | None = None,
                     specs: Mapping[str, ExperimentSpec] | None = None, gate_limits: GateLimits | None = None,
                     global_start: bool = True,
                     nuisance: Sequence[str] = NUISANCE_PARAMS) -> SessionResult:
    """Identify the session's parameters from the recordings of its steps.

    recordings_by_step: {step: [Recording, ...]} for some of wheel, pivot, chassis, platform
        (project format; each step's fixture as ``experiments.PAPER_EXPERIMENTS`` defines);
    params_start: the robot's parameters before the session (unloaded platform; geometry and
        m_p0, x_F0, y_F0 taken for granted); the steps' known values until estimated;
    method: "joint" or "propagate" (module docstring); known_std: std of the parameters taken
        for granted (``KNOWN_PARAMS``), default exact; guesses: per step, initial guesses by the
        paper's model names (as ``identify_step``); specs: per step, the experiment that was run
        (default the paper's; a designed excitation passes its own); gate_limits: the gates' thresholds;
        nuisance: parameters taken for granted that the joint fit estimates too once the chassis step's
        floor run is in (default the unloaded platform's centre of mass x_F0, y_F0: a file whose values
        are off would otherwise leave every floor run unexplained); their std then comes from the data.
        A nuisance parameter the recordings cannot determine (``NotIdentifiableError`` of the chassis
        step or of a joint fit naming it) is held at ``params_start``'s value instead, its ``known_std``
        carried into the others' std, and ``notices`` says so.
    A step that does not converge stops the chain (later steps are not fitted); its gates and
    the session's ``reasons`` say why. Raises ``IdentificationError`` for bad input.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    if method not in METHODS:
        raise IdentificationError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    unknown = [s for s in recordings_by_step if s not in STEPS]
    if unknown:
        raise IdentificationError(f"unknown step(s) {', '.join(unknown)} (known: {', '.join(STEPS)})")
    order = [s for s in STEPS if recordings_by_step.get(s)]
    if not order:
        raise IdentificationError("no recording given for any step")
    bad = [n for n in nuisance if n not in KNOWN_PARAMS]
    if bad:
        raise IdentificationError(f"nuisance: {', '.join(bad)} not parameters taken for granted "
                                  f"(known: {', '.join(KNOWN_PARAMS)})")
    free_nuisance = list(nuisance) if "chassis" in order else []
    estimated_all = [n for s in order for n in STEP_PARAMS[s]] + free_nuisance
    carried = _carried_std(params_start, estimated_all, {n: v for n, v in (known_std or {}).items()
                                                          if n not in free_nuisance})
    values = session_vector(params_start)
    cov = JointCovariance(list(carried), np.diag([carried[n] ** 2 for n in carried]))
    steps: dict[str, SessionStep] = {}
    reasons: list[str] = []
    notices: list[str] = []

    def hold(names: list[str], exc: NotIdentifiableError) -> None:
        """Nuisance ``names`` held at the file's values, their std carried (the session goes on)."""
        nonlocal cov
        for n in names:
            free_nuisance.remove(n)
            chained[n] = values[n]
            s = float((known_std or {}).get(n, 0.0))
            if s > 0:
                carried[n] = s
            if s > 0 and n not in cov.names:
                k = len(cov.names)
                m = np.zeros((k + 1, k + 1))
                m[:k, :k], m[k, k] = cov.matrix, s * s
                cov = JointCovariance(cov.names + [n], m)
        held = ", ".join(f"{n} = {values[n]:.4g}" + (f" +- {carried[n]:.2g}" if n in carried else "")
                         + f" {SESSION_UNITS[n]}" for n in names)
        notices.append(f"{', '.join(names)} not identifiable from these recordings ({exc}); held at the parameter "
                       f"file's value ({held}) "
                       + ("with its std carried into the other parameters' std" if any(n in carried for n in names)
                          else "taken as exact (no std given for it)"))

    def holding(fit, involved_in):
        """``fit()`` (which frees ``free_nuisance``); when it raises ``NotIdentifiableError`` naming free nuisance
        parameters (``involved_in(exc)``), the fewest of them held (each alone, then all) that let it run; else
        the first error."""
        try:
            return fit()
        except NotIdentifiableError as exc:
            involved = involved_in(exc)
            if not involved:
                raise
            for cand in [[n] for n in involved] + ([involved] if len(involved) > 1 else []):
                saved = list(free_nuisance)
                free_nuisance[:] = [n for n in saved if n not in cand]
                try:
                    out = fit()
                except NotIdentifiableError:
                    continue
                finally:
                    free_nuisance[:] = saved
                hold(cand, exc)
                return out
            raise

    naive_std: dict[str, float] = {}
    experiments_all: list = []
    loaded_names: list[str] = []
    joint: FitResult | None = None
    chained = dict(values)
    for step in order:
        spec = (specs or {}).get(step) or PAPER_EXPERIMENTS[step]
        base = robot_params(chained, params_start, loaded=step in LOADED_STEPS)

        def fit_step():
            extra = ()
            if step == "chassis" and free_nuisance:  # the unloaded platform's inertia moves with its centre (J_p0)
                extra = tuple(n[:-1] for n in free_nuisance if n.endswith("0")) + ("I_p",)
            return identify_step(step, recordings_by_step[step], base, guess=(guesses or {}).get(step),
                                 global_start=global_start, spec=spec, extra_free=extra)

        res = holding(fit_step, lambda exc: [n for n in free_nuisance if step == "chassis" and n.endswith("0")
                                             and n[:-1] in exc.parameters])
        if not res.converged and method == "propagate":
            # (the joint method goes on: a step fitted with the earlier steps' estimates held exact may miss
            # the noise floor by a little because of their errors; the joint fit below judges it)
            steps[step] = SessionStep(step, res, check_step(res, gate_limits))
            reasons.append(f"step {step} did not converge; "
                           + ("later steps not fitted" if step != order[-1] else "no session estimate"))
            break
        st = SessionStep(step, res, StepGates(step))
        steps[step] = st
        free = [res.symbol(n) for n in res.fit.names]
        st.step_std = {res.symbol(n): s for n, s in res.fit.std.items()}
        naive_std.update(st.step_std)
        chained.update(st.estimate)
        mine = [e.name for e in res.experiments]
        experiments_all += res.experiments
        if step in LOADED_STEPS:
            loaded_names += mine
        model = SessionModel(loaded_names)
        cov, _ = propagate_step(cov, free, res.fit.covariance, model, res.experiments, chained)
        st.propagated_std = {n: cov.std()[n] for n in free}
        if method == "propagate":
            st.gates = check_step(res, gate_limits)
            continue
        # the session so far in one fit: the step's gates judge its recordings with every parameter free
        estimated = [n for n in SESSION_PARAMS if n in naive_std]
        if "chassis" in steps:
            estimated += free_nuisance
        start = {**chained, **(joint.estimate if joint is not None else {}), **st.estimate}

        def fit_joint():
            held = [n for n in nuisance if n not in free_nuisance]
            return joint_fit(model, experiments_all, [n for n in estimated if n not in held],
                             {**start, **{n: values[n] for n in held}}, params_start.radius)

        joint = holding(fit_joint, lambda exc: [n for n in free_nuisance if n in exc.parameters])
        free = [n for n in free if n in joint.names]  # (a nuisance held above is no longer fitted)
        st.joint = joint
        st.gates = check_fit(step, joint, experiments_all, model, params=free, only=mine, limits=gate_limits,
                             reasons=[f"the recordings of steps {', '.join(steps)} cannot be explained by one "
                                      f"parameter set: {'; '.join(joint.reasons)}"])
        st.session_std = {n: joint.std[n] for n in free}
        if not joint.converged:
            reasons.append(f"step {step}: the joint fit of all recordings so far did not converge; "
                           + ("later steps not fitted" if step != order[-1] else "no session estimate"))
            break
    estimated = [n for n in SESSION_PARAMS if n in naive_std]
    if "chassis" in steps:  # fitted in the chassis step (and in the joint fit)
        estimated += free_nuisance
    chained_std = cov.std()
    values = dict(chained)
    used = method
    if method == "joint" and joint is not None and joint.converged:
        values.update(joint.estimate)
        jcov = JointCovariance(list(joint.names), joint.covariance)
        cov = add_known_uncertainty(jcov, carried, SessionModel(loaded_names), experiments_all, values)
    elif method == "joint":
        used = "propagate"
    if "platform" not in steps:  # the working platform is the unloaded one
        values.update({n: values[u] for n, u in UNLOADED_PLATFORM.items()})
    try:
        robot_params(values, params_start)
    except ParameterError as exc:
        reasons.append(f"the session's estimates are not physical: {exc}")
    return SessionResult(steps=steps, method=used, values=values, covariance=cov, chained=chained,
                         chained_std=chained_std, naive_std=naive_std, template=params_start, estimated=estimated,
                         joint=joint, truth=_truth(steps), reasons=reasons, notices=notices,
                         wall_time=time.perf_counter() - t0,
                         cpu_time=time.process_time() - c0)
