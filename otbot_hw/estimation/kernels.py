"""Compiled (numba) hot path of the pose EKF: the IMU prediction and the gated Kalman update.

numpy spends most of a step of a 14-state filter in call overhead (tens of small arrays per step,
~1 us each), not in arithmetic; these kernels do the same algebra on caller-owned arrays in place
(``benchmarks/estimation.py`` measures both). The filter's logic -- which update when, gates,
re-anchoring, faults -- stays in ``otbot_hw.estimation.ekf``. State order as there.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from otbot_hw.model import compiled
from otbot_hw.model.kinematics import iik_dot_entries, iik_entries, model_state_into

X, Y, A, VX, VY, VA, BG, BAX, BAY, KAPPA, EP, DA, NAX, NAY = range(14)


@njit(cache=True)
def model_state(x, phi_p, prm, out):
    """Write the model state (q, q_dot) (12,) of the filter state ``x`` into ``out``: its pose and twist,
    the pivot at the reading ``phi_p`` less its quantization error e_p = reading - true angle (a state),
    joint rates by the inverse kinematics (``otbot_hw.model.kinematics.model_state_into``). The one
    place the filter turns its state into the model's."""
    model_state_into(x[X], x[Y], x[A], x[VX], x[VY], x[VA], phi_p - x[EP], prm[0], prm[1], prm[2], out)


@njit(cache=True)
def all_finite(a) -> bool:
    for v in a.ravel():
        if not math.isfinite(v):
            return False
    return True


@njit(cache=True)
def predict_imu(x, P, fx, fy, alpha_dd, dt, alpha_dd_var, bg_walk2, ba_walk2, da_walk2, F, Q):
    """Strapdown step in place: x_dd, y_dd = R(alpha_mid)(f'' - b_a) from the specific force (fx, fy) in
    B''; alpha_dot driven by ``alpha_dd`` (rad/s^2, the model's, ``yaw_acceleration``) plus the state d
    (the model's unknown share, a random walk of density ``da_walk2`` ((rad/s^2)^2/s)) and white noise of
    variance density ``alpha_dd_var`` ((rad/s^2)^2/Hz); alpha by the exact integral. The reading's own
    noise is the state (NAX, NAY), subtracted like the bias: it stays while the reading drives the steps
    (an IMU slower than the loop holds it) and ``PoseEKF`` re-draws it with every new reading. F and Q
    are (n, n) work arrays; on return they hold the step's transition and process noise. The gyro is a
    measurement (``PoseEKF``), not an input."""
    n = x.shape[0]
    h2 = 0.5 * dt * dt
    alpha_dd = alpha_dd + x[DA]
    am = x[A] + 0.5 * dt * x[VA] + 0.25 * dt * dt * alpha_dd
    c, s = math.cos(am), math.sin(am)
    gx, gy = fx - x[BAX] - x[NAX], fy - x[BAY] - x[NAY]
    ax, ay = c * gx - s * gy, s * gx + c * gy
    dax, day = -ay, ax
    F[:, :] = 0.0
    Q[:, :] = 0.0
    for i in range(n):
        F[i, i] = 1.0
    F[X, VX] = dt
    F[Y, VY] = dt
    F[A, VA] = dt
    F[A, DA] = h2
    F[VA, DA] = dt
    F[X, A] = h2 * dax
    F[Y, A] = h2 * day
    F[VX, A] = dt * dax
    F[VY, A] = dt * day
    F[X, VA] = 0.5 * dt * h2 * dax
    F[Y, VA] = 0.5 * dt * h2 * day
    F[VX, VA] = 0.5 * dt * dt * dax
    F[VY, VA] = 0.5 * dt * dt * day
    F[X, BAX] = -h2 * c
    F[X, BAY] = h2 * s
    F[Y, BAX] = -h2 * s
    F[Y, BAY] = -h2 * c
    F[VX, BAX] = -dt * c
    F[VX, BAY] = dt * s
    F[VY, BAX] = -dt * s
    F[VY, BAY] = -dt * c
    for k in range(2):  # the driving reading's own noise (NAX, NAY) enters like the bias
        F[X, NAX + k] = F[X, BAX + k]
        F[Y, NAX + k] = F[Y, BAX + k]
        F[VX, NAX + k] = F[VX, BAX + k]
        F[VY, NAX + k] = F[VY, BAX + k]
    x[X] += x[VX] * dt + h2 * ax
    x[Y] += x[VY] * dt + h2 * ay
    x[VX] += ax * dt
    x[VY] += ay * dt
    x[A] += x[VA] * dt + h2 * alpha_dd
    x[VA] += alpha_dd * dt
    Q[A, A] = alpha_dd_var * dt * dt * dt / 3.0
    Q[A, VA] = Q[VA, A] = alpha_dd_var * dt * dt / 2.0
    Q[VA, VA] = alpha_dd_var * dt
    Q[BG, BG] = bg_walk2 * dt
    Q[BAX, BAX] = Q[BAY, BAY] = ba_walk2 * dt
    Q[DA, DA] = da_walk2 * dt
    FP = np.zeros((n, n))
    for i in range(n):
        for k in range(n):
            f = F[i, k]
            if f != 0.0:
                for j in range(n):
                    FP[i, j] += f * P[k, j]
    for i in range(n):
        for j in range(i, n):
            acc = Q[i, j]
            for k in range(n):
                f = F[j, k]
                if f != 0.0:
                    acc += FP[i, k] * f
            P[i, j] = acc
            P[j, i] = acc


@njit(cache=True)
def yaw_acceleration(x, phi_p, u, ax, ay, prm):
    """alpha_dd (rad/s^2) of the paper's model at the filter state ``x`` (pose, twist; the pivot at the
    reading ``phi_p`` less e_p) under the joint torques ``u`` (3,) N m, with the unknown horizontal force
    at the pivot eliminated by the pivot's measured acceleration (ax, ay) m/s^2 (ground frame): the
    model is linear in that force, so the force that makes its x_dd, y_dd equal the measured ones is
    solved for and its share of alpha_dd added. Returns the model's alpha_dd without a force when the
    2x2 system is singular."""
    q = np.empty(12)
    model_state(x, phi_p, prm, q)
    gen = np.zeros(6)
    f = np.zeros(2)
    a0 = np.empty(6)
    a1 = np.empty(6)
    a2 = np.empty(6)
    compiled._accel_into(q, u, f, gen, prm, a0)
    f[0] = 1.0
    compiled._accel_into(q, u, f, gen, prm, a1)
    f[0] = 0.0
    f[1] = 1.0
    compiled._accel_into(q, u, f, gen, prm, a2)
    b00, b01 = a1[0] - a0[0], a2[0] - a0[0]
    b10, b11 = a1[1] - a0[1], a2[1] - a0[1]
    det = b00 * b11 - b01 * b10
    if abs(det) < 1e-12:
        return a0[2]
    rx, ry = ax - a0[0], ay - a0[1]
    fx = (b11 * rx - b01 * ry) / det
    fy = (-b10 * rx + b00 * ry) / det
    return a0[2] + fx * (a1[2] - a0[2]) + fy * (a2[2] - a0[2])


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
    ``H`` (3, n) (paper §2.3.2). theta = alpha - phi_p, the pivot angle being the reading ``phi_p`` less
    its quantization error e_p (a state)."""
    th = x[A] - phi_p + x[EP]
    c, s = math.cos(th), math.sin(th)
    m00, m01, m10, m11, m20, m21 = iik_entries(s, c, l1, l2, r)
    d00, d01, d10, d11, d20, d21 = iik_dot_entries(s, c, 1.0, l1, l2, r)  # d M_IIK / d theta
    vx, vy, va = x[VX], x[VY], x[VA]
    H[:, :] = 0.0
    H[0, VX], H[0, VY] = m00, m01
    H[1, VX], H[1, VY] = m10, m11
    H[2, VX], H[2, VY], H[2, VA] = m20, m21, 1.0
    H[0, A] = d00 * vx + d01 * vy
    H[1, A] = d10 * vx + d11 * vy
    H[2, A] = d20 * vx + d21 * vy
    H[0, EP], H[1, EP], H[2, EP] = H[0, A], H[1, A], H[2, A]
    nu[0] = phid[0] - (m00 * vx + m01 * vy)
    nu[1] = phid[1] - (m10 * vx + m11 * vy)
    nu[2] = phid[2] - (m20 * vx + m21 * vy + va)


@njit(cache=True)
def pivot_error_step(x, P, phi_p, l1, dt):
    """While the pivot reading ``phi_p`` stays, its error e_p = reading - true angle moves by minus the
    pivot's motion: e_p -= phi_p_dot dt, phi_p_dot = (sin th x_dot - cos th y_dot) / l1 + alpha_dot
    (M_IIK's last row, th = alpha - phi_p + e_p). In place: x[EP] and P = G P G^T, G the identity but for
    the row of e_p."""
    th = x[A] - phi_p + x[EP]
    c, s = math.cos(th), math.sin(th)
    vx, vy = x[VX], x[VY]
    _, _, _, _, a20, a21 = iik_entries(s, c, l1, 1.0, 1.0)  # M_IIK's last row (l2, r do not enter it)
    _, _, _, _, d20, d21 = iik_dot_entries(s, c, 1.0, l1, 1.0, 1.0)  # its derivative by theta
    x[EP] -= (a20 * vx + a21 * vy + x[VA]) * dt
    n = P.shape[0]
    g = np.zeros(n)
    g[EP] = 1.0
    dth = -dt * (d20 * vx + d21 * vy)
    g[A] += dth
    g[EP] += dth
    g[VX] = -dt * a20
    g[VY] = -dt * a21
    g[VA] = -dt
    row = np.zeros(n)
    for j in range(n):
        acc = 0.0
        for k in range(n):
            acc += g[k] * P[k, j]
        row[j] = acc
    pee = 0.0
    for k in range(n):
        pee += row[k] * g[k]
    for j in range(n):
        P[EP, j] = row[j]
        P[j, EP] = row[j]
    P[EP, EP] = pee


_SQRT2 = math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


@njit(cache=True)
def truncate(x, P, i, lo, hi, correct, plausible=0.0):
    """Truncate the Gaussian (x, P) to lo <= x[i] <= hi and match x[i]'s first two moments, in place (density
    truncation, Simon & Simon 2010), applied as the scalar Gaussian measurement of x[i] that gives exactly
    those moments. Every other state follows by its regression on x[i] (exact for a joint Gaussian) --
    unless the interval holds less than ``plausible`` of x[i]'s probability: then the states with
    ``correct[k]`` False are considered (Schmidt: zero gain, their covariance kept consistent), as so
    improbable a constraint says the linear regression does not hold there. Returns False, leaving x and
    P as they were, when the interval holds (next to) no probability."""
    mu, var = x[i], P[i, i]
    if var <= 0.0:
        return lo <= mu <= hi
    sd = math.sqrt(var)
    a, b = (lo - mu) / sd, (hi - mu) / sd
    if a > 0.0:  # both bounds above the mean: upper tails (no cancellation)
        z = 0.5 * (math.erfc(a / _SQRT2) - math.erfc(b / _SQRT2))
    elif b < 0.0:
        z = 0.5 * (math.erfc(-b / _SQRT2) - math.erfc(-a / _SQRT2))
    else:
        z = 1.0 - 0.5 * (math.erfc(-a / _SQRT2) + math.erfc(b / _SQRT2))
    if z < 1e-12:
        return False
    pa, pb = _INV_SQRT_2PI * math.exp(-0.5 * a * a), _INV_SQRT_2PI * math.exp(-0.5 * b * b)
    d = (pa - pb) / z
    mean = mu + sd * d
    new_var = var * max(1.0 + (a * pa - b * pb) / z - d * d, 1e-12)
    info = 1.0 / new_var - 1.0 / var
    if not info > 0.0:
        return True
    r = 1.0 / info  # the measurement of x[i] with these posterior moments
    s_ = var + r
    meas = mu + (mean - mu) * s_ / var
    n = x.shape[0]
    col = np.empty(n)
    k = np.empty(n)
    everything = z >= plausible
    for j in range(n):
        col[j] = P[j, i]
        k[j] = col[j] / s_ if (everything or correct[j]) else 0.0
    nu = meas - mu
    for j in range(n):
        x[j] += k[j] * nu
    for r_ in range(n):
        for c in range(n):
            P[r_, c] += -k[r_] * col[c] - col[r_] * k[c] + k[r_] * s_ * k[c]
    return True
