"""THE refit seam: fit named parameters of a (possibly extended) model to recordings.

Every fit the diagnosis makes -- the nominal fit ("before"), each nested fit of a
candidate effect, the final joint re-identification ("after") -- goes through
``refit``, which is a call of the shared identification fitter
``otbot_hw.identification.prediction_error.fit_parameters`` (prediction/output error
like the paper's §4, scipy Trust Region Reflective least squares, Jacobian columns
simulated as one batch): the extended model is its prediction model
(``prediction.ExtendedPredictionModel``), each recording one ``Experiment`` (usable
channels, initial state from the encoders, each (recording, channel) weighted by the
noise level measured from the data). Options chosen for the diagnosis: no
residual-vs-noise acceptance test (the "before" fit of a model that misses physics
is expected to be poor and is still the answer), no identifiability exception (a
parameter the data cannot determine gets std NaN instead), the diagnosis's RK4 step
(``simulated_run.diagnosis_substeps``, per parameter row), standard deviations with each channel's noise variance estimated
from its residuals.
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import threadpool_limits

from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.prediction import FAILED_OUTPUT, FITTER_CHANNEL, ExtendedPredictionModel, diagnosis_experiments
from otbot_hw.diagnose.simulated_run import initial_state, simulate_outputs
from otbot_hw.identification.prediction_error import fit_parameters
from otbot_hw.identification.residual_problem import RANK_TOL
from otbot_hw.model.effects import TIED_PARAMS, ExtendedModel, parameter_bounds


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
    correlation: np.ndarray | None = None  # of the free names, from the fitter's covariance
    scale: dict[str, float] = field(default_factory=dict)  # the fitter's scale of each free name (``refit``)

    @property
    def n_params(self) -> int:
        return len(self.names)


@contextmanager
def single_blas_thread():
    """Limit BLAS/LAPACK (OpenBLAS, MKL) to one thread inside the block.

    The fits' linear algebra is on tall, thin matrices (the least-squares SVD of a 6000 x 10
    Jacobian per iteration): a multi-threaded BLAS splits them into pieces too small to pay
    for the synchronisation, and on a loaded 2-core machine (the simulation threads, other
    jobs) each piece waits for a core -- measured 10-45 ms per SVD instead of 1 ms."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield


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
            with np.errstate(over="ignore", invalid="ignore"):  # a diverged simulation: handled below
                r = (d.measured(ch) - sim[ch]) / sigmas[(d.name, ch)]
            # a diverged simulation (non-finite, or beyond any physical output) reads 1e6 sigma
            out[(d.name, ch)] = np.where(np.isfinite(r) & (np.abs(sim[ch]) < FAILED_OUTPUT), r, 1e6)
    return out


def _typical(name: str) -> float:
    """Typical size of a parameter for scaling the search: 1 % of its bounded range, else 1 cm / small."""
    lo, hi = parameter_bounds(name)
    if np.isfinite(lo) and np.isfinite(hi):
        return (hi - lo) / 100.0
    return 1e-2


def default_nfev(n_free: int) -> int:
    """The fitter's default iteration budget for ``n_free`` free parameters (``refit`` without ``max_nfev``)."""
    return 30 * (n_free + 1)


def refit(recordings: list[DiagnosisData], model: ExtendedModel, free_names: list[str],
          guess: dict[str, float] | None = None, bounds: dict[str, tuple[float, float]] | None = None,
          max_nfev: int | None = None, tol: float = 1e-7, scale: dict[str, float] | None = None) -> FitResult:
    """Fit ``free_names`` of ``model`` (others held) to ``recordings`` by simulation output error.

    ``guess``: start values (default: the model's); ``bounds``: per-name (lo, hi) (default: the
    physical bounds of each parameter); ``tol``: the fitter's relative tolerances (cost, step);
    ``scale``: the fitter's scale per name (default max(|start|, ``_typical``)) -- a fit continued from
    another one's end passes that fit's ``FitResult.scale``: the same finite-difference steps, so its first
    Jacobian is the other's last one, simulated already (the cache of recent simulations).
    Returns the fitted model and statistics.
    """
    sigmas = channel_sigmas(recordings)
    names = list(free_names)
    guess = guess or {}
    x_start = np.array([guess.get(n, model.get(n)) for n in names], dtype=float)
    bnd = {n: tuple(map(float, (bounds or {}).get(n, parameter_bounds(n)))) for n in names}
    lo = np.array([bnd[n][0] for n in names])
    hi = np.array([bnd[n][1] for n in names])
    with np.errstate(invalid="ignore"):
        x_start = np.clip(x_start, np.where(np.isfinite(lo), lo + 1e-12 * (np.abs(lo) + 1), lo),
                          np.where(np.isfinite(hi), hi - 1e-12 * (np.abs(hi) + 1), hi))
    if not names:
        res = weighted_residuals(recordings, model, sigmas)
        return FitResult(names=[], values={}, std={}, model=model, rss={k: float(v @ v) for k, v in res.items()},
                         n_samples={k: len(v) for k, v in res.items()}, nfev=1, success=True,
                         message="nothing to fit", sigma=sigmas)
    sc = {n: (scale or {}).get(n, max(abs(x), _typical(n))) for n, x in zip(names, x_start)}
    pm = ExtendedPredictionModel(model, tied=[n for n in names if n in TIED_PARAMS])
    fit = fit_parameters(
        pm, diagnosis_experiments(recordings, model.with_values(dict(zip(names, x_start))), sigmas), names,
        pm.vector(model),
        guess=dict(zip(names, x_start)), bounds=bnd,
        scale=sc,
        noise="residuals", max_nfev=max_nfev or default_nfev(len(names)), tol=tol,
        residual_tolerance=None, check_identifiability=False, integration_tol=None)
    rss, nobs = {}, {}
    for d in recordings:
        for ch in d.channels():
            key = f"{d.name}/{FITTER_CHANNEL[ch]}"
            rss[(d.name, ch)] = float(fit.weighted_rss[key])
            nobs[(d.name, ch)] = int(fit.samples[key])
    std = {n: float(fit.std[n]) for n in names}
    if not _determined(fit.covariance):
        lost = _undetermined(fit.covariance)
        std = {n: float("nan") if lost[i] else std[n] for i, n in enumerate(names)}
    return FitResult(names=names, values=dict(fit.estimate), std=std, model=model.with_values(fit.estimate),
                     rss=rss, n_samples=nobs, nfev=fit.nfev, success=fit.optimizer_status > 0,
                     message=fit.message, sigma=sigmas, correlation=np.asarray(fit.correlation), scale=sc)


def _determined(cov: np.ndarray) -> bool:
    """Whether the data determine every free parameter: a finite covariance whose correlation matrix
    has condition number below 1 / RANK_TOL^2 (the identification's rank tolerance)."""
    if not np.all(np.isfinite(cov)):
        return False
    with np.errstate(invalid="ignore"):  # a negative variance: NaN, not determined (below)
        d = np.sqrt(np.diag(cov))
    if not np.all(d > 0):
        return False
    return bool(np.linalg.cond(cov / np.outer(d, d)) < 1.0 / RANK_TOL ** 2)


NULL_COMPONENT = 0.3  # a parameter with a larger share of a near-null direction is not determined


def _undetermined(cov: np.ndarray) -> np.ndarray:
    """Which free parameters the data do not determine, when ``_determined`` says not all are: a non-finite
    or zero variance, or a share above ``NULL_COMPONENT`` of a near-null direction of the correlation matrix
    (eigenvalue below RANK_TOL^2 of the largest). The others keep their std (a traction limit's t_trac is
    determined to 1 mN m under constant torques far above it; its creep slope is not)."""
    n = cov.shape[0]
    with np.errstate(invalid="ignore"):
        d = np.sqrt(np.abs(np.diag(cov)))
    lost = ~(np.isfinite(d) & (d > 0))
    ok = np.flatnonzero(~lost)
    sub = cov[np.ix_(ok, ok)]
    if ok.size == 0 or not np.all(np.isfinite(sub)):
        return np.ones(n, bool)
    w, v = np.linalg.eigh(sub / np.outer(d[ok], d[ok]))
    null = w < RANK_TOL ** 2 * max(w.max(), 1e-300)
    if null.any():
        lost[ok[np.any(np.abs(v[:, null]) > NULL_COMPONENT, axis=1)]] = True
    if not lost.any():  # determined by these tests but not by ``_determined``: keep the old answer
        return np.ones(n, bool)
    return lost


# --- residual correlation: evidence and standard deviations that survive model-form error ----------

MAX_LAG_FRACTION = 0.25  # longest autocorrelation lag considered, fraction of the block length


def _autocorr(r: np.ndarray, max_lag: int) -> np.ndarray:
    """Autocorrelation rho_1..rho_max_lag of one residual series about zero, not about its mean (FFT):
    the residuals of a right model have zero mean, so an offset (an IMU bias left out) is structure."""
    n = len(r)
    f = np.fft.rfft(r, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[:max_lag + 1]
    return ac[1:] / ac[0] if ac[0] > 0 else np.zeros(max_lag)


def bandwidth(r: np.ndarray) -> int:
    """Lag (samples) after which a residual series is uncorrelated: the first lag whose
    autocorrelation falls below 0.05, at least 1, at most ``MAX_LAG_FRACTION`` of its length."""
    max_lag = max(1, int(MAX_LAG_FRACTION * len(r)))
    rho = _autocorr(r, max_lag)
    below = np.nonzero(rho < 0.05)[0]
    return int(below[0] + 1) if len(below) else max_lag


def correlation_factor(residuals: dict) -> float:
    """N / N_eff of the residuals: the variance inflation of sums of correlated residuals,
    1 + 2 sum_l (1 - l / (L + 1)) rho_l (Bartlett weights, L = ``bandwidth``), averaged over the
    (recording, channel) series weighted by their squared residuals; 1 for white residuals.

    Information criteria count every sample as independent; with correlated residuals (a model
    that is still wrong somewhere) their differences are inflated by about this factor."""
    num = den = 0.0
    for r in residuals.values():
        r = np.asarray(r, dtype=float)
        if len(r) < 8:
            continue
        L = bandwidth(r)
        rho = _autocorr(r, L)
        k = 1.0 + 2.0 * float(np.sum((1.0 - np.arange(1, L + 1) / (L + 1)) * rho))
        w = float(r @ r)
        num += w * max(k, 1.0)
        den += w
    return num / den if den > 0 else 1.0


def robust_std(recordings: list[DiagnosisData], fit: FitResult) -> dict[str, float]:
    """Standard deviations of the free parameters that hold when the residuals are correlated
    (model-form error): the Newey-West (HAC) sandwich (J^T J)^-1 M (J^T J)^-1 with the score
    autocovariances M summed per (recording, channel) up to its ``bandwidth`` with Bartlett weights.
    J by forward differences of the noise-weighted residuals. NaN where the data do not determine
    the parameters. For white residuals it equals the usual estimate."""
    # parameters the fit itself does not determine (std NaN) stay NaN; the sandwich is taken over the others
    # (a traction limit's creep slope that never acts gives a zero column and a singular J^T J)
    names = [n for n in fit.names if np.isfinite(fit.std.get(n, np.nan))]
    lost = {n: float("nan") for n in fit.names if n not in names}
    if not names:
        return lost
    base = weighted_residuals(recordings, fit.model, fit.sigma)
    keys = list(base)
    cols = []
    for n in names:
        x = fit.values[n]
        lo, hi = parameter_bounds(n)
        h = 1e-4 * max(abs(x), _typical(n))
        if x + h > hi:
            h = -h
        m = fit.model.with_values({n: x + h})  # the initial rates fitted at the estimate (a nuisance estimate)
        res = weighted_residuals(recordings, m, fit.sigma, [initial_state(d, m, rates_from=fit.model) for d in recordings])
        cols.append({k: (base[k] - res[k]) / h for k in keys})  # d(simulated)/d theta, in sigma units
    J = {k: np.column_stack([c[k] for c in cols]) for k in keys}
    A = sum(J[k].T @ J[k] for k in keys)
    meat = np.zeros_like(A)
    for k in keys:
        g = J[k] * base[k][:, None]  # score contributions, one row per sample
        L = bandwidth(base[k])
        m = g.T @ g
        for lag in range(1, L + 1):
            c = g[lag:].T @ g[:-lag]
            m += (1.0 - lag / (L + 1)) * (c + c.T)
        meat += m
    try:
        B = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return {**lost, **{n: float("nan") for n in names}}
    cov = B @ meat @ B
    gone = _undetermined(cov) if not _determined(cov) else np.zeros(len(names), bool)
    return {**lost, **{n: float("nan") if gone[i] else float(np.sqrt(max(cov[i, i], 0.0)))
                       for i, n in enumerate(names)}}
