"""Otbot task-space model (paper §3.3): M_bar(q) p_dd + C_bar(q, q_d) p_d = u.

Delta(q) = [M_FIK; I3] parameterizes admissible velocities by joint rates,
Lambda(q) = [I3; M_IIK] by the platform twist p_dot = (x_dot, y_dot, alpha_dot).
M_bar = Delta^T M Lambda and C_bar = Delta^T (M Lambda_dot + (C - E_f) Lambda);
the computed-torque controller uses them directly.
"""
from __future__ import annotations

import numpy as np

from otbot_hw.model import kinematics as kin
from otbot_hw.params import OtbotParams


def delta_matrix(q: np.ndarray, p: OtbotParams) -> np.ndarray:
    """Delta(q) (6x3): q_dot = Delta phi_dot; J Delta = 0 and Delta^T E = I3."""
    return np.vstack([kin.forward_kinematics_matrix(q, p), np.eye(3)])


def lambda_matrix(q: np.ndarray, p: OtbotParams) -> np.ndarray:
    """Lambda(q) (6x3): q_dot = Lambda p_dot."""
    return np.vstack([np.eye(3), kin.inverse_kinematics_matrix(q, p)])


def lambda_matrix_dot(q: np.ndarray, qd: np.ndarray, p: OtbotParams) -> np.ndarray:
    """dLambda/dt (6x3) = [0; dM_IIK/dt]."""
    return np.vstack([np.zeros((3, 3)), kin.inverse_kinematics_matrix_dot(q, qd, p)])


def task_space_model(q: np.ndarray, qd: np.ndarray, p: OtbotParams) -> tuple[np.ndarray, np.ndarray]:
    """(M_bar (3x3), C_bar (3x3)) so that M_bar p_dd + C_bar p_d = u (N m)."""
    from otbot_hw.model.dynamics import coriolis_matrix, friction_matrix, mass_matrix

    D = delta_matrix(q, p)
    L = lambda_matrix(q, p)
    M = mass_matrix(q, p)
    Mbar = D.T @ M @ L
    Cbar = D.T @ (M @ lambda_matrix_dot(q, qd, p) + (coriolis_matrix(q, qd, p) - friction_matrix(p)) @ L)
    return Mbar, Cbar
