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

Its parts: ``residual_problem`` (residuals, batch Jacobian, integration accuracy, rank check) and
``fit_result`` (``FitResult``); here the fit itself and the Cramer-Rao bound (``cramer_rao_std``).
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from otbot_hw.identification.errors import IdentificationError, NotIdentifiableError
from otbot_hw.identification.fit_result import FitResult
from otbot_hw.identification.residual_problem import (INTEGRATION_TOL, ResidualProblem, full_vector, integration_error,
                                                      rank_check, tune_substeps)

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

PRACTICAL_STD = 10.0  # std above this many times max(|value|, the fit's scale of it): not identifiable in practice


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
        # against the parameter's own magnitude, never the estimate alone: a centre of mass at 0 m has a std
        # of a millimetre that is a good estimate, not a loose one (``sc``: the fit's scale of each parameter,
        # ``scale`` or ``TYPICAL_SCALE``; session names such as y_F0 are not in ``TYPICAL_SCALE``)
        typical = np.maximum(np.abs(z), sc)
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
