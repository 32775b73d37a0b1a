"""One IMU-predicted cycle of the pose EKF as a single compiled call (``PoseEKF.step``'s common path).

``PoseEKF.step`` used to cross from Python into compiled code up to ten times per cycle (pivot error,
a held reading's correction, yaw acceleration, prediction, pivot motion, joint-rate Jacobian, two
gated updates, health), each
crossing paying numba's argument dispatch (1-3 us in the daemon's loop, where other threads share the
interpreter and the caches). ``imu_cycle`` runs the same kernels in the same order on the same
arrays inside one call, so the filter's numbers do not change (``tests/test_ekf_kernels.py`` replays
a recorded run against estimates of the code before); the branches that are rare (a rejected
heading's re-anchoring, standstill, the gyro, the count constraint, the model prediction) stay in
``otbot_hw.estimation.ekf``. State order as there.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from otbot_hw.estimation import kernels
from otbot_hw.estimation.kernels import A, EP, KAPPA, NAX, NAY
from otbot_hw.model import compiled

#: Layout of ``imu_cycle``'s scalar input ``s`` (one float64 array, filled by ``PoseEKF``).
#: ``S_HELD``: the reading driving the step is an older one, taken under the torque ``u_reading``.
(S_DT, S_FX, S_FY, S_PHI_OLD, S_PHI_NEW, S_PHI_R, S_PHI_L, S_HAVE_TORQUE, S_NEW_NOISE, S_HELD, S_VAR_ACC,
 S_VAR_ALPHA_DD, S_BG_WALK2, S_BA_WALK2, S_DA_WALK2, S_L1, S_L2, S_R, S_K, S_GATE_ENC, S_GATE_HEAD,
 S_COUNT, S_VAR_Q, N_SCALARS) = range(24)
#: Layout of its output ``res``: the pivot reading's jump (rad, 0 when e_p was re-drawn), the joint
#: rates' NIS and acceptance (1/0), the wheel heading's residual (rad, wrapped), NIS and acceptance
#: (nan, -1 when not attempted: the rates were rejected), whether state and covariance are healthy after
#: these steps (``healthy``).
R_JUMP, R_NIS_ENC, R_OK_ENC, R_NU_HEAD, R_NIS_HEAD, R_OK_HEAD, R_HEALTHY, N_RESULTS = range(8)

_TWO_PI = 2.0 * math.pi


@njit(cache=True)
def imu_cycle(x, P, F, Q, u, u_reading, prm, s, phid, H_rates, nu3, R_rates, H_head, nu1, R_head, res):
    """One cycle in place on ``x`` (n,), ``P`` (n, n): the pivot error's first half step, the specific
    force (``s[S_FX]``, ``s[S_FY]``, B'') of a held reading (``s[S_HELD]``) corrected for the torque
    change since it (``held_force_correction``), the model's yaw
    acceleration under the torque ``u`` (3,) N m (when ``s[S_HAVE_TORQUE]``), the driving reading's noise
    re-drawn (``s[S_NEW_NOISE]``), the IMU prediction (``kernels.predict_imu``; ``F``, ``Q`` hold the
    step's), the pivot's second half step and its reading's jump, then the gated joint-rate update with the
    rates ``phid`` (3,) rad/s and, if accepted, the gated wheel-heading update. ``H_rates``, ``nu3``,
    ``nu1`` are work arrays; ``R_rates`` (3, 3), ``H_head`` (1, n), ``R_head`` (1, 1) the updates'
    constants; ``prm`` the model's parameter array. Scalars in ``s`` and results in ``res`` by the
    ``S_*`` and ``R_*`` indices of this module."""
    dt = s[S_DT]
    phi_old, phi_new = s[S_PHI_OLD], s[S_PHI_NEW]
    l1 = s[S_L1]
    kernels.pivot_error_step(x, P, phi_old, l1, 0.5 * dt)
    fx, fy = s[S_FX], s[S_FY]
    if s[S_HELD] != 0.0:
        fx, fy = held_force_correction(x, phi_old, u, u_reading, prm, fx, fy)
    add = 0.0
    if s[S_HAVE_TORQUE] != 0.0:
        c, sn = math.cos(x[A]), math.sin(x[A])
        gx, gy = fx - x[kernels.BAX], fy - x[kernels.BAY]
        add = kernels.yaw_acceleration(x, phi_old, u, c * gx - sn * gy, sn * gx + c * gy, prm)
    if s[S_NEW_NOISE] != 0.0:  # a new reading drives: its own noise, drawn afresh
        n = x.shape[0]
        for i in range(n):
            for j in range(NAX, NAY + 1):
                P[j, i] = 0.0
                P[i, j] = 0.0
        P[NAX, NAX] = P[NAY, NAY] = s[S_VAR_ACC]
        x[NAX] = x[NAY] = 0.0
    kernels.predict_imu(x, P, fx, fy, add, dt, s[S_VAR_ALPHA_DD], s[S_BG_WALK2], s[S_BA_WALK2], s[S_DA_WALK2], F, Q)
    # the pivot's second half step (the rates after the prediction), then its reading's jump
    kernels.pivot_error_step(x, P, phi_old, l1, 0.5 * dt)
    jump = phi_new - phi_old
    x[EP] += jump
    if abs(jump) > 1.5 * s[S_COUNT]:  # re-drawn: zero mean, the uniform's variance, uncorrelated
        for i in range(x.shape[0]):
            P[EP, i] = 0.0
            P[i, EP] = 0.0
        P[EP, EP] = s[S_VAR_Q]
        x[EP] = 0.0
        jump = 0.0
    res[R_JUMP] = jump
    kernels.joint_rates(x, phi_new, l1, s[S_L2], s[S_R], H_rates, nu3, phid)
    d2, ok = kernels.gated_update(x, P, nu3, H_rates, R_rates, s[S_GATE_ENC], False, False)
    res[R_NIS_ENC], res[R_OK_ENC] = d2, 1.0 if ok else 0.0
    res[R_NU_HEAD], res[R_NIS_HEAD], res[R_OK_HEAD] = math.nan, math.nan, -1.0
    if ok:
        a = s[S_K] * (s[S_PHI_R] - s[S_PHI_L]) + phi_new - (x[A] - x[KAPPA] + x[EP])
        nu1[0] = (a + math.pi) % _TWO_PI - math.pi
        d2, ok = kernels.gated_update(x, P, nu1, H_head, R_head, s[S_GATE_HEAD], False, False)
        res[R_NU_HEAD], res[R_NIS_HEAD], res[R_OK_HEAD] = nu1[0], d2, 1.0 if ok else 0.0
    res[R_HEALTHY] = 1.0 if healthy(x, P) else 0.0


@njit(cache=True)
def held_force_correction(x, phi_p, u, u_reading, prm, fx, fy):
    """An IMU slower than the loop: the specific force (fx, fy) m/s^2 in B'' of a reading held over several
    steps, plus the change of the pivot acceleration the torque made since the reading (taken under
    ``u_reading`` (3,) N m; now ``u``), M_bar^-1 (u - u_reading) from the paper's model at the filter state
    ``x`` (the pivot at the reading ``phi_p`` less e_p): linear in u, so only the torque difference enters
    and unmodelled forces acting on both cancel."""
    du = np.empty(3)
    moved = False
    for i in range(3):
        du[i] = u[i] - u_reading[i]
        moved = moved or du[i] != 0.0
    if not moved:
        return fx, fy
    q = np.empty(12)
    kernels.model_state(x, phi_p, prm, q)
    f, gen = np.zeros(2), np.zeros(6)
    a1, a0 = np.empty(6), np.empty(6)
    compiled._accel_into(q, du, f, gen, prm, a1)
    compiled._accel_into(q, np.zeros(3), f, gen, prm, a0)
    dp0, dp1 = a1[0] - a0[0], a1[1] - a0[1]
    c, sn = math.cos(x[A]), math.sin(x[A])
    return fx + c * dp0 + sn * dp1, fy - sn * dp0 + c * dp1


@njit(cache=True)
def healthy(x, P) -> bool:
    """Every state and covariance entry finite and every variance > 0."""
    if not (kernels.all_finite(x) and kernels.all_finite(P)):
        return False
    for i in range(P.shape[0]):
        if not P[i, i] > 0.0:
            return False
    return True


@njit(cache=True)
def estimate_vectors(x, P, out):
    """``out`` (14,) = pose (3), twist (3), their standard deviations (6), accelerometer biases (2)."""
    for i in range(6):
        out[i] = x[i]
        out[6 + i] = math.sqrt(P[i, i])
    out[12], out[13] = x[kernels.BAX], x[kernels.BAY]


_F8 = np.dtype(np.float64)


def plain_vectors(a, b, c) -> bool:
    """Whether ``a``, ``b``, ``c`` are all float64 numpy arrays of shape (3,) with finite values (the
    loop's sensor vectors: then ``PoseEKF.step`` takes them as they are, one check for the three)."""
    return (type(a) is np.ndarray and type(b) is np.ndarray and type(c) is np.ndarray and a.shape == (3,)
            and b.shape == (3,) and c.shape == (3,) and a.dtype == _F8 and b.dtype == _F8 and c.dtype == _F8
            and finite9(a, b, c))


@njit(cache=True)
def finite9(a, b, c) -> bool:
    for i in range(3):
        if not (math.isfinite(a[i]) and math.isfinite(b[i]) and math.isfinite(c[i])):
            return False
    return True
