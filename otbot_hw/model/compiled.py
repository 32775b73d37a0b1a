"""Compiled (numba) forward dynamics and zero-order-hold integration: the fast path.

Same physics as ``otbot_hw.model.dynamics`` (multiplier-free forward dynamics,
paper Eq. forward_dyn2), written on flat arrays so numba can compile it:
``prm`` is ``OtbotParams.as_array()`` (order ``PARAM_NAMES``), x = (q, q_dot) (12,),
u = (tau_r, tau_l, tau_p) N m, f = (f_x, f_y) N at the pivot in the ground frame,
``gen`` is an extra generalized force (6,) added to the right-hand side (used by
model extensions; zeros for the paper's model).
"""
from __future__ import annotations

import numpy as np
from numba import njit

_L1, _L2, _R, _MC, _IC, _XB, _YB, _MP, _IP, _XF, _YF, _IA, _BW, _BP = range(14)


@njit(cache=True)
def _solve3(A, b):
    """Solve the 3x3 system A z = b by Cramer's rule (A is M_bar: well conditioned)."""
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    z = np.empty(3)
    z[0] = (b[0] * c00 + A[0, 1] * (A[1, 2] * b[2] - b[1] * A[2, 2])
            + A[0, 2] * (b[1] * A[2, 1] - A[1, 1] * b[2])) / det
    z[1] = (A[0, 0] * (b[1] * A[2, 2] - A[1, 2] * b[2]) + b[0] * c01
            + A[0, 2] * (A[1, 0] * b[2] - b[1] * A[2, 0])) / det
    z[2] = (A[0, 0] * (A[1, 1] * b[2] - b[1] * A[2, 1]) + A[0, 1] * (b[1] * A[2, 0] - A[1, 0] * b[2])
            + b[0] * c02) / det
    return z


@njit(cache=True)
def accelerations(x, u, f, gen, prm):
    """q_ddot (6,) at state x under torques u, pivot force f and extra generalized force gen."""
    l1, l2, r = prm[_L1], prm[_L2], prm[_R]
    mc, ic0, xb, yb = prm[_MC], prm[_IC], prm[_XB], prm[_YB]
    mp, ip, xf, yf = prm[_MP], prm[_IP], prm[_XF], prm[_YF]
    ia, bw, bp = prm[_IA], prm[_BW], prm[_BP]
    a = x[2]
    th = x[2] - x[5]
    ad = x[8]
    thd = x[8] - x[11]
    sa, ca, st, ct = np.sin(a), np.cos(a), np.sin(th), np.cos(th)
    # mass matrix entries
    m13 = -mp * yf * ca - mp * xf * sa - mc * yb * ct - mc * xb * st
    m23 = mp * xf * ca - mp * yf * sa + mc * xb * ct - mc * yb * st
    m16 = mc * yb * ct + mc * xb * st
    m26 = mc * yb * st - mc * xb * ct
    ic = mc * (xb * xb + yb * yb) + ic0
    m33 = ic + mp * (xf * xf + yf * yf) + ip
    mt = mc + mp
    M = np.zeros((6, 6))
    M[0, 0] = mt
    M[1, 1] = mt
    M[0, 2] = m13
    M[2, 0] = m13
    M[1, 2] = m23
    M[2, 1] = m23
    M[0, 5] = m16
    M[5, 0] = m16
    M[1, 5] = m26
    M[5, 1] = m26
    M[2, 2] = m33
    M[2, 5] = -ic
    M[5, 2] = -ic
    M[3, 3] = ia
    M[4, 4] = ia
    M[5, 5] = ic
    # Lambda = [I; Miik], Delta = [Mfik; I]
    k = 1.0 / (r * l1)
    Miik = np.empty((3, 3))
    Miik[0, 0] = (l1 * ct - l2 * st) * k
    Miik[0, 1] = (l2 * ct + l1 * st) * k
    Miik[0, 2] = 0.0
    Miik[1, 0] = (l1 * ct + l2 * st) * k
    Miik[1, 1] = (-l2 * ct + l1 * st) * k
    Miik[1, 2] = 0.0
    Miik[2, 0] = st / l1
    Miik[2, 1] = -ct / l1
    Miik[2, 2] = 1.0
    Miikd = np.empty((3, 3))
    Miikd[0, 0] = (-l1 * st - l2 * ct) * k * thd
    Miikd[0, 1] = (-l2 * st + l1 * ct) * k * thd
    Miikd[0, 2] = 0.0
    Miikd[1, 0] = (-l1 * st + l2 * ct) * k * thd
    Miikd[1, 1] = (l2 * st + l1 * ct) * k * thd
    Miikd[1, 2] = 0.0
    Miikd[2, 0] = ct / l1 * thd
    Miikd[2, 1] = st / l1 * thd
    Miikd[2, 2] = 0.0
    kf = r / (2.0 * l2)
    Mfik = np.empty((3, 3))
    Mfik[0, 0] = kf * (l2 * ct - l1 * st)
    Mfik[0, 1] = kf * (l2 * ct + l1 * st)
    Mfik[0, 2] = 0.0
    Mfik[1, 0] = kf * (l1 * ct + l2 * st)
    Mfik[1, 1] = kf * (-l1 * ct + l2 * st)
    Mfik[1, 2] = 0.0
    Mfik[2, 0] = kf
    Mfik[2, 1] = -kf
    Mfik[2, 2] = 1.0
    L = np.zeros((6, 3))
    D = np.zeros((6, 3))
    for i in range(3):
        L[i, i] = 1.0
        D[3 + i, i] = 1.0
        for j in range(3):
            L[3 + i, j] = Miik[i, j]
            D[i, j] = Mfik[i, j]
    pd = x[6:9]
    qd = np.empty(6)
    qd[:3] = pd
    qd[3:] = x[9:12]
    # (C - E_f) q_dot + M Lambda_dot p_dot  ->  h (6,)
    cb1 = thd * mc * (xb * ct - yb * st)
    cf1 = ad * mp * (xf * ca - yf * sa)
    cb2 = thd * mc * (yb * ct + xb * st)
    cf2 = ad * mp * (yf * ca + xf * sa)
    h = np.zeros(6)
    h[0] = (-cb1 - cf1) * qd[2] + cb1 * qd[5]
    h[1] = (-cb2 - cf2) * qd[2] + cb2 * qd[5]
    h[3] = bw * qd[3]
    h[4] = bw * qd[4]
    h[5] = bp * qd[5]
    ldp = np.zeros(6)
    ldp[3:] = Miikd @ pd
    h += M @ ldp
    # generalized external forces
    qe = gen.copy()
    qe[0] += f[0]
    qe[1] += f[1]
    Mbar = D.T @ (M @ L)
    rhs = u + D.T @ (qe - h)
    pdd = _solve3(Mbar, rhs)
    out = np.empty(6)
    out[:3] = pdd
    out[3:] = Miik @ pdd + Miikd @ pd
    return out


#: Bench fixtures: the robot on the floor (full model), on a stand (chassis held,
#: wheels spin freely) and with both wheels locked on the floor (chassis held).
FLOOR, STAND, LOCKED = 0, 1, 2


@njit(cache=True)
def fixture_accelerations(x, u, gen, prm, fixture):
    """q_ddot (6,) with the chassis held fixed (``STAND`` or ``LOCKED``).

    The platform turns about the pivot: (I_p + m_p |PF|^2) phi_p_dd = tau_p - b_p phi_p_d,
    alpha follows phi_p; on the stand each wheel obeys I_a phi_dd = tau - b_w phi_d,
    locked wheels do not move.
    """
    out = np.zeros(6)
    ipp = prm[_IP] + prm[_MP] * (prm[_XF] ** 2 + prm[_YF] ** 2)
    out[5] = (u[2] + gen[5] - prm[_BP] * x[11]) / ipp
    out[2] = out[5]
    if fixture == STAND:
        out[3] = (u[0] + gen[3] - prm[_BW] * x[9]) / prm[_IA]
        out[4] = (u[1] + gen[4] - prm[_BW] * x[10]) / prm[_IA]
    return out


@njit(cache=True)
def derivative(x, u, f, gen, prm, fixture=FLOOR):
    """x_dot (12,) = (q_dot, q_ddot)."""
    xd = np.empty(12)
    xd[:6] = x[6:]
    if fixture == FLOOR:
        xd[6:] = accelerations(x, u, f, gen, prm)
    else:
        xd[6:] = fixture_accelerations(x, u, gen, prm, fixture)
    return xd


@njit(cache=True)
def rk4_zoh(x0, U, F, dt, substeps, prm, fixture=FLOOR):
    """Integrate N zero-order-hold intervals of length dt with classical RK4.

    U (N, 3) torques and F (N, 2) pivot forces held on [t_k, t_k+1); each interval
    is split into ``substeps`` RK4 steps. Returns X (N+1, 12) at the interval ends.
    """
    n = U.shape[0]
    X = np.empty((n + 1, 12))
    X[0] = x0
    h = dt / substeps
    gen = np.zeros(6)
    x = x0.copy()
    for k in range(n):
        u = U[k]
        f = F[k]
        for _ in range(substeps):
            k1 = derivative(x, u, f, gen, prm, fixture)
            k2 = derivative(x + 0.5 * h * k1, u, f, gen, prm, fixture)
            k3 = derivative(x + 0.5 * h * k2, u, f, gen, prm, fixture)
            k4 = derivative(x + h * k3, u, f, gen, prm, fixture)
            x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        X[k + 1] = x
    return X
