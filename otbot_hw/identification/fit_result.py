"""The outcome of a prediction-error fit (``FitResult``): estimate, std, correlation, fit percent and noise
per channel, convergence with its reasons, likelihood, AIC/BIC (``prediction_error.fit_parameters``)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np


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
