"""Compiled (numba) forward dynamics and zero-order-hold integration: the fast path.

Same physics as ``otbot_hw.model.dynamics`` (multiplier-free forward dynamics,
paper Eq. forward_dyn2), written on flat arrays so numba can compile it:
``prm`` is ``OtbotParams.as_array()`` (order ``PARAM_NAMES``), x = (q, q_dot) (12,),
u = (tau_r, tau_l, tau_p) N m, f = (f_x, f_y) N at the pivot in the ground frame,
``gen`` is an extra generalized force (6,) added to the right-hand side (used by
model extensions; zeros for the paper's model).

The inner functions (``_accel_into``, ``_derivative_into``) write into caller-owned
arrays and work on scalars, so the integrator allocates nothing per step: about
0.13 us per model evaluation (``benchmarks/model.py``, ``docs/performance.md``).
"""
from __future__ import annotations

import numpy as np
from numba import njit

_L1, _L2, _R, _MC, _IC, _XB, _YB, _MP, _IP, _XF, _YF, _IA, _BW, _BP = range(14)


@njit(cache=True)
def _accel_into(x, u, f, gen, prm, out):
    """Write q_ddot (6,) into ``out``: allocation-free multiplier-free forward dynamics.

    With Lambda = [I3; M_IIK] and Delta = [M_FIK; I3] (paper §3.3), the task-space
    rows read M_bar p_dd = u + Delta^T (Q - h), h = (C - E_f) q_d + M Lambda_dot p_d,
    and the joint rows phi_dd = M_IIK p_dd + M_IIK_dot p_d. M (paper Fig.
    massmatrixexpr) couples only (x, y, alpha, phi_p) besides the wheel inertias,
    so every product below is written out on scalars.
    """
    l1, l2, r = prm[_L1], prm[_L2], prm[_R]
    mc, ic0, xb, yb = prm[_MC], prm[_IC], prm[_XB], prm[_YB]
    mp, ip, xf, yf = prm[_MP], prm[_IP], prm[_XF], prm[_YF]
    ia, bw, bp = prm[_IA], prm[_BW], prm[_BP]
    a = x[2]
    th = x[2] - x[5]
    pd0, pd1, ad = x[6], x[7], x[8]
    qd3, qd4, qd5 = x[9], x[10], x[11]
    thd = ad - qd5
    sa, ca, st, ct = np.sin(a), np.cos(a), np.sin(th), np.cos(th)
    # mass matrix entries (the rest: M11 = M22 = mt, M44 = M55 = ia, M36 = -ic, M66 = ic)
    m13 = -mp * yf * ca - mp * xf * sa - mc * yb * ct - mc * xb * st
    m23 = mp * xf * ca - mp * yf * sa + mc * xb * ct - mc * yb * st
    m16 = mc * yb * ct + mc * xb * st
    m26 = mc * yb * st - mc * xb * ct
    ic = mc * (xb * xb + yb * yb) + ic0
    m33 = ic + mp * (xf * xf + yf * yf) + ip
    mt = mc + mp
    # M_IIK (a_ij) and its time derivative (d_ij); third column (0, 0, 1) and (0, 0, 0)
    k = 1.0 / (r * l1)
    a00 = (l1 * ct - l2 * st) * k
    a01 = (l2 * ct + l1 * st) * k
    a10 = (l1 * ct + l2 * st) * k
    a11 = (-l2 * ct + l1 * st) * k
    a20 = st / l1
    a21 = -ct / l1
    kd = k * thd
    d00 = (-l1 * st - l2 * ct) * kd
    d01 = (-l2 * st + l1 * ct) * kd
    d10 = (-l1 * st + l2 * ct) * kd
    d11 = (l2 * st + l1 * ct) * kd
    d20 = ct / l1 * thd
    d21 = st / l1 * thd
    # M_FIK (b_ij); third row (kf, -kf, 1)
    kf = r / (2.0 * l2)
    b00 = kf * (l2 * ct - l1 * st)
    b01 = kf * (l2 * ct + l1 * st)
    b10 = kf * (l1 * ct + l2 * st)
    b11 = kf * (-l1 * ct + l2 * st)
    # G = M Lambda (6x3), column by column: M[:, j] + M[:, 3:6] M_IIK[:, j]
    # (column 2 has G[3:6, 2] = 0)
    g00 = mt + m16 * a20
    g10 = m26 * a20
    g20 = m13 - ic * a20
    g30 = ia * a00
    g40 = ia * a10
    g50 = m16 + ic * a20
    g01 = m16 * a21
    g11 = mt + m26 * a21
    g21 = m23 - ic * a21
    g31 = ia * a01
    g41 = ia * a11
    g51 = m26 + ic * a21
    g02 = m13 + m16
    g12 = m23 + m26
    g22 = m33 - ic
    # M_bar = Delta^T G = M_FIK^T G[0:3] + G[3:6]
    n00 = b00 * g00 + b10 * g10 + kf * g20 + g30
    n01 = b00 * g01 + b10 * g11 + kf * g21 + g31
    n02 = b00 * g02 + b10 * g12 + kf * g22
    n10 = b01 * g00 + b11 * g10 - kf * g20 + g40
    n11 = b01 * g01 + b11 * g11 - kf * g21 + g41
    n12 = b01 * g02 + b11 * g12 - kf * g22
    n20 = g20 + g50
    n21 = g21 + g51
    n22 = g22
    # w = M_IIK_dot p_dot; h = (C - E_f) q_dot + M [0; w]
    w0 = d00 * pd0 + d01 * pd1
    w1 = d10 * pd0 + d11 * pd1
    w2 = d20 * pd0 + d21 * pd1
    cb1 = thd * mc * (xb * ct - yb * st)
    cf1 = ad * mp * (xf * ca - yf * sa)
    cb2 = thd * mc * (yb * ct + xb * st)
    cf2 = ad * mp * (yf * ca + xf * sa)
    # e = Q - h with Q = gen + (f_x, f_y, 0, 0, 0, 0)
    e0 = gen[0] + f[0] - ((-cb1 - cf1) * ad + cb1 * qd5 + m16 * w2)
    e1 = gen[1] + f[1] - ((-cb2 - cf2) * ad + cb2 * qd5 + m26 * w2)
    e2 = gen[2] + ic * w2
    e3 = gen[3] - bw * qd3 - ia * w0
    e4 = gen[4] - bw * qd4 - ia * w1
    e5 = gen[5] - bp * qd5 - ic * w2
    # right-hand side u + Delta^T e
    r0 = u[0] + b00 * e0 + b10 * e1 + kf * e2 + e3
    r1 = u[1] + b01 * e0 + b11 * e1 - kf * e2 + e4
    r2 = u[2] + e2 + e5
    # p_dd = M_bar^-1 rhs by Cramer's rule (M_bar is well conditioned)
    c00 = n11 * n22 - n12 * n21
    c01 = n12 * n20 - n10 * n22
    c02 = n10 * n21 - n11 * n20
    inv = 1.0 / (n00 * c00 + n01 * c01 + n02 * c02)
    p0 = (r0 * c00 + n01 * (n12 * r2 - r1 * n22) + n02 * (r1 * n21 - n11 * r2)) * inv
    p1 = (n00 * (r1 * n22 - n12 * r2) + r0 * c01 + n02 * (n10 * r2 - r1 * n20)) * inv
    p2 = (n00 * (n11 * r2 - r1 * n21) + n01 * (r1 * n20 - n10 * r2) + r0 * c02) * inv
    out[0] = p0
    out[1] = p1
    out[2] = p2
    out[3] = a00 * p0 + a01 * p1 + w0
    out[4] = a10 * p0 + a11 * p1 + w1
    out[5] = a20 * p0 + a21 * p1 + p2 + w2


@njit(cache=True)
def accelerations(x, u, f, gen, prm):
    """q_ddot (6,) at state x under torques u, pivot force f and extra generalized force gen."""
    out = np.empty(6)
    _accel_into(x, u, f, gen, prm, out)
    return out


#: Bench fixtures: the robot on the floor (full model), on a stand (chassis held,
#: wheels spin freely) and with both wheels locked on the floor (chassis held).
FLOOR, STAND, LOCKED = 0, 1, 2


@njit(cache=True)
def _fixture_accel_into(x, u, gen, prm, fixture, out):
    """Write q_ddot (6,) with the chassis held fixed (``STAND`` or ``LOCKED``) into ``out``."""
    ipp = prm[_IP] + prm[_MP] * (prm[_XF] ** 2 + prm[_YF] ** 2)
    out[0] = 0.0
    out[1] = 0.0
    out[5] = (u[2] + gen[5] - prm[_BP] * x[11]) / ipp
    out[2] = out[5]
    if fixture == STAND:
        out[3] = (u[0] + gen[3] - prm[_BW] * x[9]) / prm[_IA]
        out[4] = (u[1] + gen[4] - prm[_BW] * x[10]) / prm[_IA]
    else:
        out[3] = 0.0
        out[4] = 0.0


@njit(cache=True)
def fixture_accelerations(x, u, gen, prm, fixture):
    """q_ddot (6,) with the chassis held fixed (``STAND`` or ``LOCKED``).

    The platform turns about the pivot: (I_p + m_p |PF|^2) phi_p_dd = tau_p - b_p phi_p_d,
    alpha follows phi_p; on the stand each wheel obeys I_a phi_dd = tau - b_w phi_d,
    locked wheels do not move.
    """
    out = np.empty(6)
    _fixture_accel_into(x, u, gen, prm, fixture, out)
    return out


@njit(cache=True)
def _derivative_into(x, u, f, gen, prm, fixture, out, acc):
    """Write x_dot (12,) into ``out``; ``acc`` (6,) is scratch space."""
    if fixture == FLOOR:
        _accel_into(x, u, f, gen, prm, acc)
    else:
        _fixture_accel_into(x, u, gen, prm, fixture, acc)
    for i in range(6):
        out[i] = x[6 + i]
        out[6 + i] = acc[i]


@njit(cache=True)
def derivative(x, u, f, gen, prm, fixture=FLOOR):
    """x_dot (12,) = (q_dot, q_ddot)."""
    xd = np.empty(12)
    _derivative_into(x, u, f, gen, prm, fixture, xd, np.empty(6))
    return xd


@njit(cache=True)
def rk4_zoh(x0, U, F, dt, substeps, prm, fixture=FLOOR):
    """Integrate N zero-order-hold intervals of length dt with classical RK4.

    U (N, 3) torques and F (N, 2) pivot forces held on [t_k, t_k+1); each interval
    is split into ``substeps`` RK4 steps. Returns X (N+1, 12) at the interval ends.
    All work arrays are allocated once.
    """
    n = U.shape[0]
    X = np.empty((n + 1, 12))
    h = dt / substeps
    gen = np.zeros(6)
    x = np.empty(12)
    for i in range(12):
        x[i] = x0[i]
        X[0, i] = x0[i]
    k1 = np.empty(12)
    k2 = np.empty(12)
    k3 = np.empty(12)
    k4 = np.empty(12)
    xs = np.empty(12)
    acc = np.empty(6)
    for k in range(n):
        u = U[k]
        f = F[k]
        for _ in range(substeps):
            _derivative_into(x, u, f, gen, prm, fixture, k1, acc)
            for i in range(12):
                xs[i] = x[i] + 0.5 * h * k1[i]
            _derivative_into(xs, u, f, gen, prm, fixture, k2, acc)
            for i in range(12):
                xs[i] = x[i] + 0.5 * h * k2[i]
            _derivative_into(xs, u, f, gen, prm, fixture, k3, acc)
            for i in range(12):
                xs[i] = x[i] + h * k3[i]
            _derivative_into(xs, u, f, gen, prm, fixture, k4, acc)
            for i in range(12):
                x[i] += (h / 6.0) * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
        for i in range(12):
            X[k + 1, i] = x[i]
    return X
