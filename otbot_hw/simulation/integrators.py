"""The integrators: classical RK4 over zero-order-hold intervals, compiled (numba). The model gives
derivatives (``otbot_hw.model.compiled`` for the paper's model, ``otbot_hw.model.effect_physics`` for the
extended one); time advances only here.

* ``rk4_zoh``: the paper's model, x = (q, q_dot) (12,);
* ``ext_rk4_zoh`` / ``ext_rk4_zoh_samples``: the extended model on z = (x, wheel slip angles) (14,),
  with the current-loop lag integrated exactly inside each interval. With every effect at zero it
  gives ``rk4_zoh``'s states (``tests/test_effects.py``); ``rk4_zoh`` stays as the paper model's fast
  path (identification fits it thousands of times).

Torques U (N, 3) N m and pivot forces F (N, 2) N (ground frame) are held on [t_k, t_k+1); each
interval is split into ``substeps`` RK4 steps; work arrays are allocated once per call.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from otbot_hw.model.compiled import FLOOR, _derivative_into
from otbot_hw.model.effect_catalog import T_I
from otbot_hw.model.effect_physics import actuated_torque, ext_derivative_into, forces_active, lagged_torque_into


@njit(cache=True)
def rk4_zoh(x0, U, F, dt, substeps, prm, fixture=FLOOR):
    """Integrate N zero-order-hold intervals of length dt with classical RK4.

    U (N, 3) torques and F (N, 2) pivot forces held on [t_k, t_k+1); each interval
    is split into ``substeps`` RK4 steps. Returns X (N+1, 12) at the interval ends.
    All work arrays are allocated once.
    """
    X = np.empty((U.shape[0] + 1, 12))
    rk4_zoh_into(x0, U, F, dt, substeps, prm, fixture, X)
    return X


@njit(cache=True, nogil=True)
def rk4_zoh_into(x0, U, F, dt, substeps, prm, fixture, X):
    """``rk4_zoh`` writing into caller-owned X (N+1, 12)."""
    n = U.shape[0]
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


@njit(cache=True, nogil=True)
def ext_rk4_zoh(x0, tau0, U, F, dt, substeps, prm, eff, fixture):
    """Integrate the extended model over N ZOH intervals of commands U (N, 3), forces F (N, 2).

    Returns X (N+1, 12) states (rolling-angle coordinates), TAU (N+1, 3) delivered torque
    at the samples (TAU[k] = delivered torque at t_k, with the command u_k applied) and
    S (N+1, 2) wheel slip angles (rad). tau0 (3,) is the delivered torque just before t_0.
    Work arrays are allocated once (classical RK4 on z = (x, slip angles)).
    """
    n = U.shape[0]
    X, TAU, S = np.empty((n + 1, 12)), np.empty((n + 1, 3)), np.zeros((n + 1, 2))
    ext_rk4_into(x0, tau0, U, F, dt, substeps, prm, eff, fixture, X, TAU, S, np.empty((0, 6)), np.empty((0, 2)))
    return X, TAU, S


@njit(cache=True, nogil=True)
def ext_rk4_zoh_samples(x0, tau0, U, F, dt, substeps, prm, eff, fixture):
    """``ext_rk4_zoh`` that also returns QDD (N+1, 6), the accelerations at the samples (under TAU[k]
    and F[k], the last sample under F[N-1]), and SD (N+1, 2), the slip rates there: what
    ``ext_sample_accelerations`` and ``slip_rate_samples`` give, taken from the first RK4 stage of
    each interval (the same evaluation), so they cost one evaluation for the last sample only."""
    n = U.shape[0]
    X, TAU, S = np.empty((n + 1, 12)), np.empty((n + 1, 3)), np.zeros((n + 1, 2))
    QDD, SD = np.empty((n + 1, 6)), np.empty((n + 1, 2))
    ext_rk4_into(x0, tau0, U, F, dt, substeps, prm, eff, fixture, X, TAU, S, QDD, SD)
    return X, TAU, S, QDD, SD


@njit(cache=True, nogil=True)
def ext_rk4_into(x0, tau0, U, F, dt, substeps, prm, eff, fixture, X, TAU, S, QDD, SD):
    """The RK4 of ``ext_rk4_zoh`` writing into caller-owned X (N+1, 12), TAU (N+1, 3), S (N+1, 2) (S[0], the
    slip angles at t_0, is read, not written: zero unless the caller continues a run); and
    into QDD, SD when they have N+1 rows (``otbot_hw.simulation.simulator.Stepper`` keeps its one-interval
    outputs)."""
    n = U.shape[0]
    samples = QDD.shape[0] == n + 1
    if not samples and eff[T_I] == 0.0 and not forces_active(eff):
        # no effect force, slip or current lag (the paper's model, or one whose effects act only on
        # the drives' gain and saturation or the sensors): the paper's integrator on the actuated
        # torques, the same arithmetic as the extended RK4 below, at the paper model's speed (the
        # call through the effect layer cost the paper model's stepper half its speed)
        UA = np.empty((n, 3))
        for k in range(n):
            UA[k] = actuated_torque(U[k], eff)
            TAU[k] = UA[k]
        rk4_zoh_into(x0, UA, F, dt, substeps, prm, fixture, X)
        TAU[n] = UA[n - 1] if n > 0 else tau0
        S[:] = 0.0
        return
    # scratch allocated here, each its own array: slices of one caller-owned buffer may alias for LLVM,
    # which then keeps the RK4 loops scalar (5 % slower, measured)
    z, k1, k2, k3, k4, zs = np.empty(14), np.empty(14), np.empty(14), np.empty(14), np.empty(14), np.empty(14)
    gen, acc, g2, slip = np.empty(6), np.empty(6), np.empty(6), np.empty(2)
    t1, t2, t3, ta = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for i in range(12):
        z[i] = x0[i]
    z[12] = S[0, 0]  # the slip before t_0: 0 (ext_rk4_zoh*, the Stepper's step), a chunk's start in
    z[13] = S[0, 1]  # simulator.simulate_extended (the sum goes on as in one call: the same numbers)
    X[0] = x0
    h = dt / substeps
    T = eff[T_I]
    for i in range(3):
        ta[i] = tau0[i]
    for k in range(n):
        tc = actuated_torque(U[k], eff)
        f = F[k]
        lagged_torque_into(tc, ta, 0.0, T, TAU[k])
        for j in range(substeps):
            s0 = j * h
            lagged_torque_into(tc, ta, s0, T, t1)
            lagged_torque_into(tc, ta, s0 + 0.5 * h, T, t2)
            lagged_torque_into(tc, ta, s0 + h, T, t3)
            ext_derivative_into(z, t1, f, eff, prm, fixture, k1, gen, acc, g2, slip)
            if samples and j == 0:  # the state X[k] under TAU[k] (t1 at s0 = 0)
                for i in range(6):
                    QDD[k, i] = k1[6 + i]
                SD[k, 0] = k1[12]
                SD[k, 1] = k1[13]
            for i in range(14):
                zs[i] = z[i] + 0.5 * h * k1[i]
            ext_derivative_into(zs, t2, f, eff, prm, fixture, k2, gen, acc, g2, slip)
            for i in range(14):
                zs[i] = z[i] + 0.5 * h * k2[i]
            ext_derivative_into(zs, t2, f, eff, prm, fixture, k3, gen, acc, g2, slip)
            for i in range(14):
                zs[i] = z[i] + h * k3[i]
            ext_derivative_into(zs, t3, f, eff, prm, fixture, k4, gen, acc, g2, slip)
            for i in range(14):
                z[i] = z[i] + (h / 6.0) * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
        lagged_torque_into(tc, ta, dt, T, t1)
        for i in range(3):
            ta[i] = t1[i]
        X[k + 1] = z[:12]
        S[k + 1] = z[12:14]
    if n > 0:
        lagged_torque_into(actuated_torque(U[n - 1], eff), ta, 0.0, T, TAU[n])
    else:
        TAU[0] = tau0
    if samples:
        f = F[n - 1] if n > 0 else np.zeros(2)
        ext_derivative_into(z, TAU[n], f, eff, prm, fixture, k1, gen, acc, g2, slip)
        for i in range(6):
            QDD[n, i] = k1[6 + i]
        SD[n, 0] = k1[12]
        SD[n, 1] = k1[13]

