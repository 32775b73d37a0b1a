"""Quality gates of one identification step: pass, or redo with the reason in words.

A step passes when all five hold:

* **converged**: the fit's own verdict (optimizer converged, no estimate on a bound,
  residual RMS of every channel within 1.5 sigma of its noise, ``prediction_error``);
* **fit**: every channel's fit percent, 100 (1 - ||y - y_pred|| / ||y - mean y||), reaches
  what residuals of ``fit_noise_factor`` times the channel's noise sigma would give (the
  model explains the channel down to its noise);
* **excitation**: the best-moved channel of every run allows a fit of at least
  ``min_fit_percent`` (the robot moved well above the sensor noise);
* **Cramer-Rao**: each parameter's std is within a factor ``crb_factor`` of its Cramer-Rao
  bound, computed from the model at the estimate and the *stated* sensor noise (the
  recording's ``noise`` metadata): a std far above the bound means the residuals are
  larger than the sensors' noise (missing physics, disturbances), far below means the
  stated noise is too pessimistic; either way the std cannot be trusted;
* **whiteness**: the residuals of every channel pass the Ljung-Box test (statsmodels)
  over min(``max_lags``, n/5) lags at level ``whiteness_alpha``: correlated residuals mean
  unmodelled dynamics or coloured sensor noise, and a std computed for white noise
  is then too small.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np


@dataclass(frozen=True)
class GateLimits:
    """Thresholds of the gates (dimensionless).

    fit_noise_factor: a channel's fit percent must reach that of a model whose residuals
    are this many times the channel's noise sigma, 100 (1 - f sigma / std(y));
    min_fit_percent: the best-moved channel of every run must reach this fit percent;
    crb_factor: std / Cramer-Rao bound within [1/f, f]; whiteness_alpha, max_lags: Ljung-Box.
    """

    fit_noise_factor: float = 1.3
    min_fit_percent: float = 50.0
    crb_factor: float = 1.5
    whiteness_alpha: float = 1e-3
    max_lags: int = 20


@dataclass
class GateCheck:
    """One check: ``gate`` (converged, fit, cramer_rao, whiteness) on ``subject`` (channel, parameter or step)."""

    gate: str
    subject: str
    passed: bool
    value: float | None
    limit: str
    message: str

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if d["value"] is not None and not math.isfinite(d["value"]):
            d["value"] = None
        return d


@dataclass
class StepGates:
    """The gates of one step; ``verdict`` is "pass" or "redo", ``reasons`` the failed checks in words."""

    step: str
    checks: list[GateCheck] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.checks)

    @property
    def verdict(self) -> str:
        return "pass" if self.passed else "redo"

    @property
    def reasons(self) -> list[str]:
        return [c.message for c in self.checks if not c.passed]

    def to_dict(self) -> dict[str, Any]:
        return {"step": self.step, "verdict": self.verdict, "reasons": self.reasons,
                "checks": [c.to_dict() for c in self.checks]}


def residuals(fit, experiments: Sequence) -> dict[str, np.ndarray]:
    """Measured minus predicted samples per ``experiment/channel`` of a fit of ``experiments``."""
    out = {}
    for e, pred in zip(experiments, fit.predicted):
        for c in e.channels:
            out[f"{e.name}/{c}"] = e.measured[c] - pred[c]
    return out


def ljung_box(r: np.ndarray, max_lags: int = 20) -> tuple[float, float, int]:
    """(Q, p-value, lags) of the Ljung-Box test on the residual series ``r`` (lags = min(max_lags, n/5))."""
    from statsmodels.stats.diagnostic import acorr_ljungbox

    r = np.asarray(r, dtype=float)
    lags = max(1, min(int(max_lags), len(r) // 5))
    tab = acorr_ljungbox(r - r.mean(), lags=[lags])
    return float(tab["lb_stat"].iloc[0]), float(tab["lb_pvalue"].iloc[0]), lags


def check_step(res, limits: GateLimits | None = None, crb: Mapping[str, float] | None = None) -> StepGates:
    """The gates on a ``steps.StepResult``'s own fit (``crb`` per free parameter, default computed at the estimate)."""
    from otbot_hw.identification.model import OtbotModel

    return check_fit(res.step, res.fit, res.experiments, OtbotModel(), symbol=res.symbol, crb=crb, limits=limits,
                     converged=res.converged, reasons=res.reasons or res.fit.reasons)


def check_fit(step: str, fit, experiments: Sequence, model, params: Sequence[str] | None = None,
              only: Sequence[str] | None = None, symbol: Callable[[str], str] = str,
              crb: Mapping[str, float] | None = None, limits: GateLimits | None = None,
              converged: bool | None = None, reasons: Sequence[str] = ()) -> StepGates:
    """The gates of ``step`` on a prediction-error ``fit`` of ``experiments`` with ``model``.

    params: the step's parameters among ``fit.names`` (default all); only: names of the
    step's experiments among ``experiments`` (default all; a session's joint fit covers
    earlier steps too); crb: Cramer-Rao bound per parameter (default: computed with
    ``model`` at the estimate for the experiments' stated noise, all of ``fit.names`` free).
    """
    from otbot_hw.identification.prediction_error import cramer_rao_std

    lim = limits or GateLimits()
    params = list(params or fit.names)
    conv = fit.converged if converged is None else converged
    mine = [e for e in experiments if only is None or e.name in only]
    g = StepGates(step)
    g.checks.append(GateCheck("converged", step, bool(conv), None, "fit converged",
                              "converged" if conv else
                              f"step {step}: the fit did not converge: " + "; ".join(reasons or fit.reasons)))
    for e in mine:
        best = -math.inf
        for c in e.channels:
            key = f"{e.name}/{c}"
            fp = fit.fit_percent.get(key, float("nan"))
            spread = float(np.std(e.measured[c]))
            expect = 100.0 * (1.0 - lim.fit_noise_factor * e.sigma[c] / spread) if spread > 0 else -math.inf
            best = max(best, 100.0 * (1.0 - e.sigma[c] / spread) if spread > 0 else -math.inf)
            ok = bool(fp >= expect)
            msg = (f"{key}: fit {fp:.1f} % (noise allows {100.0 * (1.0 - e.sigma[c] / spread):.1f} %)" if ok else
                   f"{key}: fit {fp:.1f} % is below {expect:.1f} %, what residuals of {lim.fit_noise_factor:g} x the "
                   f"noise sigma would give: the model does not explain this channel (wrong fixture, wrong known "
                   f"parameters, missing physics)")
            g.checks.append(GateCheck("fit", key, ok, fp, f">= {expect:.1f} %", msg))
        ok = bool(best >= lim.min_fit_percent)
        msg = (f"{e.name}: the best-moved channel allows a fit of {best:.1f} %" if ok else
               f"{e.name}: the robot barely moved: even a perfect model would fit at most {best:.1f} % "
               f"(limit {lim.min_fit_percent:g} %) against the sensor noise: excite more (larger torques, "
               "longer run) or check that the drives were enabled")
        g.checks.append(GateCheck("excitation", e.name, ok, best, f">= {lim.min_fit_percent:g} %", msg))
    if conv:
        bound = dict(crb) if crb is not None else cramer_rao_std(model, experiments, fit.names, fit.theta)
        for n in params:
            sd = fit.std[n]
            ratio = sd / bound[n] if bound[n] > 0 else float("inf")
            ok = bool(1.0 / lim.crb_factor <= ratio <= lim.crb_factor)
            if ok:
                msg = f"{symbol(n)}: std {sd:.3g} is {ratio:.2f} x its Cramer-Rao bound {bound[n]:.3g}"
            elif ratio > lim.crb_factor:
                msg = (f"{symbol(n)}: std {sd:.3g} is {ratio:.2f} x its Cramer-Rao bound {bound[n]:.3g} "
                       f"(limit {lim.crb_factor:g}): the residuals exceed the stated sensor noise "
                       "(missing physics or disturbances during the run)")
            else:
                msg = (f"{symbol(n)}: std {sd:.3g} is only {ratio:.2f} x its Cramer-Rao bound {bound[n]:.3g} "
                       f"(limit 1/{lim.crb_factor:g}): the residuals are smaller than the stated sensor noise "
                       "(noise levels in the recording's metadata too pessimistic)")
            g.checks.append(GateCheck("cramer_rao", symbol(n), ok, ratio,
                                      f"[{1 / lim.crb_factor:.3g}, {lim.crb_factor:g}] x bound", msg))
    for key, r in residuals(fit, experiments).items():
        if only is not None and key.split("/")[0] not in only:
            continue
        q, p, lags = ljung_box(r, lim.max_lags)
        ok = bool(p >= lim.whiteness_alpha)
        if ok:
            msg = f"{key}: residuals white (Ljung-Box Q {q:.1f} over {lags} lags, p {p:.3g})"
        else:
            rho1 = float(np.corrcoef(r[:-1], r[1:])[0, 1]) if len(r) > 2 else float("nan")
            msg = (f"{key}: residuals are correlated (Ljung-Box Q {q:.1f} over {lags} lags, p {p:.2g} < "
                   f"{lim.whiteness_alpha:g}; lag-1 autocorrelation {rho1:.2f}): unmodelled dynamics or "
                   "coloured sensor noise, the std (computed for white noise) would be too small")
        g.checks.append(GateCheck("whiteness", key, ok, p, f"p >= {lim.whiteness_alpha:g}", msg))
    return g
