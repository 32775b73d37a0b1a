"""Compiled (numba) hot path of the pose EKF: the IMU prediction and the gated Kalman update.

numpy spends most of a step of an 11-state filter in call overhead (tens of small arrays per step,
~1 us each), not in arithmetic; these kernels do the same algebra on caller-owned arrays in place
(``benchmarks/estimation.py`` measures both). The filter's logic -- which update when, gates,
re-anchoring, faults -- stays in ``otbot_hw.estimation.ekf``. State order as there.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

X, Y, A, VX, VY, VA, BG, BAX, BAY, KAPPA, EP = range(11)


@njit(cache=True)
def all_finite(a) -> bool:
    for v in a.ravel():
        if not math.isfinite(v):
            return False
    return True


@njit(cache=True)
def predict_imu(x, P, fx, fy, w_new, new_gyro, dt, hold, accel_var, gyro_var, bg_walk2, ba_walk2, F, Q):
    """Strapdown step in place: x_dd, y_dd = R(alpha_mid)(f'' - b_a), alpha by the trapezoid of the
    previous rate and the new gyro reading less b_g (or the previous rate when no new reading).
    ``hold``: the IMU sample period (s) -- the reading's noise is spread over the steps it drives.
    F and Q are (11, 11) work arrays; on return they hold the step's transition and process noise."""
    bg = x[BG]
    va0 = x[VA]
    va1 = w_new - bg if new_gyro else va0
    am = x[A] + 0.25 * (va0 + va1) * dt
    c, s = math.cos(am), math.sin(am)
    gx, gy = fx - x[BAX], fy - x[BAY]
    ax, ay = c * gx - s * gy, s * gx + c * gy
    dax, day = -ay, ax
    h2 = 0.5 * dt * dt
    F[:, :] = 0.0
    Q[:, :] = 0.0
    for i in range(11):
        F[i, i] = 1.0
    F[X, VX] = dt
    F[Y, VY] = dt
    F[X, A] = h2 * dax
    F[Y, A] = h2 * day
    F[VX, A] = dt * dax
    F[VY, A] = dt * day
    F[X, BAX] = -h2 * c
    F[X, BAY] = h2 * s
    F[Y, BAX] = -h2 * s
    F[Y, BAY] = -h2 * c
    F[VX, BAX] = -dt * c
    F[VX, BAY] = dt * s
    F[VY, BAX] = -dt * s
    F[VY, BAY] = -dt * c
    x[X] += x[VX] * dt + h2 * ax
    x[Y] += x[VY] * dt + h2 * ay
    x[VX] += ax * dt
    x[VY] += ay * dt
    qv = accel_var * dt * max(hold, dt)
    Q[X, X] = Q[Y, Y] = qv * 0.25 * dt * dt
    Q[X, VX] = Q[VX, X] = Q[Y, VY] = Q[VY, Y] = qv * 0.5 * dt
    Q[VX, VX] = Q[VY, VY] = qv
    if new_gyro:
        F[A, VA] = 0.5 * dt
        F[A, BG] = -0.5 * dt
        F[VA, VA] = 0.0
        F[VA, BG] = -1.0
        Q[A, A] = 0.25 * dt * dt * gyro_var
        Q[A, VA] = Q[VA, A] = 0.5 * dt * gyro_var
        Q[VA, VA] = gyro_var
        x[A] += 0.5 * (va0 + va1) * dt
        x[VA] = va1
    else:
        F[A, VA] = dt
        x[A] += va0 * dt
    Q[BG, BG] = bg_walk2 * dt
    Q[BAX, BAX] = Q[BAY, BAY] = ba_walk2 * dt
    FP = np.zeros((11, 11))
    for i in range(11):
        for k in range(11):
            f = F[i, k]
            if f != 0.0:
                for j in range(11):
                    FP[i, j] += f * P[k, j]
    for i in range(11):
        for j in range(i, 11):
            acc = Q[i, j]
            for k in range(11):
                f = F[j, k]
                if f != 0.0:
                    acc += FP[i, k] * f
            P[i, j] = acc
            P[j, i] = acc


@njit(cache=True)
def _inverse(S):
    """Inverse of a symmetric positive 1x1, 2x2 or 3x3 matrix (cofactors; no LAPACK to compile)."""
    m = S.shape[0]
    out = np.empty((m, m))
    if m == 1:
        out[0, 0] = 1.0 / S[0, 0]
    elif m == 2:
        d = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
        out[0, 0], out[1, 1] = S[1, 1] / d, S[0, 0] / d
        out[0, 1], out[1, 0] = -S[0, 1] / d, -S[1, 0] / d
    else:
        a, b, c = S[0, 0], S[0, 1], S[0, 2]
        d, e, f = S[1, 0], S[1, 1], S[1, 2]
        g, h, i = S[2, 0], S[2, 1], S[2, 2]
        A, B, C = e * i - f * h, -(d * i - f * g), d * h - e * g
        det = a * A + b * B + c * C
        out[0, 0], out[1, 0], out[2, 0] = A / det, B / det, C / det
        out[0, 1], out[1, 1], out[2, 1] = -(b * i - c * h) / det, (a * i - c * g) / det, -(a * h - b * g) / det
        out[0, 2], out[1, 2], out[2, 2] = (b * f - c * e) / det, -(a * f - c * d) / det, (a * e - b * d) / det
    return out


@njit(cache=True)
def gated_update(x, P, nu, H, R, gate, force, update_accel_bias):
    """Kalman update in place unless the squared Mahalanobis distance of ``nu`` (m <= 3 values) exceeds
    ``gate`` (and ``force`` is False). Without ``update_accel_bias`` the accelerometer biases are
    considered (Schmidt-Kalman: zero gain; covariance P+ = P - K H P - P H^T K^T + K S K^T, valid for any
    gain). Returns (nis, accepted)."""
    n, m = P.shape[0], H.shape[0]
    PHt = np.zeros((n, m))
    for i in range(n):
        for j in range(m):
            acc = 0.0
            for k in range(n):
                acc += P[i, k] * H[j, k]
            PHt[i, j] = acc
    S = R.copy()
    for i in range(m):
        for j in range(m):
            acc = 0.0
            for k in range(n):
                acc += H[i, k] * PHt[k, j]
            S[i, j] += acc
    Sinv = _inverse(S)
    d2 = 0.0
    for i in range(m):
        for j in range(m):
            d2 += nu[i] * Sinv[i, j] * nu[j]
    if not (d2 <= gate or force):
        return d2, False
    K = np.zeros((n, m))
    for i in range(n):
        for j in range(m):
            for k in range(m):
                K[i, j] += PHt[i, k] * Sinv[k, j]
    if not update_accel_bias:
        K[BAX, :] = 0.0
        K[BAY, :] = 0.0
    for i in range(n):
        acc = 0.0
        for j in range(m):
            acc += K[i, j] * nu[j]
        x[i] += acc
    KS = np.zeros((n, m))
    for i in range(n):
        for j in range(m):
            for k in range(m):
                KS[i, j] += K[i, k] * S[k, j]
    for i in range(n):
        for j in range(i, n):
            acc = P[i, j]
            for k in range(m):
                acc += -K[i, k] * PHt[j, k] - PHt[i, k] * K[j, k] + KS[i, k] * K[j, k]
            P[i, j] = acc
            P[j, i] = acc
    return d2, True


@njit(cache=True)
def joint_rates(x, phi_p, l1, l2, r, H, nu, phid):
    """Innovation of the joint rates phi_dot - M_IIK(theta) p_dot into ``nu`` (3,) and its Jacobian into
    ``H`` (3, 11) (paper §2.3.2). theta = alpha - phi_p, the pivot angle being the reading ``phi_p`` less
    its quantization error e_p (a state)."""
    th = x[A] - phi_p + x[EP]
    c, s = math.cos(th), math.sin(th)
    n = 1.0 / (r * l1)
    m00, m01 = n * (l1 * c - l2 * s), n * (l2 * c + l1 * s)
    m10, m11 = n * (l1 * c + l2 * s), n * (-l2 * c + l1 * s)
    m20, m21 = s / l1, -c / l1
    vx, vy, va = x[VX], x[VY], x[VA]
    H[:, :] = 0.0
    H[0, VX], H[0, VY] = m00, m01
    H[1, VX], H[1, VY] = m10, m11
    H[2, VX], H[2, VY], H[2, VA] = m20, m21, 1.0
    H[0, A] = n * ((-l1 * s - l2 * c) * vx + (-l2 * s + l1 * c) * vy)
    H[1, A] = n * ((-l1 * s + l2 * c) * vx + (l2 * s + l1 * c) * vy)
    H[2, A] = (c * vx + s * vy) / l1
    H[0, EP], H[1, EP], H[2, EP] = H[0, A], H[1, A], H[2, A]
    nu[0] = phid[0] - (m00 * vx + m01 * vy)
    nu[1] = phid[1] - (m10 * vx + m11 * vy)
    nu[2] = phid[2] - (m20 * vx + m21 * vy + va)
