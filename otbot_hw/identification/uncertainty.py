"""Uncertainty across identification steps: the session's parameters, their joint model and covariance.

The paper's steps are chained: step 2 (chassis) fixes I_a, b_w, I_p0, b_p at step 1's
estimates, step 3 (platform) fixes steps 1-2. Each step's own std (``FitResult.std``)
treats those values as exact, so on a robot that differs from nominal the chassis
estimates miss by 5-10 of their stated sigmas (``benchmarks/bench_accuracy.py``).
Two ways to carry the earlier uncertainty, both here:

* **propagation** (``propagate_step``): linearize the estimator of a step around its
  estimate. Gauss-Newton gives theta_F - theta_F* = A e - S (theta_O - theta_O*) with
  S = (J_F^T J_F)^-1 J_F^T J_O, J_F (J_O) the weighted output sensitivities to the
  step's free (the earlier, fixed) parameters, so
      Cov_FF = C_F + S Cov_OO S^T,   Cov_FO = -S Cov_OO,
  C_F the step's own (noise) covariance. Applied step after step it builds the full
  covariance of all estimates, the steps' estimates unchanged.
* **joint fit** (``joint_fit``): one prediction-error fit of every recording of every
  step together, all session parameters free, started at the chained estimates.
  Its covariance (J^T W J)^-1 is the joint one directly, and the recordings of later
  steps also inform earlier parameters (the floor runs carry information on b_p).

Parameters taken for granted (paper §4.3.1: l1, l2, r and the unloaded platform's
m_p0, x_F0, y_F0) may carry a std (``known_std``); both methods add it by the same
propagation. ``SessionModel`` is the prediction model both use: the session's
parameter vector mapped, per experiment, onto the paper's model (the unloaded
platform m_p0, I_p0, x_F0, y_F0 in the wheel, pivot and chassis runs; the loaded
working platform m_p, I_p, x_F, y_F in the platform runs).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping, Sequence

import numpy as np

from otbot_hw.identification.model import CHANNELS, OtbotModel
from otbot_hw.identification.fit_result import FitResult
from otbot_hw.identification.prediction_error import DEFAULT_BOUNDS, TYPICAL_SCALE, fit_parameters
from otbot_hw.identification.residual_problem import ResidualProblem
from otbot_hw.params import PARAM_NAMES, OtbotParams

#: Parameters a bench session identifies, by the paper's symbols (I_p0: unloaded platform about the pivot).
SESSION_PARAMS: tuple[str, ...] = ("I_a", "b_w", "I_p0", "b_p", "m_c", "I_c", "x_B", "y_B",
                                   "m_p", "I_p", "x_F", "y_F")
#: Parameters taken for granted (measured), with the unloaded platform's mass and centre of mass.
KNOWN_PARAMS: tuple[str, ...] = ("l1", "l2", "r", "m_p0", "x_F0", "y_F0")
#: The unloaded platform's centre of mass: estimated by the joint fit as nuisance parameters once an unloaded
#: floor run (chassis) is in the session (the platform's first moment m_p0 (x_F0, y_F0) turns with the pivot
#: relative to the chassis, so the floor runs tell it apart from the chassis' m_c (x_B, y_B)).
NUISANCE_PARAMS: tuple[str, ...] = ("x_F0", "y_F0")
#: Which session parameters each step estimates.
STEP_PARAMS: dict[str, tuple[str, ...]] = {
    "wheel": ("I_a", "b_w"), "pivot": ("I_p0", "b_p"),
    "chassis": ("m_c", "I_c", "x_B", "y_B"), "platform": ("m_p", "I_p", "x_F", "y_F"),
}
#: Steps whose platform carries the load (all others run with the unloaded platform).
LOADED_STEPS = ("platform",)
#: The paper model's platform names filled from the unloaded platform in unloaded runs.
UNLOADED_PLATFORM = {"m_p": "m_p0", "I_p": "I_p0", "x_F": "x_F0", "y_F": "y_F0"}
#: Typical magnitudes of every session name (finite-difference steps, fit scaling).
_SCALE = {**TYPICAL_SCALE, **{u: TYPICAL_SCALE[n] for n, u in UNLOADED_PLATFORM.items()}}


def session_vector(unloaded: OtbotParams, loaded: OtbotParams | None = None) -> dict[str, float]:
    """Session values (``SESSION_PARAMS`` + ``KNOWN_PARAMS``) from the unloaded robot and its loaded platform."""
    loaded = loaded or unloaded
    v = {n: float(getattr(unloaded, n)) for n in ("I_a", "b_w", "b_p", "m_c", "I_c", "x_B", "y_B", "l1", "l2", "r")}
    v.update(I_p0=unloaded.I_p, m_p0=unloaded.m_p, x_F0=unloaded.x_F, y_F0=unloaded.y_F)
    v.update({n: float(getattr(loaded, n)) for n in ("m_p", "I_p", "x_F", "y_F")})
    return v


def robot_params(values: Mapping[str, float], template: OtbotParams, loaded: bool = True,
                 std: Mapping[str, float] | None = None) -> OtbotParams:
    """The paper's parameter set from session values: the loaded working platform (``loaded``) or the unloaded one.

    ``std`` (session symbols) becomes the parameter set's std, the unloaded platform's I_p0
    reported as I_p when ``loaded`` is False.
    """
    names = [n for n in PARAM_NAMES if n not in UNLOADED_PLATFORM] + list(UNLOADED_PLATFORM)
    src = {n: (n if loaded or n not in UNLOADED_PLATFORM else UNLOADED_PLATFORM[n]) for n in names}
    out_std = {n: float(std[s]) for n, s in src.items() if std and s in std}
    return template.replace(**{n: float(values[s]) for n, s in src.items()}, std=out_std)


class SessionModel:
    """The paper's model over the session's parameters (``names``), loaded or not per experiment.

    loaded_experiments: names of the experiments made with the load on the platform.
    """

    names: tuple[str, ...] = SESSION_PARAMS + KNOWN_PARAMS
    channels: tuple[str, ...] = CHANNELS

    def __init__(self, loaded_experiments: Iterable[str] = ()):
        self.loaded = frozenset(loaded_experiments)
        self._inner = OtbotModel()
        idx = {n: i for i, n in enumerate(self.names)}
        self._map_unloaded = np.array([idx[UNLOADED_PLATFORM.get(n, n)] for n in PARAM_NAMES])
        self._map_loaded = np.array([idx[n] for n in PARAM_NAMES])

    def paper_vectors(self, thetas: np.ndarray, experiment) -> np.ndarray:
        """(m, 14) parameter rows of the paper's model for the experiment."""
        mp = self._map_loaded if experiment.name in self.loaded else self._map_unloaded
        return np.atleast_2d(thetas)[:, mp]

    def predict(self, thetas: np.ndarray, experiment) -> np.ndarray:
        return self._inner.predict(self.paper_vectors(thetas, experiment), experiment)


def session_bounds(radius: float) -> tuple[dict[str, tuple[float, float]], dict[str, float]]:
    """Box bounds and typical scales of the session parameters (the step fits' defaults)."""
    b = {n: DEFAULT_BOUNDS[n] for n in SESSION_PARAMS if n in DEFAULT_BOUNDS}
    b["I_p0"] = DEFAULT_BOUNDS["I_p"]
    b["m_p0"] = DEFAULT_BOUNDS["m_p"]
    b.update({n: DEFAULT_BOUNDS[n] for n in ("l1", "l2", "r")})
    b["x_F"] = b["y_F"] = b["x_F0"] = b["y_F0"] = (-radius, radius)
    return b, {n: _SCALE[n] for n in SESSION_PARAMS + KNOWN_PARAMS}


@dataclass
class JointCovariance:
    """Covariance of a set of named parameters (session symbols), grown step by step."""

    names: list[str]
    matrix: np.ndarray

    @classmethod
    def empty(cls) -> "JointCovariance":
        return cls([], np.zeros((0, 0)))

    def std(self) -> dict[str, float]:
        return {n: float(np.sqrt(max(self.matrix[i, i], 0.0))) for i, n in enumerate(self.names)}

    def sub(self, names: Sequence[str]) -> np.ndarray:
        """Covariance of ``names`` (zero rows/columns for names not held)."""
        out = np.zeros((len(names), len(names)))
        pos = [self.names.index(n) if n in self.names else -1 for n in names]
        for a, i in enumerate(pos):
            for b, j in enumerate(pos):
                if i >= 0 and j >= 0:
                    out[a, b] = self.matrix[i, j]
        return out

    def correlation(self) -> np.ndarray:
        s = np.sqrt(np.maximum(np.diag(self.matrix), 0.0))
        with np.errstate(invalid="ignore", divide="ignore"):
            c = self.matrix / np.outer(s, s)
        return np.where(np.isfinite(c), c, 0.0)


def sensitivities(model: SessionModel, experiments: Sequence, names: Sequence[str],
                  values: Mapping[str, float]) -> np.ndarray:
    """Weighted output sensitivities d r / d theta (n_residuals, len(names)) by central differences.

    Rows are the residuals (y - y_pred) / sigma of the experiments, stacked as the fitter stacks them.
    """
    theta = np.array([float(values[n]) for n in model.names])
    z = np.array([float(values[n]) for n in names])
    sc = np.array([max(abs(v), _SCALE[n]) for v, n in zip(z, names)])
    inf = np.full(len(z), np.inf)
    prob = ResidualProblem(model, experiments, list(names), theta, sc, -inf, inf)
    return prob.jac(z, "central")


def propagate_step(cov: JointCovariance, free: Sequence[str], step_cov: np.ndarray, model: SessionModel,
                   experiments: Sequence, values: Mapping[str, float]) -> tuple[JointCovariance, np.ndarray]:
    """Add a step's estimates ``free`` (own noise covariance ``step_cov``) to ``cov``.

    The step fixed every parameter held in ``cov`` at ``values``; their uncertainty
    enters through S = (J_F^T J_F)^-1 J_F^T J_O (see the module docstring). Returns the
    grown covariance (old names, then ``free``) and S (len(free), len(cov.names)).
    """
    old = [n for n in cov.names if n not in free]
    C_oo = cov.sub(old)
    if old:
        J = sensitivities(model, experiments, list(free) + old, values)
        Jf, Jo = J[:, :len(free)], J[:, len(free):]
        S = np.linalg.solve(Jf.T @ Jf, Jf.T @ Jo)
    else:
        S = np.zeros((len(free), 0))
    C_ff = step_cov + S @ C_oo @ S.T
    C_fo = -S @ C_oo
    top = np.hstack([C_oo, C_fo.T])
    bottom = np.hstack([C_fo, C_ff])
    return JointCovariance(old + list(free), np.vstack([top, bottom])), S


def joint_fit(model: SessionModel, experiments: Sequence, free: Sequence[str], values: Mapping[str, float],
              radius: float, residual_tolerance: float | None = 1.5, max_nfev: int = 100) -> FitResult:
    """One fit of all ``experiments`` with the session parameters ``free``, started at ``values``."""
    bounds, scale = session_bounds(radius)
    sc = {n: max(abs(float(values[n])), scale[n]) for n in free}
    lo_hi = {n: bounds[n] for n in free}
    guess = {}
    for n in free:  # a chained estimate may sit within rounding of a bound
        lo, hi = lo_hi[n]
        guess[n] = float(np.clip(values[n], lo, hi))
    return fit_parameters(model, experiments, list(free), values, guess=guess, bounds=lo_hi, scale=sc,
                          max_nfev=max_nfev, residual_tolerance=residual_tolerance, check_identifiability=True)


def add_known_uncertainty(cov: JointCovariance, known_std: Mapping[str, float], model: SessionModel,
                          experiments: Sequence, values: Mapping[str, float]) -> JointCovariance:
    """The joint fit's covariance plus the effect of the std of parameters taken for granted.

    The estimates theta_F move with the known parameters theta_K by -S (theta_K - theta_K*),
    S = (J_F^T J_F)^-1 J_F^T J_K over all experiments (the joint fit's own weights).
    """
    known = [n for n, s in known_std.items() if s > 0]
    if not known:
        return cov
    free = list(cov.names)
    J = sensitivities(model, experiments, free + known, values)
    Jf, Jk = J[:, :len(free)], J[:, len(free):]
    S = np.linalg.solve(Jf.T @ Jf, Jf.T @ Jk)
    Ck = np.diag([known_std[n] ** 2 for n in known])
    top = np.hstack([Ck, -(S @ Ck).T])
    bottom = np.hstack([-S @ Ck, cov.matrix + S @ Ck @ S.T])
    return JointCovariance(known + free, np.vstack([top, bottom]))
