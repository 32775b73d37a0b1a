"""Otbot dynamics (paper §3): Lagrange's equations with multipliers,

    M(q) q_dd + C(q, q_d) q_d + J(q)^T lambda = E u + E_f q_d + Q_p,

with u = (tau_r, tau_l, tau_p) in N m and Q_p the generalized force of a
horizontal force f_p = (f_x, f_y) (N, ground frame) applied at the pivot (§5.4).
Both the conventional solutions ([E -J^T] 6x6 inverse, 9x9 forward) and the
multiplier-free ones (Delta, Lambda, K, b_FD) are here; all functions are pure.
"""
from __future__ import annotations

import numpy as np

from otbot_hw.model.kinematics import (
    constraint_jacobian,
    constraint_jacobian_dot,
    delta_matrix,
    inverse_kinematics_matrix,
    inverse_kinematics_matrix_dot,
    lambda_matrix,
    lambda_matrix_dot,
)
from otbot_hw.params import OtbotParams

#: Actuation matrix E (6x3): Q_a = E u.
ACTUATION_MATRIX = np.vstack([np.zeros((3, 3)), np.eye(3)])


def actuation_matrix() -> np.ndarray:
    """E (6x3), mapping motor torques u to generalized forces."""
    return ACTUATION_MATRIX.copy()


def friction_matrix(p: OtbotParams) -> np.ndarray:
    """E_f (6x6): viscous friction Q_f = E_f q_dot (wheels b_w, pivot b_p)."""
    return -np.diag([0.0, 0.0, 0.0, p.b_w, p.b_w, p.b_p])


def pivot_force_generalized(f_p: np.ndarray | None) -> np.ndarray:
    """Q_p (6,): generalized force of a force f_p = (f_x, f_y) N at the pivot, ground frame."""
    out = np.zeros(6)
    if f_p is not None:
        out[0], out[1] = f_p[0], f_p[1]
    return out


def mass_matrix(q: np.ndarray, p: OtbotParams) -> np.ndarray:
    """M(q) (6x6), paper Fig. massmatrixexpr."""
    a, th = q[2], q[2] - q[5]
    sa, ca, st, ct = np.sin(a), np.cos(a), np.sin(th), np.cos(th)
    mc, mp = p.m_c, p.m_p
    xb, yb, xf, yf = p.x_B, p.y_B, p.x_F, p.y_F
    m13 = -mp * yf * ca - mp * xf * sa - mc * yb * ct - mc * xb * st
    m23 = mp * xf * ca - mp * yf * sa + mc * xb * ct - mc * yb * st
    m16 = mc * yb * ct + mc * xb * st
    m26 = mc * yb * st - mc * xb * ct
    ic = mc * (xb * xb + yb * yb) + p.I_c
    m33 = ic + mp * (xf * xf + yf * yf) + p.I_p
    return np.array([
        [mc + mp, 0.0, m13, 0.0, 0.0, m16],
        [0.0, mc + mp, m23, 0.0, 0.0, m26],
        [m13, m23, m33, 0.0, 0.0, -ic],
        [0.0, 0.0, 0.0, p.I_a, 0.0, 0.0],
        [0.0, 0.0, 0.0, 0.0, p.I_a, 0.0],
        [m16, m26, -ic, 0.0, 0.0, ic],
    ])


def coriolis_matrix(q: np.ndarray, qd: np.ndarray, p: OtbotParams) -> np.ndarray:
    """C(q, q_dot) (6x6), paper Fig. cormatrixexpr (Christoffel construction).

    Like ``mass_matrix`` it also accepts object arrays (CasADi symbols, intervals).
    """
    a, th = q[2], q[2] - q[5]
    ad, thd = qd[2], qd[2] - qd[5]
    sa, ca, st, ct = np.sin(a), np.cos(a), np.sin(th), np.cos(th)
    mc, mp = p.m_c, p.m_p
    xb, yb, xf, yf = p.x_B, p.y_B, p.x_F, p.y_F
    cb1 = thd * mc * (xb * ct - yb * st)
    cf1 = ad * mp * (xf * ca - yf * sa)
    cb2 = thd * mc * (yb * ct + xb * st)
    cf2 = ad * mp * (yf * ca + xf * sa)
    numeric = all(isinstance(v, (float, int, np.floating)) for v in (cb1, cf1, cb2, cf2))
    out = np.zeros((6, 6), dtype=float if numeric else object)  # object: symbolic or interval entries
    out[0, 2], out[0, 5] = -cb1 - cf1, cb1
    out[1, 2], out[1, 5] = -cb2 - cf2, cb2
    return out


def kinetic_energy(q: np.ndarray, qd: np.ndarray, p: OtbotParams) -> float:
    """Kinetic energy T (J) summed body by body from the velocities of the centres of mass.

    Independent of ``mass_matrix``: the chassis centre of mass B moves with the
    pivot velocity plus theta_dot x PB, the platform's F with alpha_dot x PF.
    """
    a, th = q[2], q[2] - q[5]
    ad, thd = qd[2], qd[2] - qd[5]

    def point_velocity(angle: float, rate: float, cx: float, cy: float) -> np.ndarray:
        rel = np.array([cx * np.cos(angle) - cy * np.sin(angle), cx * np.sin(angle) + cy * np.cos(angle)])
        return qd[:2] + rate * np.array([-rel[1], rel[0]])

    vb = point_velocity(th, thd, p.x_B, p.y_B)
    vf = point_velocity(a, ad, p.x_F, p.y_F)
    return float(0.5 * p.m_c * vb @ vb + 0.5 * p.I_c * thd ** 2
                 + 0.5 * p.m_p * vf @ vf + 0.5 * p.I_p * ad ** 2
                 + 0.5 * p.I_a * (qd[3] ** 2 + qd[4] ** 2))


def task_space_model(q: np.ndarray, qd: np.ndarray, p: OtbotParams) -> tuple[np.ndarray, np.ndarray]:
    """(M_bar (3x3), C_bar (3x3)) so that M_bar p_dd + C_bar p_d = u (N m) (paper §3.3)."""
    D = delta_matrix(q, p)
    L = lambda_matrix(q, p)
    M = mass_matrix(q, p)
    Mbar = D.T @ M @ L
    Cbar = D.T @ (M @ lambda_matrix_dot(q, qd, p) + (coriolis_matrix(q, qd, p) - friction_matrix(p)) @ L)
    return Mbar, Cbar


# --- conventional solutions (with multipliers) -------------------------------

def inverse_dynamics_conventional(q, qd, qdd, p: OtbotParams, f_p=None) -> tuple[np.ndarray, np.ndarray]:
    """Torques u (N m) and multipliers lambda for an admissible (q, q_dot, q_ddot).

    Solves [E  -J^T] [u; lambda] = M q_dd + (C - E_f) q_d - Q_p (6x6).
    """
    tau_id = (mass_matrix(q, p) @ qdd + (coriolis_matrix(q, qd, p) - friction_matrix(p)) @ qd
              - pivot_force_generalized(f_p))
    A = np.hstack([ACTUATION_MATRIX, -constraint_jacobian(q, p).T])
    sol = np.linalg.solve(A, tau_id)
    return sol[:3], sol[3:]


def forward_dynamics_conventional(q, qd, u, p: OtbotParams, f_p=None) -> tuple[np.ndarray, np.ndarray]:
    """q_ddot and multipliers lambda from the 9x9 augmented system (paper Eq. forward_dyn1)."""
    M = mass_matrix(q, p)
    J = constraint_jacobian(q, p)
    A = np.zeros((9, 9))
    A[:6, :6], A[:6, 6:], A[6:, :6] = M, J.T, J
    rhs = np.concatenate([
        ACTUATION_MATRIX @ u + (friction_matrix(p) - coriolis_matrix(q, qd, p)) @ qd + pivot_force_generalized(f_p),
        -constraint_jacobian_dot(q, qd, p) @ qd,
    ])
    sol = np.linalg.solve(A, rhs)
    return sol[:6], sol[6:]


# --- multiplier-free solutions ------------------------------------------------

def inverse_dynamics(q, qd, qdd, p: OtbotParams, f_p=None) -> np.ndarray:
    """u = Delta^T (M q_dd + (C - E_f) q_d - Q_p): no matrix inverse (paper Eq. simple_inverse)."""
    D = delta_matrix(q, p)
    return D.T @ (mass_matrix(q, p) @ qdd + (coriolis_matrix(q, qd, p) - friction_matrix(p)) @ qd
                  - pivot_force_generalized(f_p))


def forward_dynamics_matrices(q, qd, u, p: OtbotParams, f_p=None) -> tuple[np.ndarray, np.ndarray]:
    """K(q) (6x6) and b_FD(q, q_d, u) (6,) with K q_dd = b_FD (paper Eq. forward_dyn2).

    The external pivot force enters the task-space rows as Delta^T Q_p.
    """
    Mbar, Cbar = task_space_model(q, qd, p)
    Miik = inverse_kinematics_matrix(q, p)
    pd = qd[:3]
    K = np.zeros((6, 6))
    K[:3, :3] = Mbar
    K[3:, :3] = -Miik
    K[3:, 3:] = np.eye(3)
    ext = delta_matrix(q, p).T @ pivot_force_generalized(f_p)
    b = np.concatenate([u + ext - Cbar @ pd, inverse_kinematics_matrix_dot(q, qd, p) @ pd])
    return K, b


def forward_dynamics(q, qd, u, p: OtbotParams, f_p=None) -> np.ndarray:
    """q_ddot = K^-1 b_FD, the multiplier-free forward dynamics (6,)."""
    K, b = forward_dynamics_matrices(q, qd, u, p, f_p)
    return np.linalg.solve(K, b)


def state_derivative(x: np.ndarray, u: np.ndarray, p: OtbotParams, f_p=None) -> np.ndarray:
    """x_dot = f(x, u) for the state x = (q, q_dot) (12,)."""
    return np.concatenate([x[6:], forward_dynamics(x[:6], x[6:], u, p, f_p)])
