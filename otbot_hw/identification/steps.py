"""The three identification steps (paper Table 5), on recordings or simulated experiments.

step 1  ``wheel`` (I_a, b_w) and ``pivot`` (I_p0, b_p): first-order shaft dynamics
step 2  ``chassis`` (m_c, I_c, x_B, y_B) with the unloaded platform known
step 3  ``platform`` (m_p, I_p, x_F, y_F) with steps 1-2 known

``identify_step`` runs the prediction-error fit from a sequence of starts and keeps
the lowest-cost fit that converged (residuals at the noise floor, no bound active):

1. for the floor steps, the equation-error estimate (``equation_error``), a start
   near the global minimum computed from the measured signals;
2. the user's (or the paper's) initial guess;
3. a few spread starts, tried only when the first two did not converge.

If no start converges the result says so (``converged`` False with the reasons) and
carries no parameter set: a local minimum is never returned as an answer.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from otbot_hw.identification.errors import IdentificationError
from otbot_hw.identification.experiment import Experiment
from otbot_hw.identification.experiments import PAPER_EXPERIMENTS, STEPS, ExperimentSpec, paper_guess
from otbot_hw.identification.model import OtbotModel
from otbot_hw.identification.fit_result import FitResult
from otbot_hw.identification.prediction_error import DEFAULT_BOUNDS, fit_parameters
from otbot_hw.params import OtbotParams, ParameterError


@dataclass
class StepResult:
    """Outcome of one identification step.

    ``fit`` is the accepted fit (or, when nothing converged, the lowest-cost attempt,
    for diagnosis only); ``params`` the full parameter set with the estimates and
    their ``std`` (None unless converged); ``attempts`` one summary per start tried.
    """

    step: str
    spec: ExperimentSpec
    fit: FitResult
    converged: bool
    params: OtbotParams | None
    attempts: list[dict[str, Any]]
    experiments: list[Experiment]
    truth: dict[str, float] | None = None
    reasons: list[str] = field(default_factory=list)
    wall_time: float = 0.0

    def symbol(self, name: str) -> str:
        s = self.spec.symbol(name)
        if self.step != "platform" and s in ("m_p", "I_p", "x_F", "y_F"):
            return s + "0"  # the unloaded platform of the wheel, pivot and chassis runs
        return s


def platform_bounds(base: OtbotParams) -> dict[str, tuple[float, float]]:
    """Default bounds with the centre of mass of the platform inside its radius."""
    b = dict(DEFAULT_BOUNDS)
    b["x_F"] = b["y_F"] = (-base.radius, base.radius)
    return b


def explain_unidentifiable(names: list[str], experiments: Sequence[Experiment]) -> str | None:
    """Why ``names`` cannot be told apart in these experiments, in the robot's terms."""
    held = [e for e in experiments if e.fixture != "floor"]
    platform = {"m_p", "x_F", "y_F", "I_p"}
    chassis = {"m_c", "I_c", "x_B", "y_B"}
    pivot_still = all(np.all(np.abs(e.torque[:, 2]) < 1e-9) and e.motion.get("pivot_range", 0.0) < 0.01
                      for e in experiments)
    if set(names) & {"x_F", "y_F", "I_p"} and pivot_still:
        return "the platform never rotated relative to the chassis (no pivot torque, no pivot motion)"
    if held and len(held) == len(experiments) and set(names) & (platform | chassis):
        fx = held[0].fixture
        return (f"on the '{fx}' fixture the chassis is held, so only the platform's inertia about the pivot "
                "I_p + m_p (x_F^2 + y_F^2) and b_p act on the outputs")
    if set(names) & {"I_a", "b_w"}:
        wheels = {"w_r": (0, "right", "tau_r"), "w_l": (1, "left", "tau_l")}
        idle = [wheels[c] for e in experiments for c in e.channels if c in wheels
                and np.all(np.abs(e.torque[:, wheels[c][0]]) < 1e-9)]
        fitted = [c for e in experiments for c in e.channels if c in wheels]
        if fitted and len(idle) == len(fitted):
            side, tau = idle[0][1], idle[0][2]
            return f"the {side} wheel, whose encoder is fitted, was never driven ({tau} = 0)"
    if all(e.motion.get("moved", 1.0) < 1e-6 for e in experiments):
        return "the measured outputs never changed: the robot did not move"
    return None


def check_guess(step: str, guess: Mapping[str, float], base: OtbotParams) -> None:
    """``IdentificationError`` unless every guessed value of ``step`` lies within the fit's bounds
    (cheap: callers check before simulating or loading anything)."""
    from otbot_hw.params import UNITS

    spec = PAPER_EXPERIMENTS[step]
    bounds = platform_bounds(base)
    for n, v in guess.items():
        lo, hi = bounds.get(n, (-np.inf, np.inf))
        if not lo <= v <= hi:
            raise IdentificationError(f"guess {spec.symbol(n)} = {v:g} {UNITS.get(n, '')} lies outside its bounds "
                                      f"[{lo:g}, {hi:g}]".replace("  ", " "))


def _attempt_summary(label: str, fit: FitResult | None, error: str | None = None) -> dict[str, Any]:
    if fit is None:
        return {"start": label, "error": error}
    return {"start": label, "guess": fit.guess, "estimate": fit.estimate, "cost": fit.cost,
            "converged": fit.converged, "reasons": fit.reasons, "nfev": fit.nfev}


def _spread_starts(step: str, base: OtbotParams) -> list[dict[str, float]]:
    """Deterministic extra starts spanning the physical range (used only as a fallback)."""
    if step == "platform":
        out = []
        for m in (base.m_p, 100.0, 300.0):
            out.append({"m_p": m, "I_p": max(base.I_p, 0.05 * m), "x_F": 0.0, "y_F": 0.0})
        return out
    if step == "chassis":
        return [{"m_c": m, "I_c": 0.02 * m, "x_B": 0.0, "y_B": 0.0, "x_F": 0.0, "y_F": 0.0, "I_p": base.I_p}
                for m in (30.0, 100.0, 300.0)]
    spec = PAPER_EXPERIMENTS[step]
    return [{n: getattr(base, n) * f for n in spec.free} for f in (0.1, 10.0)]


def check_fixtures(step: str, recordings: Sequence, names: Sequence[str], spec: ExperimentSpec | None = None) -> None:
    """``IdentificationError`` when a recording's metadata names another fixture than the step needs."""
    spec = spec or PAPER_EXPERIMENTS[step]
    for name, rec in zip(names, recordings):
        fixture = rec.metadata.get("fixture") if rec.metadata else None
        if fixture is not None and fixture != spec.fixture:
            raise IdentificationError(
                f"{name}: recording was made on the '{fixture}' fixture, step {step} needs '{spec.fixture}' "
                f"({spec.description})")


def experiments_from_recordings(step: str, recordings: Sequence, base: OtbotParams,
                                spec: ExperimentSpec | None = None, t_max: float | None = -1.0,
                                sigma: Mapping[str, float] | None = None) -> list[Experiment]:
    """``Experiment``s of a step from recordings; ``t_max`` -1 means the spec's duration."""
    spec = spec or PAPER_EXPERIMENTS[step]
    if not recordings:
        raise IdentificationError(f"step {step}: no recording given")
    tm = spec.duration if t_max == -1.0 else t_max
    names = [f"{step}" if len(recordings) == 1 else f"{step}{i + 1}" for i in range(len(recordings))]
    check_fixtures(step, recordings, names, spec)
    out = []
    for name, rec in zip(names, recordings):
        out.append(Experiment.from_recording(rec, spec.channels, name=name, fixture=spec.fixture, t_max=tm,
                                             sigma=sigma, geometry=base))
    return out


def identify_step(step: str, recordings: Sequence, base: OtbotParams, guess: Mapping[str, float] | None = None,
                  global_start: bool = True, spec: ExperimentSpec | None = None, t_max: float | None = -1.0,
                  sigma: Mapping[str, float] | None = None, residual_tolerance: float | None = 1.5,
                  max_nfev: int = 200, truth: OtbotParams | None = None, guess_first: bool = False,
                  extra_free: Sequence[str] = ()) -> StepResult:
    """Identify the parameters of ``step`` from ``recordings`` (project format).

    base: all other parameters (known from the earlier steps); guess: initial guess of
    the free parameters (default: the paper's); global_start: also try the
    equation-error start and, if needed, spread starts (False: a single fit from
    the guess, like the paper); guess_first: with global_start, fit from the guess before
    the equation-error start (a guess the user gave is tried, not only kept as a fallback);
    truth: the simulated robot's parameters, for the report (default: read from a
    simulated recording's metadata); extra_free: parameters (paper's names) fitted with the
    step's own, e.g. the unloaded platform's x_F, y_F, I_p in the chassis step when the file's
    values may be off (``session.identify_session``'s nuisance parameters).
    Raises ``IdentificationError`` / ``NotIdentifiableError`` for bad input.
    """
    t0 = time.perf_counter()
    if step not in STEPS:
        raise IdentificationError(f"unknown step '{step}' (known: {', '.join(STEPS)})")
    spec = spec or PAPER_EXPERIMENTS[step]
    exps = experiments_from_recordings(step, recordings, base, spec, t_max, sigma)
    free = list(spec.free) + [n for n in extra_free if n not in spec.free]
    g = paper_guess(step, base)
    g.update({n: float(getattr(base, n)) for n in free if n not in g})
    unknown = [n for n in (guess or {}) if n not in free]
    if unknown:
        raise IdentificationError(f"--guess {', '.join(unknown)}: step {step} estimates "
                                  f"{', '.join(spec.symbol(n) for n in free)}")
    g.update({n: float(v) for n, v in (guess or {}).items()})
    bounds = platform_bounds(base)
    model = OtbotModel()
    starts: list[tuple[str, dict[str, float]]] = []
    attempts: list[dict[str, Any]] = []
    if global_start and step in ("chassis", "platform"):
        try:
            from otbot_hw.identification.equation_error import estimate_body

            est = estimate_body(recordings[0], base, step, t_max=spec.duration if t_max == -1.0 else t_max,
                                platform_moments=step == "chassis" and bool({"x_F", "y_F"} & set(free)))
            est = {n: v for n, v in est.items() if n in free}
            for n, v in est.items():
                lo, hi = bounds[n]
                est[n] = float(np.clip(v, lo + 1e-3 * (hi - lo), hi - 1e-3 * (hi - lo)))
            starts.append(("equation error", est))
        except IdentificationError as exc:
            attempts.append(_attempt_summary("equation error", None, str(exc)))
    starts.insert(0 if guess_first else len(starts), ("guess", g))
    fits: list[FitResult] = []

    def run(label: str, start: dict[str, float]) -> FitResult:
        f = fit_parameters(model, exps, free, base, guess=start, bounds=bounds, max_nfev=max_nfev,
                           residual_tolerance=residual_tolerance, explain=explain_unidentifiable)
        fits.append(f)
        attempts.append(_attempt_summary(label, f))
        return f

    accepted: FitResult | None = None
    for label, start in starts:
        f = run(label, start)
        if f.converged:
            accepted = f
            break
    if accepted is None and global_start:
        for i, start in enumerate(_spread_starts(step, base)):
            start = {n: start.get(n, float(getattr(base, n))) for n in free}
            f = run(f"spread start {i + 1}", start)
            if f.converged:
                accepted = f
                break
    best = accepted or min(fits, key=lambda f: f.cost)
    params = None
    reasons = [] if accepted else [f"no start converged; best attempt: {'; '.join(best.reasons)}"]
    if accepted is not None:
        std = dict(base.std)
        std.update(accepted.std)
        try:
            params = base.replace(**accepted.estimate, std=std)
        except ParameterError as exc:
            reasons.append(f"estimate is not physical: {exc}")
    tr = truth or next((e.truth_params for e in exps if e.truth_params is not None), None)
    truth_d = {n: float(getattr(tr, n)) for n in free} if tr is not None else None
    return StepResult(step=step, spec=spec, fit=best, converged=params is not None, params=params,
                      attempts=attempts, experiments=exps, truth=truth_d, reasons=reasons,
                      wall_time=time.perf_counter() - t0)


def identify_simulated(step: str, truth: OtbotParams, base: OtbotParams | None = None, seed: int | None = 0,
                       guess: Mapping[str, float] | None = None, global_start: bool = True,
                       noise=None, **kw) -> StepResult:
    """Simulate the paper's experiment of ``step`` on ``truth`` and identify it.

    base: the known parameters used by the fit (default ``truth``: steps 1-2 known exactly).
    """
    from otbot_hw.identification.experiments import simulate_experiment

    rec = simulate_experiment(step, truth, seed=seed, noise=noise)
    return identify_step(step, [rec], base or truth, guess=guess, global_start=global_start, truth=truth, **kw)


def demo_stage(recording, params: OtbotParams, out_dir, quiet: bool = False) -> dict[str, Any]:
    """``otbot demo``'s identification stage: step 2 (chassis) on the demo recording.

    Runs the step's pipeline (equation-error start, then the paper's guess 54.57 kg,
    0.65 kg m^2, -0.07 m, 0.25 m if needed), writes the fitting plot and returns the
    JSON summary (estimates, std, truth, fit percent).
    """
    from pathlib import Path

    from otbot_hw.identification.report import plot_fit, step_table, step_to_dict

    res = identify_step("chassis", [recording], params, truth=params)
    out = step_to_dict(res)
    out["plots"] = plot_fit(Path(out_dir) / "identification", res)
    if not quiet:
        print(step_table(res))
        for p in out["plots"]:
            print(f"[demo] plot: {p}")
    return out
