"""Otbot kinematics (paper §2): rolling constraints and instantaneous kinematics.

State coordinates q = (x, y, alpha, phi_r, phi_l, phi_p): pivot position (m) in
the ground frame B, platform angle alpha (rad), wheel angles and pivot angle (rad).
The chassis heading is theta = alpha - phi_p. Task coordinates p = (x, y, alpha),
joint coordinates phi = (phi_r, phi_l, phi_p). All functions are pure.

The entries of M_FIK, M_IIK and dM_IIK/dt are written once, as scalar formulas in sin/cos of
theta (``fik_entries``, ``iik_entries``, ``iik_dot_entries``, ``model_state_into``), registered
with numba (``register_jitable``): Python calls them as they are (numpy or symbolic entries: the
planner passes CasADi symbols to the matrix functions below, which build from them) and numba-compiled
callers (the dynamics kernel ``otbot_hw.model.compiled``, the extended model, the EKF's kernels)
inline them at numba-IR level (``inline="always"``: as a called function they cost the dynamics a
third of its speed, 0.16 -> 0.22 us per evaluation, ``benchmarks/model.py``). numba keys a cache entry
by its own file only; ``otbot_hw.model.kernel_cache`` keys the whole cache folder by every kernel
source, this file included, so an edit here recompiles its callers.
"""
from __future__ import annotations

import math

import numpy as np
from numba.extending import register_jitable

from otbot_hw.params import OtbotParams

@register_jitable(inline="always")
def fik_entries(s, c, l1, l2, r):
    """M_FIK's varying entries (b00, b01, b10, b11) and kf = r / (2 l2) at sin, cos of theta:
    M_FIK = [[b00, b01, 0], [b10, b11, 0], [kf, -kf, 1]] (paper §2.3.1)."""
    kf = r / (2.0 * l2)
    return kf * (l2 * c - l1 * s), kf * (l2 * c + l1 * s), kf * (l1 * c + l2 * s), kf * (-l1 * c + l2 * s), kf


@register_jitable(inline="always")
def iik_entries(s, c, l1, l2, r):
    """M_IIK's varying entries (a00, a01, a10, a11, a20, a21) at sin, cos of theta:
    M_IIK = [[a00, a01, 0], [a10, a11, 0], [a20, a21, 1]] = M_FIK^-1 (paper §2.3.2)."""
    k = 1.0 / (r * l1)
    return ((l1 * c - l2 * s) * k, (l2 * c + l1 * s) * k, (l1 * c + l2 * s) * k, (-l2 * c + l1 * s) * k,
            s / l1, -c / l1)


@register_jitable(inline="always")
def iik_dot_entries(s, c, thd, l1, l2, r):
    """dM_IIK/dt's entries (d00, d01, d10, d11, d20, d21) at sin, cos of theta and theta_dot (third
    column zero); with thd = 1 the derivative of M_IIK with respect to theta."""
    kd = (1.0 / (r * l1)) * thd
    return ((-l1 * s - l2 * c) * kd, (-l2 * s + l1 * c) * kd, (-l1 * s + l2 * c) * kd, (l2 * s + l1 * c) * kd,
            c / l1 * thd, s / l1 * thd)


@register_jitable(inline="always")
def model_state_into(x, y, alpha, vx, vy, va, phi_p, l1, l2, r, out):
    """Write the model state (q, q_dot) (12,) of a pose (x, y, alpha) m, rad, a twist (vx, vy, va) m/s,
    rad/s and the true pivot angle phi_p (rad) into ``out``: wheel angles 0 (the dynamics does not
    depend on them), joint rates phi_dot = M_IIK(theta) p_dot with theta = alpha - phi_p."""
    th = alpha - phi_p
    a00, a01, a10, a11, a20, a21 = iik_entries(math.sin(th), math.cos(th), l1, l2, r)
    out[0], out[1], out[2], out[3], out[4], out[5] = x, y, alpha, 0.0, 0.0, phi_p
    out[6], out[7], out[8] = vx, vy, va
    out[9] = a00 * vx + a01 * vy
    out[10] = a10 * vx + a11 * vy
    out[11] = a20 * vx + a21 * vy + va


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
    b00, b01, b10, b11, kf = fik_entries(np.sin(th), np.cos(th), p.l1, p.l2, p.r)
    return np.array([[b00, b01, 0.0], [b10, b11, 0.0], [kf, -kf, 1.0]])


def inverse_kinematics_matrix(q: np.ndarray, p: OtbotParams) -> np.ndarray:
    """M_IIK(q) = M_FIK(q)^-1, 3x3: joint rates phi_dot = M_IIK(q) p_dot (paper §2.3.2)."""
    th = q[2] - q[5]
    a00, a01, a10, a11, a20, a21 = iik_entries(np.sin(th), np.cos(th), p.l1, p.l2, p.r)
    return np.array([[a00, a01, 0.0], [a10, a11, 0.0], [a20, a21, 1.0]])


def inverse_kinematics_matrix_dot(q: np.ndarray, qd: np.ndarray, p: OtbotParams) -> np.ndarray:
    """dM_IIK/dt (3x3) along the motion; M_IIK depends on q only through theta."""
    th = q[2] - q[5]
    d00, d01, d10, d11, d20, d21 = iik_dot_entries(np.sin(th), np.cos(th), qd[2] - qd[5], p.l1, p.l2, p.r)
    return np.array([[d00, d01, 0.0], [d10, d11, 0.0], [d20, d21, 0.0]])


def holonomic_constraint(q: np.ndarray, q0: np.ndarray, p: OtbotParams) -> float:
    """Residual of alpha - r/(2 l2)(phi_r - phi_l) - phi_p - K0 = 0 (rad), K0 from q0."""
    k = p.r / (2 * p.l2)

    def g(v: np.ndarray) -> float:
        return float(v[2] - k * v[3] + k * v[4] - v[5])

    return g(q) - g(q0)


def delta_matrix(q: np.ndarray, p: OtbotParams) -> np.ndarray:
    """Delta(q) (6x3): q_dot = Delta phi_dot; J Delta = 0 and Delta^T E = I3."""
    return np.vstack([forward_kinematics_matrix(q, p), np.eye(3)])


def lambda_matrix(q: np.ndarray, p: OtbotParams) -> np.ndarray:
    """Lambda(q) (6x3): q_dot = Lambda p_dot."""
    return np.vstack([np.eye(3), inverse_kinematics_matrix(q, p)])


def lambda_matrix_dot(q: np.ndarray, qd: np.ndarray, p: OtbotParams) -> np.ndarray:
    """dLambda/dt (6x3) = [0; dM_IIK/dt]."""
    return np.vstack([np.zeros((3, 3)), inverse_kinematics_matrix_dot(q, qd, p)])


def admissible_velocity(q: np.ndarray, phi_dot: np.ndarray, p: OtbotParams) -> np.ndarray:
    """q_dot = Delta(q) phi_dot: the admissible generalized velocity for joint rates phi_dot."""
    return np.concatenate([forward_kinematics_matrix(q, p) @ phi_dot, phi_dot])
