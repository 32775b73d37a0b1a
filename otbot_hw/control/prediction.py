"""One-period prediction of the task state: compensating the loop's sample delay.

On the bus (and behind every ``otbot_hw.robot.Robot``) the torque computed from the sensors of
sample k can only act from sample k+1 on: during [t_k, t_k+1) the command already written, u_k,
holds. The tracking law is therefore evaluated at the state the robot will be in when its command
takes effect, predicted from the fed-back state at t_k under u_k with the controller's own model
(the paper's dynamics, or the extended model whose effects the controller compensates), one
zero-order-hold period of the compiled RK4 integrator. With a perfect model and feedback this
gives exactly the loop without delay; otherwise the prediction error is what the delay costs.

The full state is rebuilt from what the law is fed (p, p_dot, phi_p): the wheel rates follow from
the rolling constraints (M_IIK), the wheel angles are set to 0 (they are cyclic: nothing depends
on them). Pivot forces are unknown to the controller and not predicted.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from otbot_hw.model.compiled import FLOOR
from otbot_hw.model.effect_physics import actuated_torque
from otbot_hw.model.kinematics import model_state_into
from otbot_hw.simulation.integrators import ext_rk4_zoh, rk4_zoh
from otbot_hw.simulation.simulator import default_substeps

_L1, _L2, _R = 0, 1, 2


@njit(cache=True)
def task_state_vector(p, pd, phi_p, prm):
    """State x (12,) with pivot pose p, twist pd, pivot angle phi_p, wheel angles 0 and the wheel and
    pivot rates the rolling constraints imply (phi_dot = M_IIK p_dot)."""
    x = np.empty(12)
    model_state_into(p[0], p[1], p[2], pd[0], pd[1], pd[2], phi_p, prm[_L1], prm[_L2], prm[_R], x)
    return x


@njit(cache=True)
def predict_paper(p, pd, phi_p, u, dt, substeps, prm):
    """State (12,) ``dt`` s after (p, pd, phi_p) under torques u, the paper's model (one compiled call)."""
    x = task_state_vector(p, pd, phi_p, prm)
    U = np.empty((1, 3))
    U[0, 0], U[0, 1], U[0, 2] = u[0], u[1], u[2]
    return rk4_zoh(x, U, np.zeros((1, 2)), dt, substeps, prm, FLOOR)[1]


class TaskStatePredictor:
    """Predict (p, p_dot, phi_p) ``dt`` s ahead under a held command, with the controller's model.

    ``params``: ``OtbotParams`` or an ``ExtendedModel`` (its physical and actuator effects are
    integrated too; the current-loop lag is not)."""

    def __init__(self, params, dt: float):
        self.eff = None
        if hasattr(params, "eff"):
            if params.active_effects():
                self.eff = np.ascontiguousarray(params.eff, dtype=float)
            params = params.params
        self._prm = params.as_array()
        self.dt = float(dt)
        self._substeps = default_substeps(self.dt)
        self._U = np.zeros((1, 3))
        self._F = np.zeros((1, 2))

    def predict(self, p: np.ndarray, p_dot: np.ndarray, phi_p: float, u: np.ndarray,
                dt: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
        """(p, p_dot, phi_p) after ``dt`` s (default: the period) under torques u (3,) N m."""
        h = self.dt if dt is None else float(dt)
        sub = self._substeps if dt is None else default_substeps(h)
        if self.eff is None:
            x1 = predict_paper(p, p_dot, float(phi_p), u, h, sub, self._prm)
        else:
            x = task_state_vector(p, p_dot, float(phi_p), self._prm)
            self._U[0] = u
            tau0 = actuated_torque(self._U[0], self.eff)
            x1 = ext_rk4_zoh(x, tau0, self._U, self._F, h, sub, self._prm, self.eff, FLOOR)[0][1]
        return x1[0:3], x1[6:9], float(x1[5])
