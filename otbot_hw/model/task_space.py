"""Otbot task-space model (paper §3.3): M_bar(q) p_dd + C_bar(q, q_d) p_d = u.

Delta(q) = [M_FIK; I3] parameterizes admissible velocities by joint rates,
Lambda(q) = [I3; M_IIK] by the platform twist p_dot = (x_dot, y_dot, alpha_dot).
M_bar = Delta^T M Lambda and C_bar = Delta^T (M Lambda_dot + (C - E_f) Lambda);
the computed-torque controller uses them directly.

The task-space view of the model, gathered in one place: Delta and Lambda are kinematics
(``otbot_hw.model.kinematics``), M_bar and C_bar dynamics (``otbot_hw.model.dynamics``), each written
there once; imports run kinematics <- dynamics <- task_space (no cycle).
"""
from __future__ import annotations

from otbot_hw.model.dynamics import task_space_model
from otbot_hw.model.kinematics import delta_matrix, lambda_matrix, lambda_matrix_dot

__all__ = ["delta_matrix", "lambda_matrix", "lambda_matrix_dot", "task_space_model"]
