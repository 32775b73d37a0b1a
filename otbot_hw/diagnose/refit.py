"""THE refit seam: fit named parameters of a (possibly extended) model to recordings.

Every fit the diagnosis makes -- the nominal fit ("before"), each nested fit of a
candidate effect, the final joint re-identification ("after") -- goes through
``refit``. It is a prediction-error (output-error) fit like the paper's §4:
simulate each whole recording with the extended model from its encoder-estimated
initial state, compare the usable CHANNELS weighted by each channel's noise level,
and minimise with scipy's Trust Region Reflective least squares. Standard
deviations come from the Jacobian at the solution.

Phase B replaces the body of ``refit`` by a call to the shared identification
fitter (``otbot_hw.identification``), keeping this signature and ``FitResult``:
the fitter needs (i) a model callable ``simulate_outputs(data, ExtendedModel)`` and
(ii) names resolved by ``ExtendedModel.with_values`` (nominal, effect-vector or
tied names). Nothing else in ``otbot_hw.diagnose`` calls scipy.optimize.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.residuals import initial_state, simulate_outputs
from otbot_hw.model.effects import ExtendedModel, parameter_bounds


@dataclass
class FitResult:
    """Outcome of a fit: values/std per free name (std NaN when not identifiable), the fitted model,
    weighted residual sum of squares per (recording, channel), number of residuals and function evaluations."""

    names: list[str]
    values: dict[str, float]
    std: dict[str, float]
    model: ExtendedModel
    rss: dict[tuple[str, str], float]
    n_samples: dict[tuple[str, str], int]
    nfev: int
    success: bool
    message: str
    sigma: dict[tuple[str, str], float] = field(default_factory=dict)

    @property
    def n_params(self) -> int:
        return len(self.names)


def channel_sigmas(recordings: list[DiagnosisData]) -> dict[tuple[str, str], float]:
    """Noise level of every usable (recording, channel), from the data themselves."""
    return {(d.name, ch): d.noise_sigma(ch) for d in recordings for ch in d.channels()}


def weighted_residuals(recordings: list[DiagnosisData], model: ExtendedModel,
                       sigmas: dict[tuple[str, str], float], x0s: list[np.ndarray] | None = None) -> dict:
    """{(recording, channel): (measured - simulated) / sigma} for every usable channel."""
    out = {}
    for i, d in enumerate(recordings):
        try:
            sim = simulate_outputs(d, model, None if x0s is None else x0s[i])
        except (ValueError, ZeroDivisionError, FloatingPointError):
            sim = {ch: np.full(len(d), 1e6) for ch in d.channels()}
        for ch in d.channels():
            r = (d.measured(ch) - sim[ch]) / sigmas[(d.name, ch)]
            out[(d.name, ch)] = np.where(np.isfinite(r), r, 1e6)
    return out


JACOBIAN_THREADS = 2
REL_STEP = 1e-6


def _parallel_jacobian(fun, lo, hi):
    """Forward-difference Jacobian whose columns are simulated on ``JACOBIAN_THREADS`` threads
    (the compiled integrator releases the GIL). Step REL_STEP * max(1, |x|), mirrored at bounds."""
    from concurrent.futures import ThreadPoolExecutor

    def jac(theta, f0=None):
        f0 = fun(theta) if f0 is None else f0
        steps = REL_STEP * np.maximum(1.0, np.abs(theta))
        steps = np.where(theta + steps > hi, -steps, steps)

        def col(i):
            t = theta.copy()
            t[i] += steps[i]
            return (fun(t) - f0) / steps[i]

        with ThreadPoolExecutor(JACOBIAN_THREADS) as pool:
            cols = list(pool.map(col, range(len(theta))))
        return np.column_stack(cols)

    return jac


def _typical(name: str) -> float:
    """Typical size of a parameter for scaling the search: 1 % of its bounded range, else 1 cm / small."""
    lo, hi = parameter_bounds(name)
    if np.isfinite(lo) and np.isfinite(hi):
        return (hi - lo) / 100.0
    return 1e-2


def refit(recordings: list[DiagnosisData], model: ExtendedModel, free_names: list[str],
          guess: dict[str, float] | None = None, bounds: dict[str, tuple[float, float]] | None = None,
          max_nfev: int | None = None) -> FitResult:
    """Fit ``free_names`` of ``model`` (others held) to ``recordings`` by simulation output error.

    ``guess``: start values (default: the model's); ``bounds``: per-name (lo, hi) (default: the
    physical bounds of each parameter). Returns the fitted model and statistics.
    """
    sigmas = channel_sigmas(recordings)
    names = list(free_names)
    guess = guess or {}
    x_start = np.array([guess.get(n, model.get(n)) for n in names], dtype=float)
    lo = np.array([(bounds or {}).get(n, parameter_bounds(n))[0] for n in names])
    hi = np.array([(bounds or {}).get(n, parameter_bounds(n))[1] for n in names])
    with np.errstate(invalid="ignore"):
        x_start = np.clip(x_start, np.where(np.isfinite(lo), lo + 1e-12 * (np.abs(lo) + 1), lo),
                          np.where(np.isfinite(hi), hi - 1e-12 * (np.abs(hi) + 1), hi))

    def build(theta: np.ndarray) -> ExtendedModel:
        return model.with_values(dict(zip(names, theta)))

    last: dict = {}

    def fun(theta: np.ndarray) -> np.ndarray:
        if "x" in last and np.array_equal(last["x"], theta):
            return last["f"]
        try:
            m = build(theta)
        except ValueError:
            return np.full(n_res, 1e6)
        res = weighted_residuals(recordings, m, sigmas)
        out = np.concatenate(list(res.values()))
        last["x"], last["f"] = theta.copy(), out
        return out

    base = weighted_residuals(recordings, build(x_start), sigmas)
    n_res = sum(len(v) for v in base.values())
    if names:
        scale = np.array([max(abs(x), _typical(n)) for n, x in zip(names, x_start)])
        sol = least_squares(fun, x_start, jac=_parallel_jacobian(fun, lo, hi), method="trf", bounds=(lo, hi),
                            x_scale=scale, max_nfev=max_nfev or 30 * (len(names) + 1), xtol=1e-7, ftol=1e-7)
        theta, jac, nfev, success, msg = sol.x, sol.jac, sol.nfev, bool(sol.success), str(sol.message)
    else:
        theta, jac, nfev, success, msg = x_start, np.zeros((n_res, 0)), 1, True, "nothing to fit"
    fitted = build(theta)
    res = weighted_residuals(recordings, fitted, sigmas)
    rss = {k: float(v @ v) for k, v in res.items()}
    nobs = {k: len(v) for k, v in res.items()}
    std = {n: float("nan") for n in names}
    if names:
        total = sum(rss.values())
        dof = max(1, n_res - len(names))
        s2 = total / dof
        U, S, Vt = np.linalg.svd(jac, full_matrices=False)
        ok = S > S[0] * 1e-9 if len(S) else S > 0
        if np.all(ok):
            cov = (Vt.T / S ** 2) @ Vt * s2
            std = {n: float(np.sqrt(max(cov[i, i], 0.0))) for i, n in enumerate(names)}
    return FitResult(names=names, values=dict(zip(names, map(float, theta))), std=std, model=fitted, rss=rss,
                     n_samples=nobs, nfev=int(nfev), success=success, message=msg, sigma=sigmas)
