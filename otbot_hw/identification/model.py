"""Output prediction for prediction-error identification: the model as the fitter sees it.

A *prediction model* maps a batch of full parameter vectors to predicted sensor
outputs of one experiment. It has

* ``names``: the parameter names of the full vector (free and fixed ones),
* ``channels``: the output channels it predicts (last axis of the prediction),
* ``predict(thetas (m, P), experiment) -> (m, n_samples, n_channels)``.

``OtbotModel`` is the paper's model (parameters ``PARAM_NAMES``) simulated by the
compiled RK4 zero-order-hold integrator. A model extension (extra friction, sensor
bias, ...) is another object with the same three members; the fitter does not care
what is inside. Predicting a batch in one call lets the compiled code evaluate the
finite-difference Jacobian columns without going back to Python.

Output channels (sample k at t_k, command u_k held on [t_k, t_k+1)):

=========  =====================================================  =======
channel    meaning                                                unit
=========  =====================================================  =======
a_x, a_y   IMU specific force, platform frame B'' (pivot accel.)  m/s^2
omega_z    IMU yaw rate alpha_dot                                 rad/s
w_r, w_l,  encoder rates phi_r_dot, phi_l_dot, phi_p_dot          rad/s
w_p
phi_r,     encoder angles                                         rad
phi_l,
phi_p
=========  =====================================================  =======
"""
from __future__ import annotations

import os

import numpy as np
from numba import njit

from otbot_hw.model import compiled
from otbot_hw.simulation.integrators import rk4_zoh
from otbot_hw.params import PARAM_NAMES

#: Output channels predicted by ``OtbotModel``, in column order.
CHANNELS: tuple[str, ...] = ("a_x", "a_y", "omega_z", "w_r", "w_l", "w_p", "phi_r", "phi_l", "phi_p")
CHANNEL_UNITS: dict[str, str] = {"a_x": "m/s^2", "a_y": "m/s^2", "omega_z": "rad/s", "w_r": "rad/s",
                                 "w_l": "rad/s", "w_p": "rad/s", "phi_r": "rad", "phi_l": "rad", "phi_p": "rad"}


@njit(cache=True, nogil=True)
def outputs_from_states(X, U, F, prm, fixture):
    """Sensor outputs (n, 9) in ``CHANNELS`` order for states X (n, 12) under held U (n, 3), F (n, 2)."""
    n = X.shape[0]
    Y = np.empty((n, 9))
    gen = np.zeros(6)
    for k in range(n):
        xd = compiled.derivative(X[k], U[k], F[k], gen, prm, fixture)
        c = np.cos(X[k, 2])
        s = np.sin(X[k, 2])
        Y[k, 0] = c * xd[6] + s * xd[7]
        Y[k, 1] = -s * xd[6] + c * xd[7]
        Y[k, 2] = X[k, 8]
        for j in range(3):
            Y[k, 3 + j] = X[k, 9 + j]
            Y[k, 6 + j] = X[k, 3 + j]
    return Y


@njit(cache=True, nogil=True)
def predict_batch(x0, U, F, dt, substeps, P, fixture):
    """Outputs (m, n, 9) for each parameter row of P (m, 14); U (n, 3), F (n, 2) held per sample.

    The run has n samples and n - 1 zero-order-hold intervals; the IMU at sample k
    sees the command u_k (as the recorder logs it).
    """
    m = P.shape[0]
    n = U.shape[0]
    out = np.empty((m, n, 9))
    for i in range(m):
        X = rk4_zoh(x0, U[:n - 1], F[:n - 1], dt, substeps, P[i], fixture)
        out[i] = outputs_from_states(X, U, F, P[i], fixture)
    return out


_THREADS = [min(2, os.cpu_count() or 1)]
_POOL: list = [None]


def set_prediction_threads(n: int) -> None:
    """Threads that simulate the rows of a batch side by side (default min(2, CPUs)).

    The compiled kernel releases the GIL, so a batch (the Jacobian columns) is split
    over plain threads. Set 1 inside worker processes that already fill the CPUs.
    """
    _THREADS[0] = max(1, int(n))


def _forget_pool() -> None:
    _POOL[0] = None  # a forked child has none of the parent's threads


os.register_at_fork(after_in_child=_forget_pool)


def _pool(n: int):
    from concurrent.futures import ThreadPoolExecutor

    if _POOL[0] is None or _POOL[0]._max_workers != n:
        _POOL[0] = ThreadPoolExecutor(max_workers=n, thread_name_prefix="otbot-predict")
    return _POOL[0]


def map_prediction_rows(fn, n_rows: int) -> list:
    """[fn(0), ..., fn(n_rows - 1)] on the prediction threads (``set_prediction_threads``).

    For prediction models whose per-row work releases the GIL (compiled simulation):
    model extensions use it to spread a batch (the Jacobian columns) like ``OtbotModel``.
    """
    n = min(_THREADS[0], n_rows)
    if n <= 1:
        return [fn(i) for i in range(n_rows)]
    return list(_pool(n).map(fn, range(n_rows)))


class OtbotModel:
    """The paper's rigid-body model (parameters ``PARAM_NAMES``), fast compiled prediction."""

    names: tuple[str, ...] = PARAM_NAMES
    channels: tuple[str, ...] = CHANNELS

    def predict(self, thetas: np.ndarray, experiment) -> np.ndarray:
        """Predicted outputs (m, n_samples, 9) for parameter rows ``thetas`` (m, 14)."""
        P = np.ascontiguousarray(np.atleast_2d(thetas), dtype=float)
        args = (experiment.x0, experiment.torque, experiment.forces, experiment.dt, experiment.substeps)
        code = experiment.fixture_code
        n = min(_THREADS[0], len(P))
        if n <= 1:
            return predict_batch(*args, P, code)
        parts = np.array_split(np.arange(len(P)), n)
        futs = [_pool(n).submit(predict_batch, *args, np.ascontiguousarray(P[idx]), code) for idx in parts]
        return np.concatenate([f.result() for f in futs], axis=0)
