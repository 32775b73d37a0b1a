"""The wheel slip law of the extended model (compiled): the quasi-static longitudinal slip of a wheel and,
with a traction limit, the traction curve solved from the wheel's torque balance (``effect_physics`` module
doc: "Wheel slip"). Split out of ``effect_physics``, which steps it."""
from __future__ import annotations

import numpy as np
from numba import njit

from otbot_hw.model.effect_catalog import DC_TRAC, K_SLIP, T_TRAC

K_SLIP_MIN = 1e-4  # rad/(s N m): creep of the traction curve when k_slip = 0 (rigid up to the limit)
#: knee exponents c of the traction curve (``traction_curve``) that stand for known curve forms
KNEE_MAGIC = 2.0  # Pacejka's magic formula with C = 1 (the default, dc_trac = 0)
DC_TRAC_TANH = 0.7  # dc_trac of ~ t_trac tanh(y): c = 2.7, within 1.7 % of t_trac everywhere (same creep slope, limit)


@njit(cache=True)
def knee_exponent(eff):
    """Knee exponent c = 2 + dc_trac of the traction curve from the effect vector (dc_trac = 0: the magic
    formula), at least 1 (a softer knee is no longer a limit reached at finite slip)."""
    return max(KNEE_MAGIC + eff[DC_TRAC], 1.0)


@njit(cache=True)
def slip_state(tau_tr, b_i, eff):
    """(slip rate sigma rad/s, ground torque tau_g N m) of a wheel transmitting tau_tr.

    Without a traction limit: tau_g = tau_tr and sigma = k_slip tau_g (linear creep). With one
    (t_trac > 0) the traction curve tau_g(sigma) = t_trac y / (1 + |y|^c)^(1/c), y = sigma / (k_slip
    t_trac), c = ``knee_exponent`` (``traction_curve``: creep slope 1 / k_slip at small slip whatever c,
    the limit t_trac; c = 2, the default, is Pacejka's magic formula D sin(C atan(B y)) with C = 1,
    E = 0, approaching the limit as 1 / (2 y^2); c ~ 2.7 is tanh y to 1.7 % of the limit; large c a
    hard clip), and the wheel's balance tau_tr - b_i sigma = tau_g(sigma) (the motor's viscous friction
    acts on the spin rolling + sigma) give sigma, solved by safeguarded Newton (the balance is monotone):
    creep below the limit, spin-up until the viscous friction takes the excess above it.

    Why a knee parameter: fitted with one fixed knee to a simulator with another, the data see the knee,
    not the creep slope (T tanh(y) fitted to a magic-formula robot read k_slip +58 %; the magic formula
    fitted to a tanh robot -45 %)."""
    T = eff[T_TRAC]
    k = eff[K_SLIP]
    if T <= 0.0:
        return k * tau_tr, tau_tr
    kk = max(k, K_SLIP_MIN)
    b = max(b_i, 1e-3)
    c = knee_exponent(eff)
    # g(s) = tau_tr - b s - traction(s) decreases; the root lies between 0 and tau_tr / b
    lo, hi = min(0.0, tau_tr / b), max(0.0, tau_tr / b)
    s = min(max(kk * tau_tr, lo), hi) if abs(tau_tr) < T else (tau_tr - np.sign(tau_tr) * T) / b
    for _ in range(60):
        if c == KNEE_MAGIC:  # the magic formula in closed form (bit for bit the curve before dc_trac)
            y = s / (kk * T)
            q = 1.0 / np.sqrt(1.0 + y * y)
            tg = T * y * q
            dt = q * q * q / kk
        else:
            tg, dt = _knee(s, kk, T, c)
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
    return s, traction_curve(s, kk, T, c)


@njit(cache=True)
def _knee(s, k, T, c):
    """(ground torque N m, its slope d tau_g / d s N m s/rad) of the curve T y / (1 + |y|^c)^(1/c), y = s / (k T);
    the slope is (1 + |y|^c)^(-1/c - 1) / k. Evaluated through |y|^-c above |y| = 1 (no overflow at large c)."""
    y = s / (k * T)
    a = abs(y)
    if a <= 1.0:
        u = 1.0 + a ** c
        return T * y * u ** (-1.0 / c), u ** (-1.0 / c - 1.0) / k
    v = 1.0 + a ** (-c)  # (1 + a^c) = a^c v
    return T * np.sign(y) * v ** (-1.0 / c), a ** (-c - 1.0) * v ** (-1.0 / c - 1.0) / k


@njit(cache=True)
def traction_curve(s, k, T, c=KNEE_MAGIC):
    """Ground torque (N m) of a wheel slipping at s rad/s: T y / (1 + |y|^c)^(1/c), y = s / (k T) (creep slope
    1 / k rad/(s N m), limit T N m, knee exponent c; c = 2: T y / sqrt(1 + y^2), the magic formula with C = 1)."""
    if c == KNEE_MAGIC:
        y = s / (k * T)
        return T * y / np.sqrt(1.0 + y * y)
    return _knee(s, k, T, c)[0]


@njit(cache=True)
def slip_rate_series(tau_tr, b_i, eff):
    """Slip rates (N,) for transmitted torques tau_tr (N,) (``slip_state``)."""
    out = np.empty(len(tau_tr))
    for j in range(len(tau_tr)):
        out[j] = slip_state(tau_tr[j], b_i, eff)[0]
    return out
