"""The pose EKF's dynamic-model parts (``otbot_hw.estimation.ekf``): the ``model`` prediction (the
paper's multiplier-free dynamics under the commanded torque drive the twist; the accelerometer becomes
a measurement; the ``imu`` prediction's correction of a reading held over several steps is compiled:
``imu_cycle.held_force_correction``). A mixin of ``PoseEKF``: it works on the filter's state ``kf`` and
its work arrays.
"""
from __future__ import annotations

import math

import numpy as np

from otbot_hw.estimation import kernels
from otbot_hw.estimation.ekf_state import A, BAX, BAY, BG, DA, N_STATE, VA, VX, VY, X, Y, EstimatorFault
from otbot_hw.model import compiled

#: Finite-difference step of the model Jacobians (rad, m/s, rad/s).
_FD_STEP = 1e-6


class ModelPrediction:
    """The dynamic-model methods of ``PoseEKF`` (see the module docstring)."""

    def _model_acceleration(self, s: np.ndarray, u: np.ndarray) -> np.ndarray:
        """p_dd (3,) of the paper's model at filter state s and the pivot reading under u (N m); the model
        state is built in one place (``kernels.model_state``: the true pivot angle, reading less e_p)."""
        kernels.model_state(s, self._phi_p, self._prm, self._xs)
        return compiled.accelerations(self._xs, u, self._zero2, self._zero6, self._prm)[:3]

    def _model_jacobian(self, s: np.ndarray, u: np.ndarray):
        """(p_dd (3,), d p_dd / d (alpha, x_dot, y_dot, alpha_dot) (3, 4)) by forward differences."""
        f0 = self._model_acceleration(s, u)
        J = np.empty((3, 4))
        for j, i in enumerate((A, VX, VY, VA)):
            sp = s.copy()
            sp[i] += _FD_STEP
            J[:, j] = (self._model_acceleration(sp, u) - f0) / _FD_STEP
        return f0, J

    def _predict_model(self, dt: float) -> None:
        """Dynamic-model step: p_dd from the multiplier-free dynamics under the held torque; first the
        accelerometer reading of the previous sample, taken under that same torque, as a measurement."""
        if self._torque is None:
            raise EstimatorFault("the model prediction needs the commanded torque (none given yet)")
        kf, cfg = self.kf, self.config
        u = self._torque
        if self._acc_held is not None:
            self._update_accel(self._t, self._acc_held, u)
        x = kf.x
        f0, J = self._model_jacobian(x, u)
        h2 = 0.5 * dt * dt
        F = np.eye(N_STATE)
        F[X, VX] = F[Y, VY] = F[A, VA] = dt
        cols = [A, VX, VY, VA]
        F[np.ix_([X, Y, A], cols)] += h2 * J
        F[np.ix_([VX, VY, VA], cols)] += dt * J
        F[A, DA], F[VA, DA] = h2, dt
        x[0:3] += x[3:6] * dt + h2 * f0
        x[3:6] += f0 * dt
        x[A] += h2 * x[DA]
        x[VA] += dt * x[DA]
        Q = np.zeros((N_STATE, N_STATE))
        Q[DA, DA] = self._var_da * self.walk_scale * dt
        for (p, v), q in (((X, VX), cfg.model_accel_density), ((Y, VY), cfg.model_accel_density),
                          ((A, VA), cfg.model_angular_density)):
            q2 = q * q
            Q[p, p] = q2 * dt ** 3 / 3
            Q[p, v] = Q[v, p] = q2 * dt * dt / 2
            Q[v, v] = q2 * dt
        Q[BG, BG] = self._var[2] * dt
        Q[BAX, BAX] = Q[BAY, BAY] = self._var[3] * dt
        kf.F, kf.Q = F, Q
        kf.P = F @ kf.P @ F.T + Q

    def _update_accel(self, t: float, acc: np.ndarray, u: np.ndarray) -> None:
        """The accelerometer reading at t (under u) as a measurement of R(alpha)^T p_dd + b_a."""
        x = self.kf.x
        f0, J = self._model_jacobian(x, u)
        c, s = math.cos(x[A]), math.sin(x[A])
        RT = np.array([[c, s], [-s, c]])
        dRT = np.array([[-s, c], [-c, -s]])
        H = np.zeros((2, N_STATE))
        H[:, [A, VX, VY, VA]] = RT @ J[:2]
        H[:, A] += dRT @ f0[:2]
        H[0, BAX] = H[1, BAY] = 1.0
        self._update("accel", t, acc[:2] - (RT @ f0[:2] + x[[BAX, BAY]]), H, self._R_accel)
