"""The wheel slip law of the extended model (compiled): the quasi-static longitudinal slip of a wheel and,
with a traction limit, the traction curve solved from the wheel's torque balance (``effect_physics`` module
doc: "Wheel slip"). Split out of ``effect_physics``, which steps it."""
from __future__ import annotations

import numpy as np
from numba import njit

from otbot_hw.model.effect_catalog import K_SLIP, T_TRAC

K_SLIP_MIN = 1e-4  # rad/(s N m): creep of the traction curve when k_slip = 0 (rigid up to the limit)


@njit(cache=True)
def slip_state(tau_tr, b_i, eff):
    """(slip rate sigma rad/s, ground torque tau_g N m) of a wheel transmitting tau_tr.

    Without a traction limit: tau_g = tau_tr and sigma = k_slip tau_g (linear creep). With one
    (t_trac > 0) the traction curve tau_g(sigma) = t_trac y / sqrt(1 + y^2), y = sigma / (k_slip
    t_trac) (``traction_curve``: Pacejka's magic formula D sin(C atan(B y)) with C = 1, E = 0 --
    creep slope 1 / k_slip at small slip, the limit t_trac approached as 1 / (2 y^2)), and the
    wheel's balance tau_tr - b_i sigma = tau_g(sigma) (the motor's viscous friction acts on the
    spin rolling + sigma) give sigma, solved by safeguarded Newton (the balance is monotone):
    creep below the limit, spin-up until the viscous friction takes the excess above it.

    The curve was T tanh(y): the same creep slope and limit but a knee that closes exponentially;
    fitted to the independent robot's magic-formula traction (benchmarks/independent_robot.py) it
    read t_trac right and k_slip +58 % (the data see the knee, not the creep slope)."""
    T = eff[T_TRAC]
    k = eff[K_SLIP]
    if T <= 0.0:
        return k * tau_tr, tau_tr
    kk = max(k, K_SLIP_MIN)
    b = max(b_i, 1e-3)
    # g(s) = tau_tr - b s - traction(s) decreases; the root lies between 0 and tau_tr / b
    lo, hi = min(0.0, tau_tr / b), max(0.0, tau_tr / b)
    s = min(max(kk * tau_tr, lo), hi) if abs(tau_tr) < T else (tau_tr - np.sign(tau_tr) * T) / b
    for _ in range(60):
        y = s / (kk * T)
        q = 1.0 / np.sqrt(1.0 + y * y)
        g = tau_tr - b * s - T * y * q
        if abs(g) < 1e-12 * (1.0 + abs(tau_tr)):
            break
        if g > 0.0:
            lo = s
        else:
            hi = s
        dg = -b - q * q * q / kk
        s_new = s - g / dg
        s = s_new if lo < s_new < hi else 0.5 * (lo + hi)
    return s, traction_curve(s, kk, T)


@njit(cache=True)
def traction_curve(s, k, T):
    """Ground torque (N m) of a wheel slipping at s rad/s: T y / sqrt(1 + y^2), y = s / (k T) (creep slope
    1 / k rad/(s N m), limit T N m; the magic formula with C = 1)."""
    y = s / (k * T)
    return T * y / np.sqrt(1.0 + y * y)


@njit(cache=True)
def slip_rate_series(tau_tr, b_i, eff):
    """Slip rates (N,) for transmitted torques tau_tr (N,) (``slip_state``)."""
    out = np.empty(len(tau_tr))
    for j in range(len(tau_tr)):
        out[j] = slip_state(tau_tr[j], b_i, eff)[0]
    return out
