"""Computed-torque tracking law on the task-space model (paper §5.1, Eq. full_CTC_brokendown):

    u = M_bar (p_dd_d - K_p e_p - K_v e_v) + C_bar p_dot = u_traj + u_corr,
    u_traj = M_bar p_dd_d + C_bar p_dot,   u_corr = M_bar (-K_p e_p - K_v e_v),

with e_p = p - p_d, e_v = p_dot - p_dot_d, p = (x, y, alpha) (m, m, rad) in the ground
frame and u = (tau_r, tau_l, tau_p) (N m). M_bar and C_bar are evaluated at the fed-back
alpha, phi_p and p_dot (compiled closed form, ``task_model``).

Feedback comes through ``TaskState``; the loop runner (``otbot_hw.runtime``) builds it from the
EKF's estimate or a simulator's ground truth.
"""
from __future__ import annotations

from dataclasses import dataclass
import numpy as np

from otbot_hw.control.gains import Gains, gains_from_tstab
from otbot_hw.control.task_model import computed_torque, reference_state
from otbot_hw.model.compiled import FLOOR
from otbot_hw.model.effect_physics import compensated_command
from otbot_hw.params import OtbotParams


@dataclass(frozen=True)
class TaskState:
    """What the law needs: p = (x, y, alpha) (m, rad), p_dot (m/s, rad/s), pivot angle phi_p (rad)."""

    p: np.ndarray
    p_dot: np.ndarray
    phi_p: float

    @classmethod
    def from_state(cls, x: np.ndarray) -> "TaskState":
        """From the simulator state x = (q, q_dot) (12,)."""
        return cls(p=np.ascontiguousarray(x[0:3], dtype=float), p_dot=np.ascontiguousarray(x[6:9], dtype=float),
                   phi_p=float(x[5]))


@dataclass(frozen=True)
class ControlOutput:
    """One evaluation of the law: u = u_traj + u_corr (N m, (3,) each), errors e_p, e_v (3,)."""

    u: np.ndarray
    u_traj: np.ndarray
    u_corr: np.ndarray
    e_p: np.ndarray
    e_v: np.ndarray


class ComputedTorqueController:
    """The law with fixed model parameters (the controller's belief) and gains.

    ``params`` may be an ``ExtendedModel`` (e.g. a diagnosed model, ``otbot diagnose --out``): its
    physical and actuator effects are then compensated by feedforward. The law's torque u is what the
    paper's model needs; the command sent is ``effect_physics.compensated_command`` of it, evaluated on the
    desired motion (p_d, p_dot_d) and the measured pivot angle, so friction signs follow the reference
    and do not chatter with noisy feedback. The compensation is part of u_traj (u_corr is unchanged).
    """

    def __init__(self, params, gains: Gains | None = None):
        self._eff = None
        if hasattr(params, "eff"):  # ExtendedModel
            if params.active_effects():
                self._eff = np.ascontiguousarray(params.eff, dtype=float)
            params = params.params
        self.params = params
        self.gains = gains or gains_from_tstab(3.0)
        self._prm = params.as_array()
        self._kp = np.ascontiguousarray(self.gains.kp)
        self._kv = np.ascontiguousarray(self.gains.kv)
        self._out = np.empty((3, 3))
        self.compensation = np.zeros(3)  # N m: command - the paper model's torque, of the last evaluation
        self.adapter = None  # an online payload adapter (otbot_hw.runtime.payload_adapter.PayloadAdapter) or None

    @property
    def prm(self) -> np.ndarray:
        """The parameter array the law evaluates (``OtbotParams.as_array()`` order); ``set_platform`` changes it
        in place, so a predictor sharing it follows."""
        return self._prm

    def set_platform(self, m_p: float, I_p: float, x_F: float, y_F: float, sync: bool = True) -> None:
        """Parameter-swap hook (online payload adaptation): the platform + load's mass (kg), inertia about its
        centre (kg m^2) and centre (m, frame B'') the law uses from its next evaluation on. ``sync`` False
        changes only the evaluated array (cheap, every cycle of a blend); ``params`` follows at the next
        synced call."""
        prm = self._prm
        prm[7], prm[8], prm[9], prm[10] = float(m_p), float(I_p), float(x_F), float(y_F)  # PARAM_INDEX order
        if sync:
            self.params = self.params.replace(m_p=float(m_p), I_p=float(I_p), x_F=float(x_F), y_F=float(y_F))

    def update_fast(self, p: np.ndarray, p_dot: np.ndarray, phi_p: float,
                    p_d: np.ndarray, pd_d: np.ndarray, pdd_d: np.ndarray) -> np.ndarray:
        """Hot path: returns the internal (3, 3) buffer with rows u, u_traj, u_corr (N m).

        All vectors must be contiguous float64 (3,). The buffer is overwritten by the next call.
        """
        computed_torque(p, p_dot, phi_p, p_d, pd_d, pdd_d, self._kp, self._kv, self._prm, self._out)
        if self._eff is not None:
            cmd = compensated_command(reference_state(p_d, pd_d, phi_p, self._prm), self._out[0], self._eff,
                                      self._prm, FLOOR)
            self.compensation = cmd - self._out[0]  # what the effects take (payload adaptation subtracts it)
            self._out[1] += self.compensation
            self._out[0] = cmd
        return self._out

    @property
    def model(self):
        """The controller's belief: ``OtbotParams``, or an ``ExtendedModel`` when it compensates effects."""
        if self._eff is None:
            return self.params
        from otbot_hw.model.effects import ExtendedModel

        return ExtendedModel(self.params, self._eff)

    @property
    def compensates(self) -> dict[str, float]:
        """Effects the controller compensates (name: value), empty for the paper's model."""
        if self._eff is None:
            return {}
        from otbot_hw.model.effects import ExtendedModel

        return ExtendedModel(self.params, self._eff).active_effects()

    def update(self, state: TaskState, p_d: np.ndarray, pd_d: np.ndarray, pdd_d: np.ndarray) -> ControlOutput:
        """Evaluate the law for feedback ``state`` and the desired (p_d, p_dot_d, p_dd_d)."""
        f = np.ascontiguousarray
        p_d, pd_d, pdd_d = f(p_d, dtype=float), f(pd_d, dtype=float), f(pdd_d, dtype=float)
        out = self.update_fast(f(state.p, dtype=float), f(state.p_dot, dtype=float), float(state.phi_p),
                               p_d, pd_d, pdd_d).copy()
        return ControlOutput(u=out[0], u_traj=out[1], u_corr=out[2],
                             e_p=state.p - p_d, e_v=state.p_dot - pd_d)
