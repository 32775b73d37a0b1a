"""Otbot kinematics (paper §2): rolling constraints and instantaneous kinematics.

State coordinates q = (x, y, alpha, phi_r, phi_l, phi_p): pivot position (m) in
the ground frame B, platform angle alpha (rad), wheel angles and pivot angle (rad).
The chassis heading is theta = alpha - phi_p. Task coordinates p = (x, y, alpha),
joint coordinates phi = (phi_r, phi_l, phi_p). All functions are pure.
"""
from __future__ import annotations

import numpy as np

from otbot_hw.params import OtbotParams


def chassis_heading(q: np.ndarray) -> float:
    """theta = alpha - phi_p (rad): heading of the chassis axis 1' in the ground frame."""
    return float(q[2] - q[5])


def constraint_jacobian(q: np.ndarray, p: OtbotParams) -> np.ndarray:
    """J(q), 3x6: the rolling constraints read J(q) q_dot = 0 (paper Eq. chap2JacobianJ)."""
    th = q[2] - q[5]
    s, c = np.sin(th), np.cos(th)
    l1, r, l2 = p.l1, p.r, p.l2
    return np.array([
        [1.0, 0.0, l1 * s, -0.5 * r * c, -0.5 * r * c, -l1 * s],
        [0.0, 1.0, -l1 * c, -0.5 * r * s, -0.5 * r * s, l1 * c],
        [0.0, 0.0, 1.0, -r / (2 * l2), r / (2 * l2), -1.0],
    ])


def constraint_jacobian_dot(q: np.ndarray, qd: np.ndarray, p: OtbotParams) -> np.ndarray:
    """dJ/dt (3x6) along the motion (q, q_dot)."""
    th = q[2] - q[5]
    thd = qd[2] - qd[5]
    s, c = np.sin(th), np.cos(th)
    l1, r = p.l1, p.r
    out = np.zeros((3, 6))
    out[0] = [0.0, 0.0, l1 * c * thd, 0.5 * r * s * thd, 0.5 * r * s * thd, -l1 * c * thd]
    out[1] = [0.0, 0.0, l1 * s * thd, -0.5 * r * c * thd, -0.5 * r * c * thd, -l1 * s * thd]
    return out


def forward_kinematics_matrix(q: np.ndarray, p: OtbotParams) -> np.ndarray:
    """M_FIK(q), 3x3: platform twist p_dot = M_FIK(q) phi_dot (paper §2.3.1)."""
    th = q[2] - q[5]
    s, c = np.sin(th), np.cos(th)
    l1, l2, r = p.l1, p.l2, p.r
    k = r / (2 * l2)
    return k * np.array([
        [l2 * c - l1 * s, l2 * c + l1 * s, 0.0],
        [l1 * c + l2 * s, -l1 * c + l2 * s, 0.0],
        [1.0, -1.0, 2 * l2 / r],
    ])


def inverse_kinematics_matrix(q: np.ndarray, p: OtbotParams) -> np.ndarray:
    """M_IIK(q) = M_FIK(q)^-1, 3x3: joint rates phi_dot = M_IIK(q) p_dot (paper §2.3.2)."""
    th = q[2] - q[5]
    s, c = np.sin(th), np.cos(th)
    l1, l2, r = p.l1, p.l2, p.r
    return np.array([
        [l1 * c - l2 * s, l2 * c + l1 * s, 0.0],
        [l1 * c + l2 * s, -l2 * c + l1 * s, 0.0],
        [r * s, -r * c, r * l1],
    ]) / (r * l1)


def inverse_kinematics_matrix_dot(q: np.ndarray, qd: np.ndarray, p: OtbotParams) -> np.ndarray:
    """dM_IIK/dt (3x3) along the motion; M_IIK depends on q only through theta."""
    th = q[2] - q[5]
    thd = qd[2] - qd[5]
    s, c = np.sin(th), np.cos(th)
    l1, l2, r = p.l1, p.l2, p.r
    return thd * np.array([
        [-l1 * s - l2 * c, -l2 * s + l1 * c, 0.0],
        [-l1 * s + l2 * c, l2 * s + l1 * c, 0.0],
        [r * c, r * s, 0.0],
    ]) / (r * l1)


def holonomic_constraint(q: np.ndarray, q0: np.ndarray, p: OtbotParams) -> float:
    """Residual of alpha - r/(2 l2)(phi_r - phi_l) - phi_p - K0 = 0 (rad), K0 from q0."""
    k = p.r / (2 * p.l2)

    def g(v: np.ndarray) -> float:
        return float(v[2] - k * v[3] + k * v[4] - v[5])

    return g(q) - g(q0)


def admissible_velocity(q: np.ndarray, phi_dot: np.ndarray, p: OtbotParams) -> np.ndarray:
    """q_dot = Delta(q) phi_dot: the admissible generalized velocity for joint rates phi_dot."""
    return np.concatenate([forward_kinematics_matrix(q, p) @ phi_dot, phi_dot])
