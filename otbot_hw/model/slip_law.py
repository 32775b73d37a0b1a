"""The wheel slip law of the extended model (compiled): the quasi-static longitudinal slip of a wheel and,
with a traction limit, the traction curve solved from the wheel's torque balance (``effect_physics`` module
doc: "Wheel slip"). Split out of ``effect_physics``, which steps it."""
from __future__ import annotations

import numpy as np
from numba import njit

from otbot_hw.model.effect_catalog import K_SLIP, KN_TRAC, T_TRAC

K_SLIP_MIN = 1e-4  # rad/(s N m): creep of the traction curve when k_slip = 0 (rigid up to the limit)
#: knees kn_trac of known traction curves (``traction_curve``; every one: creep slope 1 / k_slip, limit t_trac)
KN_MAGIC = 0.0  # Pacejka's magic formula with C = 1, y / sqrt(1 + y^2) (the default)
KN_TANH = 1.0  # tanh y
KN_CLIP = 3.0  # a hard clip max(-1, min(y, 1))


@njit(cache=True)
def slip_state(tau_tr, b_i, eff):
    """(slip rate sigma rad/s, ground torque tau_g N m) of a wheel transmitting tau_tr.

    Without a traction limit: tau_g = tau_tr and sigma = k_slip tau_g (linear creep). With one
    (t_trac > 0) the traction curve tau_g(sigma) = t_trac tanh(h(y)), y = sigma / (k_slip t_trac), with
    the knee kn_trac (``traction_curve``: creep slope 1 / k_slip at small slip and the limit t_trac for
    every knee; kn_trac = 0, the default, is Pacejka's magic formula D sin(C atan(B y)) with C = 1,
    E = 0, 1 is tanh y, 3 a hard clip), and the wheel's balance tau_tr - b_i sigma = tau_g(sigma) (the
    motor's viscous friction acts on the spin rolling + sigma) give sigma, solved by safeguarded Newton
    (the balance is monotone): creep below the limit, spin-up until the viscous friction takes the excess.

    Why a knee parameter: fitted with one fixed knee to a simulator with another, the data see the knee,
    not the creep slope (T tanh(y) fitted to a magic-formula robot read k_slip +58 %; the magic formula
    fitted to a tanh robot -45 %)."""
    T = eff[T_TRAC]
    k = eff[K_SLIP]
    if T <= 0.0:
        return k * tau_tr, tau_tr
    kk = max(k, K_SLIP_MIN)
    b = max(b_i, 1e-3)
    kn = eff[KN_TRAC]
    # g(s) = tau_tr - b s - traction(s) decreases; the root lies between 0 and tau_tr / b
    lo, hi = min(0.0, tau_tr / b), max(0.0, tau_tr / b)
    s = min(max(kk * tau_tr, lo), hi) if abs(tau_tr) < T else (tau_tr - np.sign(tau_tr) * T) / b
    for _ in range(60):
        if kn == KN_MAGIC:  # the magic formula in closed form (bit for bit the curve before kn_trac)
            y = s / (kk * T)
            q = 1.0 / np.sqrt(1.0 + y * y)
            tg = T * y * q
            dt = q * q * q / kk
        else:
            tg, dt = _knee(s, kk, T, kn)
        g = tau_tr - b * s - tg
        if abs(g) < 1e-12 * (1.0 + abs(tau_tr)):
            break
        if g > 0.0:
            lo = s
        else:
            hi = s
        dg = -b - dt
        s_new = s - g / dg
        s = s_new if lo < s_new < hi else 0.5 * (lo + hi)
    return s, traction_curve(s, kk, T, kn)


@njit(cache=True)
def _knee(s, k, T, kn):
    """(ground torque N m, its slope d tau_g / d s N m s/rad) of the traction curve T tanh(h(y)), y = s / (k T):
    h(y) = asinh(a y) / a, a = sqrt(1 - kn) for kn < 1 (kn = 0: tanh(asinh y) = y / sqrt(1 + y^2), the magic
    formula; kn < 0 softer), h = y at kn = 1 (tanh), h = atanh(a y) / a, a = sqrt((kn - 1) / 2) for kn > 1
    (harder; kn = 3: tanh(atanh y) = y up to |y| = 1, a hard clip; above 3 the limit is reached before |y| = 1). h(y) = y - (1 - kn) y^3 / 6 + ... on both
    sides: the curve is smooth in kn, h'(0) = 1 (creep slope 1 / k for every knee)."""
    y = s / (k * T)
    if kn < 1.0:
        a = np.sqrt(1.0 - kn)
        h = np.arcsinh(a * y) / a
        hp = 1.0 / np.sqrt(1.0 + a * a * y * y)
    elif kn == 1.0:
        h = y
        hp = 1.0
    else:
        a = np.sqrt(0.5 * (kn - 1.0))
        if a * abs(y) >= 1.0:
            return T * np.sign(y), 0.0
        h = np.arctanh(a * y) / a
        hp = 1.0 / (1.0 - a * a * y * y)
    f = np.tanh(h)
    return T * f, (1.0 - f * f) * hp / k


@njit(cache=True)
def traction_curve(s, k, T, kn=KN_MAGIC):
    """Ground torque (N m) of a wheel slipping at s rad/s with creep slope 1 / k rad/(s N m), limit T N m and knee
    kn (``_knee``; kn = 0: T y / sqrt(1 + y^2), y = s / (k T), the magic formula with C = 1; 1: T tanh y; 3: a
    hard clip)."""
    if kn == KN_MAGIC:
        y = s / (k * T)
        return T * y / np.sqrt(1.0 + y * y)
    return _knee(s, k, T, kn)[0]


@njit(cache=True)
def slip_rate_series(tau_tr, b_i, eff):
    """Slip rates (N,) for transmitted torques tau_tr (N,) (``slip_state``)."""
    out = np.empty(len(tau_tr))
    for j in range(len(tau_tr)):
        out[j] = slip_state(tau_tr[j], b_i, eff)[0]
    return out
