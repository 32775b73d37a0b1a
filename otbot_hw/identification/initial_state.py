"""Initial joint rates as fitted parameters, for runs that do not start at rest.

``Experiment`` takes x0 from the first sample (encoder angles; rates at rest or the
first encoder rates, see ``experiment``). When a run starts moving, one noisy encoder
sample sets the initial velocity; ``InitialRates`` wraps any prediction model so that
each experiment's initial joint rates (phi_r_dot, phi_l_dot, phi_p_dot at t_0, rad/s)
become parameters named ``<experiment>:w0_r``, ``:w0_l``, ``:w0_p`` that the fitter
estimates with the others. The full q_dot0 follows from the fixture's kinematics
(floor: q_dot = Delta(q) phi_dot, with l1, l2, r of the parameter vector).
"""
from __future__ import annotations

import copy
from types import SimpleNamespace
from typing import Any, Sequence

import numpy as np

from otbot_hw.model.kinematics import admissible_velocity

JOINTS = ("r", "l", "p")
GEOMETRY = ("l1", "l2", "r")


def state_with_rates(x0: np.ndarray, w: np.ndarray, fixture: str, l1: float, l2: float, r: float) -> np.ndarray:
    """x0 (12,) with the joint rates w (3,) rad/s and the velocities they imply on ``fixture``."""
    x = np.array(x0, dtype=float)
    x[6:] = 0.0
    if fixture == "floor":
        x[6:] = admissible_velocity(x[:6], w, SimpleNamespace(l1=l1, l2=l2, r=r))
    else:
        x[8] = x[11] = w[2]
        if fixture == "stand":
            x[9:11] = w[:2]
    return x


class InitialRates:
    """A prediction model with each experiment's initial joint rates appended to its parameters."""

    def __init__(self, model, experiments: Sequence):
        self.model = model
        self.channels = model.channels
        self._n = len(model.names)
        self._slot = {e.name: self._n + 3 * i for i, e in enumerate(experiments)}
        self.rate_names = tuple(f"{e.name}:w0_{j}" for e in experiments for j in JOINTS)
        self.names = tuple(model.names) + self.rate_names
        self._geo = [list(model.names).index(g) if g in model.names else None for g in GEOMETRY]

    def initial_values(self, experiments: Sequence) -> dict[str, float]:
        """Start values of the rate parameters: the rates in each experiment's x0."""
        return {f"{e.name}:w0_{j}": float(e.x0[9 + k]) for e in experiments for k, j in enumerate(JOINTS)}

    def bounds_and_scale(self, limit: float = 300.0) -> tuple[dict[str, tuple[float, float]], dict[str, float]]:
        """Bounds (+- limit rad/s) and scale (1 rad/s) of the rate parameters, for ``fit_parameters``."""
        return ({n: (-limit, limit) for n in self.rate_names}, {n: 1.0 for n in self.rate_names})

    def _geometry(self, row: np.ndarray) -> tuple[float, float, float]:
        defaults = (0.25, 0.20, 0.10)
        return tuple(float(row[i]) if i is not None else d for i, d in zip(self._geo, defaults))

    def predict(self, thetas: np.ndarray, experiment) -> np.ndarray:
        thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
        k = self._slot[experiment.name]
        key = np.hstack([thetas[:, k:k + 3]] + [thetas[:, [i]] for i in self._geo if i is not None])
        _, first, group = np.unique(key, axis=0, return_index=True, return_inverse=True)
        group = np.asarray(group).ravel()
        out: Any = None
        for g, i0 in enumerate(first):
            rows = np.nonzero(group == g)[0]
            e = copy.copy(experiment)
            e.x0 = state_with_rates(experiment.x0, thetas[i0, k:k + 3], experiment.fixture,
                                    *self._geometry(thetas[i0]))
            pred = self.model.predict(thetas[rows, :self._n], e)
            if out is None:
                out = np.empty((len(thetas),) + pred.shape[1:])
            out[rows] = pred
        return out
