"""The weighted least-squares problem of a prediction-error fit: residuals r(z) of the free parameters z
and their Jacobian by finite differences simulated in one compiled batch (``ResidualProblem``), the
integration accuracy tuned to the noise (``tune_substeps``), and the Jacobian's rank check naming the
parameters that cannot be told apart (``rank_check``). Used by ``prediction_error``, ``uncertainty``,
``design``.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from otbot_hw.identification.errors import IdentificationError

INTEGRATION_TOL = 1e-3  # largest integration error allowed in any output, in units of its noise sigma
RANK_TOL = 1e-5  # smallest singular value of the column-normalized Jacobian, relative


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
