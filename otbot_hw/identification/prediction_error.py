"""Generic prediction-error fit (Ljung): eps(p) = sum_k ||(y_k - y_k^pred(p)) / sigma||^2.

``fit_parameters`` works for any prediction model (see ``identification.model``):
named free parameters are estimated, all others stay at their ``base`` values.
y^pred is simulated under the zero-order-hold torques actually recorded; the
minimizer is ``scipy.optimize.least_squares(method="trf")`` with box bounds and
``x_scale``; the Jacobian is a finite difference whose columns are simulated in
one compiled batch call (``model.predict`` on a stack of parameter vectors).

Reported like MATLAB's nlgreyest/getpvec/compare:

* estimate and std from the Jacobian, Cov = (J^T W J)^-1, the noise variance of
  each channel estimated from its residuals (``noise="residuals"``, default) or
  taken as given (``noise="given"``);
* correlation matrix; fit percent per channel, 100 (1 - ||y - y^| / ||y - mean y||);
* convergence: the optimizer's status, no estimate stopped on a bound, and every
  channel's residual RMS within ``residual_tolerance`` times its noise sigma (widened
  by 1 + 2.5/sqrt(n) when sigma is the data's own noise-floor estimate) (a
  local minimum that does not explain the data to the noise floor is reported as
  not converged, never as an answer);
* identifiability: the Jacobian is checked for rank at the start and at the end;
  a deficient one raises ``NotIdentifiableError`` naming the parameters involved.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from otbot_hw.identification.errors import IdentificationError, NotIdentifiableError

#: Physical box bounds of the paper's parameters (SI); x_F, y_F use the platform radius.
DEFAULT_BOUNDS: dict[str, tuple[float, float]] = {
    "l1": (1e-3, 2.0), "l2": (1e-3, 2.0), "r": (1e-3, 1.0),
    "m_c": (1e-2, 5e3), "I_c": (1e-4, 1e3), "x_B": (-1.0, 1.0), "y_B": (-1.0, 1.0),
    "m_p": (1e-2, 5e3), "I_p": (1e-4, 1e3), "x_F": (-0.5, 0.5), "y_F": (-0.5, 0.5),
    "I_a": (1e-6, 10.0), "b_w": (0.0, 100.0), "b_p": (0.0, 100.0),
}
#: Typical magnitudes (parameter scaling when the guess is near zero).
TYPICAL_SCALE: dict[str, float] = {
    "l1": 0.1, "l2": 0.1, "r": 0.1, "m_c": 10.0, "I_c": 0.1, "x_B": 0.05, "y_B": 0.05,
    "m_p": 10.0, "I_p": 0.1, "x_F": 0.05, "y_F": 0.05, "I_a": 1e-3, "b_w": 0.01, "b_p": 0.01,
}

INTEGRATION_TOL = 1e-3  # largest integration error allowed in any output, in units of its noise sigma
RANK_TOL = 1e-5  # smallest singular value of the column-normalized Jacobian, relative
PRACTICAL_STD = 10.0  # std above this many times max(|value|, typical scale): not identifiable in practice


@dataclass
class FitResult:
    """Outcome of one prediction-error fit (values SI; per-channel keys are ``experiment/channel``)."""

    names: list[str]
    estimate: dict[str, float]
    std: dict[str, float]
    correlation: np.ndarray
    covariance: np.ndarray
    theta: np.ndarray                 # full parameter vector at the estimate (model.names order)
    guess: dict[str, float]
    fit_percent: dict[str, float]
    residual_rms: dict[str, float]
    sigma: dict[str, float]           # noise sigma used as weight
    sigma_estimated: dict[str, float]  # noise sigma estimated from the residuals
    residual_ratio: dict[str, float]  # residual RMS / sigma
    cost: float                       # 0.5 sum of weighted squared residuals
    n_residuals: int
    chi2_pvalue: float
    converged: bool
    optimizer_status: int
    message: str
    reasons: list[str]
    nfev: int
    njev: int
    simulations: int
    wall_time: float
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    samples: dict[str, int] = field(default_factory=dict)  # samples per experiment/channel
    predicted: list[dict[str, np.ndarray]] = field(default_factory=list, repr=False)

    @property
    def weighted_rss(self) -> dict[str, float]:
        """Sum of squared residuals / sigma^2 per ``experiment/channel`` (dimensionless)."""
        return {k: self.samples[k] * self.residual_ratio[k] ** 2 for k in self.residual_ratio}

    @property
    def log_likelihood(self) -> float:
        """Gaussian log-likelihood with each channel's noise variance at its ML value (RMS^2)."""
        return sum(-0.5 * self.samples[k] * (math.log(2 * math.pi * max(rms, 1e-300) ** 2) + 1.0)
                   for k, rms in self.residual_rms.items())

    @property
    def aic(self) -> float:
        """Akaike information criterion 2k - 2 log L (k = free parameters + one variance per channel)."""
        k = len(self.names) + len(self.residual_rms)
        return 2 * k - 2 * self.log_likelihood

    @property
    def bic(self) -> float:
        """Bayesian information criterion k ln(n) - 2 log L."""
        k = len(self.names) + len(self.residual_rms)
        return k * math.log(self.n_residuals) - 2 * self.log_likelihood

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no arrays of samples)."""
        return {
            "parameters": {n: {"value": self.estimate[n], "std": self.std[n]} for n in self.names},
            "guess": dict(self.guess),
            "correlation": {"names": list(self.names), "matrix": _finite(self.correlation).tolist()},
            "fit_percent": dict(self.fit_percent),
            "residual_rms": dict(self.residual_rms),
            "residual_ratio": dict(self.residual_ratio),
            "cost": self.cost, "n_residuals": self.n_residuals, "chi2_pvalue": self.chi2_pvalue,
            "aic": self.aic, "bic": self.bic,
            "converged": self.converged, "message": self.message, "reasons": list(self.reasons),
            "nfev": self.nfev, "njev": self.njev, "simulations": self.simulations, "wall_time": self.wall_time,
        }


def _finite(a: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(a), a, 0.0)


def full_vector(model, base: Any) -> np.ndarray:
    """The model's full parameter vector from an array, a mapping or an ``OtbotParams``."""
    if hasattr(base, "values") and callable(base.values) and not isinstance(base, Mapping):
        base = base.values()
    if isinstance(base, Mapping):
        missing = [n for n in model.names if n not in base]
        if missing:
            raise IdentificationError(f"base values missing for parameter(s) {', '.join(missing)}")
        return np.array([float(base[n]) for n in model.names])
    arr = np.asarray(base, dtype=float)
    if arr.shape != (len(model.names),):
        raise IdentificationError(f"base vector must have {len(model.names)} entries ({', '.join(model.names)})")
    return arr.copy()


class ResidualProblem:
    """Weighted residuals r(z) and their Jacobian for the free parameters z of ``model``.

    Predictions of the last point are cached, so ``least_squares`` calling the
    residual and then the Jacobian at the same point simulates only once more per
    free parameter (all in one batch call).
    """

    def __init__(self, model, experiments: Sequence, free: Sequence[str], theta_base: np.ndarray,
                 scale: np.ndarray, lower: np.ndarray, upper: np.ndarray, jacobian: str = "forward"):
        self.model = model
        self.experiments = list(experiments)
        self.free = list(free)
        self.idx = np.array([list(model.names).index(n) for n in free], dtype=int)
        self.theta_base = theta_base
        self.scale = scale
        self.lower, self.upper = lower, upper
        self.jacobian_kind = jacobian
        self.cols = [np.array([list(model.channels).index(c) for c in e.channels], dtype=int)
                     for e in self.experiments]
        self.meas = [np.stack([e.measured[c] for c in e.channels], axis=1) for e in self.experiments]
        self.w = [1.0 / np.array([e.sigma[c] for c in e.channels]) for e in self.experiments]
        self.simulations = 0
        self._cache_z: np.ndarray | None = None
        self._cache_pred: list[np.ndarray] | None = None

    def theta(self, z: np.ndarray) -> np.ndarray:
        th = self.theta_base.copy()
        th[self.idx] = z
        return th

    def _predict(self, thetas: np.ndarray) -> list[np.ndarray]:
        """Per experiment: predictions (m, n, n_channels) of the fitted channels."""
        self.simulations += len(thetas) * len(self.experiments)
        out = []
        for e, cols in zip(self.experiments, self.cols):
            out.append(self.model.predict(thetas, e)[:, :, cols])
        return out

    def predictions(self, z: np.ndarray) -> list[np.ndarray]:
        """Predicted channels (n, n_channels) per experiment at z (cached)."""
        z = np.asarray(z, dtype=float)
        if self._cache_z is None or not np.array_equal(z, self._cache_z):
            self._cache_pred = [p[0] for p in self._predict(self.theta(z)[None, :])]
            self._cache_z = z.copy()
        return self._cache_pred

    def residuals(self, z: np.ndarray) -> np.ndarray:
        preds = self.predictions(z)
        r = [((m - p) * w).ravel() for m, p, w in zip(self.meas, preds, self.w)]
        out = np.concatenate(r)
        if not np.all(np.isfinite(out)):
            return np.where(np.isfinite(out), out, 1e10)
        return out

    def jac(self, z: np.ndarray, kind: str | None = None, rel_step: float | None = None) -> np.ndarray:
        """d r / d z (n_res, n_free) by finite differences simulated in one batch."""
        kind = kind or self.jacobian_kind
        z = np.asarray(z, dtype=float)
        p = len(z)
        h = (rel_step or (1e-6 if kind == "forward" else 1e-4)) * self.scale
        th0 = self.theta(z)
        if kind == "forward":
            # step away from the nearer bound
            sign = np.where(z + h > self.upper, -1.0, 1.0)
            hs = h * sign
            thetas = np.repeat(th0[None, :], p, axis=0)
            thetas[np.arange(p), self.idx] += hs
            base = self.predictions(z)
            pert = self._predict(thetas)
            cols = []
            for b, pe, w in zip(base, pert, self.w):
                cols.append(-((pe - b[None]) * w[None, None, :]).reshape(p, -1) / hs[:, None])
        else:
            thetas = np.repeat(th0[None, :], 2 * p, axis=0)
            lo = np.maximum(z - h, self.lower)
            hi = np.minimum(z + h, self.upper)
            thetas[np.arange(p), self.idx] = hi
            thetas[p + np.arange(p), self.idx] = lo
            pert = self._predict(thetas)
            cols = []
            for pe, w in zip(pert, self.w):
                d = (pe[:p] - pe[p:]) * w[None, None, :]
                cols.append(-d.reshape(p, -1) / (hi - lo)[:, None])
        return np.concatenate(cols, axis=1).T


def integration_error(model, e, theta: np.ndarray, substeps: int) -> float:
    """Largest |y(substeps) - y(2 substeps)| / sigma over the fitted channels of experiment e."""
    cols = np.array([list(model.channels).index(c) for c in e.channels], dtype=int)
    sig = np.array([e.sigma[c] for c in e.channels])
    old = e.substeps
    try:
        e.substeps = substeps
        y1 = model.predict(theta[None, :], e)[0][:, cols]
        e.substeps = 2 * substeps
        y2 = model.predict(theta[None, :], e)[0][:, cols]
    finally:
        e.substeps = old
    err = np.abs(y1 - y2) / sig
    return float(np.max(err)) if np.all(np.isfinite(err)) else float("inf")


def tune_substeps(model, e, theta: np.ndarray, tol: float = INTEGRATION_TOL, max_substeps: int = 256) -> int:
    """Fewest RK4 steps per sample interval whose integration error stays below ``tol`` sigma.

    The error of RK4 with s steps is estimated by comparing with 2 s steps (it is
    16/15 of that difference); s doubles from ``e.substeps // 8`` (at least 1).
    """
    s = max(1, e.substeps // 8) if e.auto_substeps else e.substeps
    while s < max_substeps and integration_error(model, e, theta, s) > tol:
        s *= 2
    e.substeps = s
    return s


def rank_check(J: np.ndarray, names: Sequence[str], tol: float = RANK_TOL) -> list[list[str]]:
    """Groups of parameters whose Jacobian columns are zero or linearly dependent (empty: full rank)."""
    norms = np.linalg.norm(J, axis=0)
    groups: list[list[str]] = []
    top = norms.max() if len(norms) else 0.0
    if top == 0.0 or not np.isfinite(top):
        return [list(names)]
    zero = norms <= 1e-10 * top
    for i in np.nonzero(zero)[0]:
        groups.append([names[i]])
    keep = np.nonzero(~zero)[0]
    if len(keep) > 1:
        Jn = J[:, keep] / norms[keep]
        _, s, vt = np.linalg.svd(Jn, full_matrices=False)
        for k in np.nonzero(s < tol * s[0])[0]:
            v = np.abs(vt[k])
            groups.append([names[keep[i]] for i in np.nonzero(v > 0.2 * v.max())[0]])
    return groups


def _unidentifiable_message(groups: list[list[str]], experiments, explain) -> tuple[str, list[str]]:
    involved = sorted({n for g in groups for n in g}, key=lambda n: [m for g in groups for m in g].index(n))
    reason = explain(involved, experiments) if explain else None
    if not reason:
        reason = ("their effects on the measured outputs are zero or cancel each other in this experiment; "
                  "it needs an excitation that moves them independently")
    return f"{', '.join(involved)} not identifiable: {reason}", involved


def fit_parameters(model, experiments: Sequence, free: Sequence[str], base: Any,
                   guess: Mapping[str, float] | None = None,
                   bounds: Mapping[str, tuple[float, float]] | None = None,
                   scale: Mapping[str, float] | None = None, noise: str = "residuals",
                   jacobian: str = "forward", max_nfev: int = 200, residual_tolerance: float | None = 1.5,
                   explain: Callable[[list[str], Sequence], str | None] | None = None,
                   check_identifiability: bool = True, tol: float = 1e-10,
                   covariance_jacobian: str = "forward",
                   integration_tol: float | None = INTEGRATION_TOL,
                   sigma: Mapping[str, float] | None = None) -> FitResult:
    """Estimate ``free`` parameters of ``model`` from ``experiments`` by prediction-error minimization.

    model: has ``names``, ``channels``, ``predict(thetas, experiment)``.
    experiments: ``Experiment`` objects (measured channels, sigma weights, x0, torques).
    base: full parameter set (mapping / ``OtbotParams`` / vector) giving the fixed values.
    guess: start of the free parameters (default: their base values).
    bounds, scale: per name (defaults ``DEFAULT_BOUNDS`` / ``TYPICAL_SCALE``; names the
        defaults do not know need both; a bound may be infinite).
    noise: "residuals" (each channel's noise variance estimated from its residuals) or
        "given" (the experiments' sigma, or ``sigma``).
    jacobian: "forward" or "central" differences during the iterations;
        covariance_jacobian: the same for the reported covariance.
    residual_tolerance: largest residual RMS / sigma accepted as converged (None: no test).
    integration_tol: for experiments with automatic ``substeps``, the RK4 step is the
        longest whose integration error stays below this many sigmas in every output
        (checked at the guess and at the estimate; None: the simulator's default step).
    sigma: per-channel noise sigma overriding the experiments' own.
    explain(names, experiments) -> why those parameters cannot be identified (message).
    Raises ``IdentificationError`` for bad input, ``NotIdentifiableError`` for a
    rank-deficient Jacobian (at the guess, or at a fit that explains the data).
    """
    t0 = time.perf_counter()
    experiments = list(experiments)
    if not experiments:
        raise IdentificationError("no experiment to fit")
    if sigma:
        import copy

        for c, v in sigma.items():
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise IdentificationError(f"sigma of channel {c} must be a finite number > 0, got {v!r}")
        experiments = [copy.copy(e) for e in experiments]
        for e in experiments:
            e.sigma = {c: float(sigma.get(c, e.sigma[c])) for c in e.channels}
            e.sigma_source = {c: "given" if c in sigma else e.sigma_source.get(c, "") for c in e.channels}
    free = list(free)
    if not free:
        raise IdentificationError("no free parameter to estimate")
    unknown = [n for n in free if n not in model.names]
    if unknown:
        raise IdentificationError(f"unknown parameter(s) {', '.join(unknown)} (model has {', '.join(model.names)})")
    if len(set(free)) != len(free):
        raise IdentificationError("free parameters listed twice")
    if noise not in ("residuals", "given"):
        raise IdentificationError(f"noise must be 'residuals' or 'given', got {noise!r}")
    for e in experiments:
        for c in e.channels:
            if c not in model.channels:
                raise IdentificationError(f"{e.name}: the model does not predict channel {c}")
    theta_base = full_vector(model, base)
    g = {n: float(theta_base[list(model.names).index(n)]) for n in free}
    for n, v in (guess or {}).items():
        if n not in g:
            raise IdentificationError(f"guess for '{n}', which is not a free parameter ({', '.join(free)})")
        if not math.isfinite(float(v)):
            raise IdentificationError(f"guess for '{n}' must be finite, got {v}")
        g[n] = float(v)
    bnd: dict[str, tuple[float, float]] = {}
    for n in free:
        b = (bounds or {}).get(n, DEFAULT_BOUNDS.get(n))
        if b is None:
            raise IdentificationError(f"no bounds for parameter '{n}': pass bounds={{'{n}': (lo, hi)}}")
        lo, hi = float(b[0]), float(b[1])
        if not lo < hi:
            raise IdentificationError(f"bounds of '{n}' must satisfy lo < hi, got ({lo}, {hi})")
        bnd[n] = (lo, hi)
    lower = np.array([bnd[n][0] for n in free])
    upper = np.array([bnd[n][1] for n in free])
    sc = np.array([float((scale or {}).get(n, max(abs(g[n]), TYPICAL_SCALE.get(n, 0.0)) or 1.0)) for n in free])
    z0 = np.array([g[n] for n in free])
    span = upper - lower
    margin = np.where(np.isfinite(span), 1e-6 * span, 0.0)  # half-open bounds: no margin needed
    bad = (z0 < lower) | (z0 > upper)
    if bad.any():
        i = int(np.argmax(bad))
        raise IdentificationError(f"guess {free[i]} = {z0[i]} lies outside its bounds [{lower[i]}, {upper[i]}]")
    z0 = np.clip(z0, lower + margin, upper - margin)
    n_res = sum(len(e) * len(e.channels) for e in experiments)
    if n_res <= len(free):
        raise IdentificationError(f"{n_res} measured values cannot determine {len(free)} parameters: "
                                  "recording too short or too few channels")
    if integration_tol is not None:
        th0 = theta_base.copy()
        th0[[list(model.names).index(n) for n in free]] = z0
        for e in experiments:
            if e.auto_substeps:
                tune_substeps(model, e, th0, integration_tol)
    prob = ResidualProblem(model, experiments, free, theta_base, sc, lower, upper, jacobian)
    first = [True]

    def jac(z: np.ndarray) -> np.ndarray:
        J = prob.jac(z)
        if first[0] and check_identifiability:
            # structural identifiability, checked on the first Jacobian (at the guess)
            first[0] = False
            groups = rank_check(J, free)
            if groups:
                msg, involved = _unidentifiable_message(groups, experiments, explain)
                raise NotIdentifiableError(msg, involved)
        return J

    sol = least_squares(prob.residuals, z0, jac=jac, bounds=(lower, upper), x_scale=sc, method="trf",
                        max_nfev=max_nfev, ftol=tol, xtol=tol, gtol=tol)
    z = sol.x
    if integration_tol is not None:
        # the step tuned at the guess must also be fine at the estimate; if not, refine and refit
        th = prob.theta(z)
        finer = [e for e in experiments if e.auto_substeps and integration_error(model, e, th, e.substeps) > integration_tol]
        if finer:
            for e in finer:
                tune_substeps(model, e, th, integration_tol)
            prob._cache_z = None
            sol = least_squares(prob.residuals, z, jac=jac, bounds=(lower, upper), x_scale=sc, method="trf",
                                max_nfev=max_nfev, ftol=tol, xtol=tol, gtol=tol)
            z = sol.x
    r = prob.residuals(z)
    if covariance_jacobian == jacobian and np.array_equal(sol.x, z) and np.shape(sol.jac) == (len(r), len(free)):
        J = np.asarray(sol.jac)  # trf's last Jacobian is the same finite difference at the estimate
    else:
        J = prob.jac(z, covariance_jacobian)
    groups = rank_check(J, free) if check_identifiability else []
    # per-channel residual statistics and noise estimates
    preds = prob.predictions(z)
    fitp, rms, ratio, sig_used, sig_est, predicted = {}, {}, {}, {}, {}, []
    n_free = len(free)
    row_scale = []  # per experiment: (n_channels,) factor 1 / (estimated sigma / weight sigma)
    for e, p in zip(experiments, preds):
        fac = np.ones(len(e.channels))
        predicted.append({c: p[:, j].copy() for j, c in enumerate(e.channels)})
        for j, c in enumerate(e.channels):
            key = f"{e.name}/{c}"
            y = e.measured[c]
            res = y - p[:, j]
            den = np.linalg.norm(y - y.mean())
            fitp[key] = float(100.0 * (1.0 - np.linalg.norm(res) / den)) if den > 0 else float("nan")
            rms[key] = float(np.sqrt(np.mean(res ** 2)))
            sig_used[key] = float(e.sigma[c])
            dof_frac = max(1.0 - n_free / n_res, 1e-3)
            sig_est[key] = float(np.sqrt(np.mean(res ** 2) / dof_frac))
            ratio[key] = rms[key] / e.sigma[c]
            f = sig_est[key] / e.sigma[c] if noise == "residuals" else 1.0
            fac[j] = 1.0 / max(f, 1e-12)
        row_scale.append(fac)
    # rows of J are ordered experiment by experiment, sample-major with channels inner
    rs = np.concatenate([np.tile(fac, len(e)) for fac, e in zip(row_scale, experiments)])
    Jw = J * rs[:, None]
    try:
        cov = np.linalg.inv(Jw.T @ Jw)
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(Jw.T @ Jw)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    chi2 = float(r @ r)
    dof = n_res - n_free
    pval = float(stats.chi2.sf(chi2, dof))
    reasons: list[str] = []
    if sol.status <= 0:
        reasons.append(f"optimizer stopped without converging: {sol.message}")
    tol_b = 1e-4 * sc
    for i, n in enumerate(free):
        if z[i] - lower[i] <= tol_b[i] and lower[i] > -np.inf:
            reasons.append(f"{n} stopped at its lower bound {lower[i]:g}")
        if upper[i] - z[i] <= tol_b[i] and upper[i] < np.inf:
            reasons.append(f"{n} stopped at its upper bound {upper[i]:g}")
    if residual_tolerance is not None:
        for e in experiments:
            for c in e.channels:
                key = f"{e.name}/{c}"
                lim = residual_tolerance
                if e.sigma_source.get(c, "").startswith("noise floor"):
                    lim *= 1.0 + 2.5 / math.sqrt(len(e))  # the floor itself is an estimate
                if not ratio[key] <= lim:
                    reasons.append(f"{key}: residual RMS is {ratio[key]:.2f} x the noise sigma {sig_used[key]:.3g} "
                                   f"(limit {lim:.2f}): a local minimum or a model that misses physics")
    if check_identifiability and not groups:
        typical = np.array([max(abs(z[i]), TYPICAL_SCALE.get(n, 0.0)) for i, n in enumerate(free)])
        loose = [n for i, n in enumerate(free) if not std[i] <= PRACTICAL_STD * typical[i]]
        if loose:
            groups = [loose]
    if groups:
        msg, involved = _unidentifiable_message(groups, experiments, explain)
        if not reasons:
            # the data are explained but the parameters are not determined by them
            raise NotIdentifiableError(msg, involved)
        reasons.append(msg)
    est = {n: float(z[i]) for i, n in enumerate(free)}
    return FitResult(
        names=free, estimate=est, std={n: float(std[i]) for i, n in enumerate(free)}, correlation=corr,
        covariance=cov, theta=prob.theta(z), guess=g, fit_percent=fitp, residual_rms=rms, sigma=sig_used,
        sigma_estimated=sig_est, residual_ratio=ratio, cost=float(0.5 * chi2), n_residuals=n_res,
        chi2_pvalue=pval, converged=not reasons, optimizer_status=int(sol.status), message=str(sol.message),
        reasons=reasons, nfev=int(sol.nfev), njev=int(sol.njev or 0), simulations=prob.simulations,
        wall_time=time.perf_counter() - t0, bounds=bnd, predicted=predicted,
        samples={f"{e.name}/{c}": len(e) for e in experiments for c in e.channels})


def cramer_rao_std(model, experiments: Sequence, free: Sequence[str], theta: Any,
                   sigma: Mapping[str, float] | None = None) -> dict[str, float]:
    """Cramer-Rao lower bound on the std of each free parameter at ``theta`` (the truth).

    Fisher information F = J^T Sigma^-1 J of the output predictions for white Gaussian
    noise with the experiments' sigma (or ``sigma`` per channel); bound = sqrt(diag F^-1).
    """
    theta = full_vector(model, theta)
    exps = []
    for e in experiments:
        if sigma:
            import copy

            e = copy.copy(e)
            e.sigma = {c: float(sigma.get(c, e.sigma[c])) for c in e.channels}
        exps.append(e)
    idx = [list(model.names).index(n) for n in free]
    z = theta[idx]
    sc = np.array([max(abs(v), TYPICAL_SCALE.get(n, 1e-3)) for v, n in zip(z, free)])
    prob = ResidualProblem(model, exps, free, theta, sc, np.full(len(z), -np.inf), np.full(len(z), np.inf))
    J = prob.jac(z, "central")
    cov = np.linalg.inv(J.T @ J)
    return {n: float(np.sqrt(cov[i, i])) for i, n in enumerate(free)}
