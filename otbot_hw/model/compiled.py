"""Compiled (numba) forward dynamics of the paper's model: the fast path (the integrators that advance
it are ``otbot_hw.simulation.integrators``).

Same physics as ``otbot_hw.model.dynamics`` (multiplier-free forward dynamics,
paper Eq. forward_dyn2), written on flat arrays so numba can compile it:
``prm`` is ``OtbotParams.as_array()`` (order ``PARAM_NAMES``), x = (q, q_dot) (12,),
u = (tau_r, tau_l, tau_p) N m, f = (f_x, f_y) N at the pivot in the ground frame,
``gen`` is an extra generalized force (6,) added to the right-hand side (used by
model extensions; zeros for the paper's model).

The inner functions (``_accel_into``, ``_derivative_into``) write into caller-owned
arrays and work on scalars, so an integrator allocates nothing per step: about
0.13 us per model evaluation (``benchmarks/model.py``, ``docs/performance.md``).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from otbot_hw.model.kinematics import fik_entries, iik_dot_entries, iik_entries

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
    # M_IIK (a_ij), its time derivative (d_ij) and M_FIK (b_ij) (``otbot_hw.model.kinematics``)
    a00, a01, a10, a11, a20, a21 = iik_entries(st, ct, l1, l2, r)
    d00, d01, d10, d11, d20, d21 = iik_dot_entries(st, ct, thd, l1, l2, r)
    b00, b01, b10, b11, kf = fik_entries(st, ct, l1, l2, r)
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
