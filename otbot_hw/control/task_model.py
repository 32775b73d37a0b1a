"""Closed-form, compiled task-space model for the control law: M_bar, C_bar.

Same physics as ``otbot_hw.model.task_space.task_space_model`` (M_bar = Delta^T M Lambda,
C_bar = Delta^T (M Lambda_dot + (C - E_f) Lambda)), but evaluated from what the controller
is fed: the platform angle alpha, the pivot angle phi_p (rad) and the platform twist
p_dot = (x_dot, y_dot, alpha_dot) (m/s, rad/s). The chassis heading is
theta = alpha - phi_p and its rate follows from the rolling constraints,
theta_dot = -(sin(theta) x_dot - cos(theta) y_dot) / l1, so no wheel rates are needed.
``prm`` is ``OtbotParams.as_array()``.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from otbot_hw.model.kinematics import fik_entries, iik_dot_entries, iik_entries, model_state_into

_L1, _L2, _R, _MC, _IC, _XB, _YB, _MP, _IP, _XF, _YF, _IA, _BW, _BP = range(14)


@njit(cache=True)
def task_space_matrices(alpha, phi_p, pd, prm, Mbar, Cbar):
    """Fill Mbar (3x3, kg / kg m / kg m^2) and Cbar (3x3) in place."""
    l1, l2, r = prm[_L1], prm[_L2], prm[_R]
    mc, ic0, xb, yb = prm[_MC], prm[_IC], prm[_XB], prm[_YB]
    mp, ip, xf, yf = prm[_MP], prm[_IP], prm[_XF], prm[_YF]
    ia, bw, bp = prm[_IA], prm[_BW], prm[_BP]
    th = alpha - phi_p
    sa, ca, st, ct = np.sin(alpha), np.cos(alpha), np.sin(th), np.cos(th)
    ad = pd[2]
    thd = -(st * pd[0] - ct * pd[1]) / l1
    # mass matrix M (6x6), symmetric
    M = np.zeros((6, 6))
    m13 = -mp * yf * ca - mp * xf * sa - mc * yb * ct - mc * xb * st
    m23 = mp * xf * ca - mp * yf * sa + mc * xb * ct - mc * yb * st
    m16 = mc * yb * ct + mc * xb * st
    m26 = mc * yb * st - mc * xb * ct
    ic = mc * (xb * xb + yb * yb) + ic0
    M[0, 0] = mc + mp
    M[1, 1] = mc + mp
    M[0, 2] = M[2, 0] = m13
    M[1, 2] = M[2, 1] = m23
    M[0, 5] = M[5, 0] = m16
    M[1, 5] = M[5, 1] = m26
    M[2, 2] = ic + mp * (xf * xf + yf * yf) + ip
    M[2, 5] = M[5, 2] = -ic
    M[3, 3] = ia
    M[4, 4] = ia
    M[5, 5] = ic
    # C - E_f (6x6)
    cb1 = thd * mc * (xb * ct - yb * st)
    cf1 = ad * mp * (xf * ca - yf * sa)
    cb2 = thd * mc * (yb * ct + xb * st)
    cf2 = ad * mp * (yf * ca + xf * sa)
    CF = np.zeros((6, 6))
    CF[0, 2] = -cb1 - cf1
    CF[0, 5] = cb1
    CF[1, 2] = -cb2 - cf2
    CF[1, 5] = cb2
    CF[3, 3] = bw
    CF[4, 4] = bw
    CF[5, 5] = bp
    # Lambda = [I3; M_IIK], Lambda_dot = [0; M_IIK_dot], Delta = [M_FIK; I3]
    L = np.zeros((6, 3))
    Ld = np.zeros((6, 3))
    D = np.zeros((6, 3))
    for i in range(3):
        L[i, i] = 1.0
        D[3 + i, i] = 1.0
    # M_IIK, dM_IIK/dt and M_FIK entries (``otbot_hw.model.kinematics``)
    L[3, 0], L[3, 1], L[4, 0], L[4, 1], L[5, 0], L[5, 1] = iik_entries(st, ct, l1, l2, r)
    L[5, 2] = 1.0
    Ld[3, 0], Ld[3, 1], Ld[4, 0], Ld[4, 1], Ld[5, 0], Ld[5, 1] = iik_dot_entries(st, ct, thd, l1, l2, r)
    D[0, 0], D[0, 1], D[1, 0], D[1, 1], kf = fik_entries(st, ct, l1, l2, r)
    D[2, 0] = kf
    D[2, 1] = -kf
    D[2, 2] = 1.0
    # ML = M Lambda, H = M Lambda_dot + (C - E_f) Lambda   (6x3 each)
    for j in range(3):
        for i in range(3):
            sm = 0.0
            sc = 0.0
            for a in range(6):
                da = D[a, i]
                if da == 0.0:
                    continue
                ml = 0.0
                h = 0.0
                for b in range(6):
                    ml += M[a, b] * L[b, j]
                    h += M[a, b] * Ld[b, j] + CF[a, b] * L[b, j]
                sm += da * ml
                sc += da * h
            Mbar[i, j] = sm
            Cbar[i, j] = sc


@njit(cache=True)
def computed_torque(p, pd, phi_p, p_ref, pd_ref, pdd_ref, kp, kv, prm, out):
    """Computed-torque law; fills out (3, 3) with rows u, u_traj, u_corr (N m).

    u_traj = M_bar pdd_ref + C_bar pd, u_corr = M_bar (-kp (p - p_ref) - kv (pd - pd_ref)).
    """
    Mbar = np.empty((3, 3))
    Cbar = np.empty((3, 3))
    task_space_matrices(p[2], phi_p, pd, prm, Mbar, Cbar)
    v = np.empty(3)
    for i in range(3):
        v[i] = -kp[i] * (p[i] - p_ref[i]) - kv[i] * (pd[i] - pd_ref[i])
    for i in range(3):
        ut = 0.0
        uc = 0.0
        for j in range(3):
            ut += Mbar[i, j] * pdd_ref[j] + Cbar[i, j] * pd[j]
            uc += Mbar[i, j] * v[j]
        out[1, i] = ut
        out[2, i] = uc
        out[0, i] = ut + uc


def task_space(alpha: float, phi_p: float, pd: np.ndarray, prm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M_bar, C_bar) as new arrays (convenience wrapper of the compiled kernel)."""
    Mbar = np.empty((3, 3))
    Cbar = np.empty((3, 3))
    task_space_matrices(float(alpha), float(phi_p), np.ascontiguousarray(pd, dtype=float), prm, Mbar, Cbar)
    return Mbar, Cbar


@njit(cache=True)
def reference_state(p, pd, phi_p, prm):
    """State x (12,) for task pose p = (x, y, alpha), task rates pd and pivot angle phi_p: wheel angles
    0 (no physics depends on them), joint rates from the inverse kinematics (paper §2.3.2;
    ``otbot_hw.model.kinematics.model_state_into``)."""
    x = np.empty(12)
    model_state_into(p[0], p[1], p[2], pd[0], pd[1], pd[2], phi_p, prm[_L1], prm[_L2], prm[_R], x)
    return x
