"""Extended-model physics (compiled): the generalized force, actuator and slip laws of the effects
in ``otbot_hw.model.effect_catalog`` on top of the paper's dynamics (``otbot_hw.model.compiled``, entered
through its ``gen`` hook), and the derivative of the extended state z = (x, slip angles) that the
integrators of ``otbot_hw.simulation.integrators`` advance. All zeros = the paper's model.

Length: the effects' force, actuator and slip laws and the derivative that solves them together (the
slip split's fixed point with the accelerations) are one compiled kernel; about half the lines are the
modelling choices stated below.

Modelling choices (documented, not hidden):

* Signs are smoothed, sgn(w) ~ tanh(w / width) and the caster's direction
  v / sqrt(|v|^2 + width_v^2), so the extended model stays smooth for integration and least
  squares. Real Coulomb friction is (nearly) discontinuous, and a wide tanh under-predicts it
  whenever the joint turns slower than the width (a fit then inflates c). The stiffness of a
  smoothed sign is level / (width * I_eff), so each width is proportional to the joint's
  friction level at zero speed (Coulomb + Stribeck + rolling resistance; ``sign_width``):
  the narrowest the RK4 step (``otbot_hw.simulation.simulator.default_substeps``: 2.5 ms,
  0.5 ms on the stand) keeps stable on the joint's smallest effective inertia at *every*
  level, h * level / (width * I_eff) <= 2.1: ``WIDTH_PER_NM_WHEEL`` rad/s per N m at a wheel
  (I_eff >= 0.048 kg m^2 on the floor, chassis reflected; I_a = 0.0104 kg m^2 free on the
  stand), ``WIDTH_PER_NM_PIVOT`` at the pivot (>= 0.31 kg m^2), never below ``WIDTH_MIN_*``.
  A 0.3 N m Coulomb friction is smoothed over 0.0075 rad/s at a wheel and 0.0015 rad/s at
  the pivot (the widths were fixed 0.05 and 0.01 rad/s, sized for the 2 N m bound, and
  biased sharper real friction: Stribeck sizes +33 %).
* Different wheel radii break the paper's J. The compiled model is kept by working in
  *rolling angles* psi_i = (r_i / r) phi_i, for which J is the paper's with radius r:
  on psi_i act the torque rho_i (tau_i - friction(phi_dot_i)) with rho_i = r / r_i, the
  wheel inertia becomes rho_i^2 I_a (one fixed-point correction of the accelerations),
  and the encoders read phi_i = rho_i psi_i.
* Wheel slip is a quasi-static longitudinal slip law (``slip_state``; the spin-up of the slip
  itself is quasi-static, the wheel's rolling inertia is not neglected): tau_tr_i = delivered
  torque minus motor friction at the rolling speed minus I_a times the wheel's rolling
  acceleration (what turns the wheel itself; solved with the accelerations by a fixed point,
  ``_force_accel_into``). Without a traction limit the contact creeps at s_dot = k_slip * tau_tr
  and passes tau_tr. With one, the traction curve tau_g(s_dot) = t_trac tanh(h(y)), y = s_dot / (k_slip t_trac),
  knee kn_trac (0: h = asinh, the magic formula with C = 1, t_trac y / sqrt(1 + y^2); 1: tanh; 3: a hard clip;
  ``slip_law``)
  (linear creep k_slip at small slip, saturating at t_trac) and the wheel's balance
  tau_tr - b_i s_dot = tau_g give s_dot: creep below the limit, spin-up above it until the
  motor's viscous friction takes the excess. The body is driven by tau_g (above the limit the
  chassis gets t_trac, not t_trac minus the wheel's own inertia torque: that was the split before,
  and it put the spin rate I_a psi_dd / b_w off, ~0.5 rad/s at 10 rad/s^2); the encoders read
  psi_i + s_i: odometry and IMU disagree, energy is lost at the contact. Slip states s_r, s_l
  (rad) are integrated.
* Casters: ``n_cst`` contacts at (x_ci, y_ci) in the chassis frame B' (the robot
  configuration's ``casters``, ``otbot_hw.diagnose.geometry``; default one at
  ``CASTER_POSITION``), each with drag f_cst / n_cst opposing its contact velocity.
* Rolling resistance assumes the weight shared equally by the two wheels.
* Current-loop lag is integrated exactly inside each zero-order-hold interval
  (tau_a(t) = tau_c + (tau_a0 - tau_c) exp(-t / T_i)), so small T_i never makes RK4 unstable.
* Laws beyond the catalog (written by ``otbot diagnose`` when it discovers them): linear drag
  -c_lin v at the pivot (beside the quadratic air drag), cogging -cog sin(cogn phi + cogph) on a
  motor at its own angle (a wheel's: the rolling angle times r / r_i), a drive dead zone and a
  soft torque limit ts tanh(t / ts) in ``actuated_torque`` (after the gain, before the hard saturation).
* Floor slope, rolling resistance, caster drag, slip, linear and air drag act only on the
  ``floor`` fixture; on the stand/locked fixtures the slope turns the platform only.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from otbot_hw.model import compiled
from otbot_hw.model.constants import GRAVITY
from otbot_hw.model.effect_catalog import (C_AIR, C_L, C_LIN, C_P, C_R, C_RR, COG_R, COGN_R, COGPH_R, DB_W, DZ_R, DR_L, DR_R, F_CST, G_X, G_Y, K_L, K_P, K_R,
                                           K_SLIP, N_CST, S_W, T_TRAC, TS_R, U_MAX_R, V_S, WIDTH_MIN_CASTER,
                                           WIDTH_MIN_PIVOT, WIDTH_MIN_WHEEL, WIDTH_PER_N_CASTER, WIDTH_PER_NM_PIVOT,
                                           WIDTH_PER_NM_WHEEL, X_C1)
from otbot_hw.model.kinematics import fik_entries
from otbot_hw.model.slip_law import K_SLIP_MIN, slip_rate_series, slip_state  # noqa: F401 (the model's slip law)

_L1, _L2, _IA, _BW, _R, _MC, _MP, _XB, _YB, _XF, _YF = 0, 1, 11, 12, 2, 3, 7, 5, 6, 9, 10  # OtbotParams.as_array()


@njit(cache=True)
def _sgn(v, w):
    return np.tanh(v / w)


@njit(cache=True)
def rolling_torque(eff, prm):
    """Rolling-resistance torque (N m) at each wheel: c_rr (m_c + m_p) g r / 2."""
    return eff[C_RR] * (prm[_MC] + prm[_MP]) * GRAVITY * 0.5 * prm[_R]


@njit(cache=True)
def sign_width(i, eff, prm):
    """Width (rad/s) of the smoothed friction sign at motor i (0 r, 1 l, 2 p): proportional to the
    joint's friction level at zero speed, the narrowest RK4 keeps stable (module doc)."""
    if i == 2:
        return max(WIDTH_MIN_PIVOT, WIDTH_PER_NM_PIVOT * eff[C_P])
    level = eff[C_R + i] + eff[S_W] + rolling_torque(eff, prm)
    return max(WIDTH_MIN_WHEEL, WIDTH_PER_NM_WHEEL * level)


@njit(cache=True)
def actuated_torque(u, eff):
    """Commanded torque (3,) -> torque the drives deliver in steady state: gain, then each motor's dead
    zone sgn(t) max(|t| - dz, 0), soft limit ts tanh(t / ts) and (hard) saturation."""
    out = np.empty(3)
    out[0] = (1.0 + eff[K_R]) * u[0]
    out[1] = (1.0 + eff[K_L]) * u[1]
    out[2] = (1.0 + eff[K_P]) * u[2]
    for i in range(3):
        d = eff[DZ_R + i]
        if d > 0.0:
            out[i] = max(out[i] - d, 0.0) if out[i] >= 0.0 else min(out[i] + d, 0.0)
        ts = eff[TS_R + i]
        if ts > 0.0:
            out[i] = ts * np.tanh(out[i] / ts)
        m = eff[U_MAX_R + i]
        if m > 0.0:
            out[i] = min(max(out[i], -m), m)
    return out


@njit(cache=True, nogil=True)
def actuated_torques(U, eff):
    """``actuated_torque`` of each command row of U (N, 3)."""
    out = np.empty((U.shape[0], 3))
    for k in range(U.shape[0]):
        out[k] = actuated_torque(U[k], eff)
    return out


@njit(cache=True)
def _motor_friction(w, i, eff, prm):
    """Non-viscous friction torque (N m) at motor i (0 r, 1 l, 2 p) turning at w rad/s (opposes w)."""
    if eff[C_R + i] == 0.0 and (i == 2 or eff[S_W] == 0.0):
        return 0.0
    sg = _sgn(w, sign_width(i, eff, prm))
    t = eff[C_R + i] * sg
    if i < 2 and eff[S_W] != 0.0:
        t += eff[S_W] * np.exp(-(w / eff[V_S]) ** 2) * sg
    return t


@njit(cache=True)
def cogging_torque(phi, i, eff):
    """Cogging torque (N m) acting on motor i (0 r, 1 l, 2 p) at its angle phi (rad):
    -cog sin(cogn phi + cogph) (0 without cogging)."""
    a = eff[COG_R + i]
    if a == 0.0:
        return 0.0
    return -a * np.sin(eff[COGN_R + i] * phi + eff[COGPH_R + i])


@njit(cache=True)
def radius_ratios(eff):
    """rho_i = r / r_i (right, left): the nominal radius over each wheel's own."""
    return 1.0 / (1.0 + eff[DR_R]), 1.0 / (1.0 + eff[DR_L])


DEADZONE_SMOOTH = 0.02  # N m: width of the dead-zone compensation's sign (``compensated_command``)
@njit(cache=True)
def effect_force(x, tau, eff, prm, fixture):
    """Extra generalized force (6,) of the effects at state x under delivered torque tau.

    Excludes the inertia correction of unequal wheel radii (see ``ext_accelerations``).
    The compiled model itself adds tau and the paper's viscous friction b_w psi_dot.
    """
    gen = np.empty(6)
    _effect_force_into(x, tau, eff, prm, fixture, gen, np.empty(2), np.zeros(2))
    return gen


@njit(cache=True)
def forces_active(eff):
    """Whether an effect adds a generalized force or a wheel slip (False: the paper's model, or effects
    on the drives' gain and saturation or the sensors only; ``integrators.ext_rk4_into`` then runs the
    paper model's RK4)."""
    return (eff[C_R] != 0.0 or eff[C_L] != 0.0 or eff[C_P] != 0.0 or eff[S_W] != 0.0 or eff[C_RR] != 0.0
            or eff[F_CST] != 0.0 or eff[K_SLIP] != 0.0 or eff[G_X] != 0.0 or eff[G_Y] != 0.0 or eff[C_AIR] != 0.0
            or eff[DB_W] != 0.0 or eff[DR_R] != 0.0 or eff[DR_L] != 0.0 or eff[T_TRAC] != 0.0
            or eff[C_LIN] != 0.0 or eff[COG_R] != 0.0 or eff[COG_R + 1] != 0.0 or eff[COG_R + 2] != 0.0)


@njit(cache=True)
def _effect_force_into(x, tau, eff, prm, fixture, gen, slip, inertial):
    """Write ``effect_force`` into gen (6,) and ``slip_rates`` into slip (2,) (one slip law solve
    serves both). inertial (2,): I_a times each wheel's rolling acceleration (N m), the torque that turns
    the wheel itself, taken from the transmitted torque before the slip law (zeros: the first pass of
    ``_force_accel_into``)."""
    for i in range(6):
        gen[i] = 0.0
    slip[0] = 0.0
    slip[1] = 0.0
    bw = prm[_BW]
    rho = radius_ratios(eff)
    # wheel motors, expressed on the rolling angles psi
    traction = eff[T_TRAC] > 0.0 and fixture == compiled.FLOOR
    slipping = (eff[K_SLIP] != 0.0 or eff[T_TRAC] != 0.0) and fixture == compiled.FLOOR
    for i in range(2):
        psid = x[9 + i]
        w = rho[i] * psid
        b_i = bw + eff[DB_W] * (1.0 if i == 0 else -1.0)
        t_tr = tau[i] - b_i * w - _motor_friction(w, i, eff, prm) + cogging_torque(rho[i] * x[3 + i], i, eff)
        if slipping:
            sigma, t_g = slip_state(t_tr - inertial[i], b_i, eff)
            slip[i] = sigma
            motor = rho[i] * (t_g + inertial[i] if traction else t_tr)
        else:
            motor = rho[i] * t_tr
        gen[3 + i] = motor - (tau[i] - bw * psid)
    gen[5] = -_motor_friction(x[11], 2, eff, prm) + cogging_torque(x[5], 2, eff)
    mc, mp = prm[_MC], prm[_MP]
    gx, gy = eff[G_X], eff[G_Y]
    slope = gx != 0.0 or gy != 0.0
    if slope:
        # platform centre of mass relative to P, ground frame
        a = x[2]
        ca, sa = np.cos(a), np.sin(a)
        fx = ca * prm[_XF] - sa * prm[_YF]
        fy = sa * prm[_XF] + ca * prm[_YF]
    else:
        fx = fy = 0.0
    if fixture != compiled.FLOOR:
        if slope:
            gen[5] += mp * (-fy * gx + fx * gy)
        return
    if slope or eff[F_CST] != 0.0:
        th = x[2] - x[5]
        ct, st = np.cos(th), np.sin(th)
    else:
        ct, st = 1.0, 0.0
    # floor slope: gravity on both centres of mass
    if slope:
        bx = ct * prm[_XB] - st * prm[_YB]
        by = st * prm[_XB] + ct * prm[_YB]
        gen[0] += (mc + mp) * gx
        gen[1] += (mc + mp) * gy
        mom_c = mc * (-by * gx + bx * gy)
        gen[2] += mom_c + mp * (-fy * gx + fx * gy)
        gen[5] -= mom_c
    # rolling resistance at both contacts, on the rolling angles
    if eff[C_RR] != 0.0:
        t_rr = rolling_torque(eff, prm)
        gen[3] -= t_rr * _sgn(x[9], sign_width(0, eff, prm))
        gen[4] -= t_rr * _sgn(x[10], sign_width(1, eff, prm))
    # caster drag: f_cst / n_cst at each caster contact (x_ci, y_ci in B')
    if eff[F_CST] != 0.0:
        n_c = int(eff[N_CST])
        f_each = eff[F_CST] / n_c
        width = max(WIDTH_MIN_CASTER, WIDTH_PER_N_CASTER * eff[F_CST])
        thd = x[8] - x[11]
        for j in range(n_c):
            cx, cy = eff[X_C1 + 2 * j], eff[X_C1 + 2 * j + 1]
            rcx = ct * cx - st * cy
            rcy = st * cx + ct * cy
            vx = x[6] - thd * rcy
            vy = x[7] + thd * rcx
            nv = np.sqrt(vx * vx + vy * vy + width * width)
            Fx = -f_each * vx / nv
            Fy = -f_each * vy / nv
            gen[0] += Fx
            gen[1] += Fy
            m = -rcy * Fx + rcx * Fy
            gen[2] += m
            gen[5] -= m
    # linear drag at the pivot
    if eff[C_LIN] != 0.0:
        gen[0] -= eff[C_LIN] * x[6]
        gen[1] -= eff[C_LIN] * x[7]
    # air drag at the pivot
    if eff[C_AIR] != 0.0:
        sp = np.sqrt(x[6] * x[6] + x[7] * x[7])
        gen[0] -= eff[C_AIR] * sp * x[6]
        gen[1] -= eff[C_AIR] * sp * x[7]


@njit(cache=True)
def effect_joint_torque(x, tau, eff, prm, fixture):
    """Joint-torque equivalent (3,) N m of the effect forces at state x under delivered torque tau:
    Delta(q)^T gen, what the effects add to the right side of the task-space model
    M_bar p_dd + C_bar p_d = u (Delta = [M_FIK; I], Delta^T E = I)."""
    gen = effect_force(x, tau, eff, prm, fixture)
    th = x[2] - x[5]
    b00, b01, b10, b11, kf = fik_entries(np.sin(th), np.cos(th), prm[_L1], prm[_L2], prm[_R])
    out = gen[3:6].copy()
    out[0] += b00 * gen[0] + b10 * gen[1] + kf * gen[2]
    out[1] += b01 * gen[0] + b11 * gen[1] - kf * gen[2]
    out[2] += gen[2]
    return out


@njit(cache=True)
def compensated_command(x, u_task, eff, prm, fixture):
    """Command (3,) N m under which the extended model's drives act like the paper model's torque
    ``u_task``: the delivered torque tau solves tau + Delta^T gen(x, tau) = u_task (fixed point; gen
    depends on tau only through unequal wheel radii, a contraction of factor |dr_r|, |dr_l|), then each
    motor's soft limit (inverted up to 0.99 ts), dead zone (dz added in the torque's direction, smoothed
    over ``DEADZONE_SMOOTH`` N m so that the command does not chatter about zero) and gain error are
    undone. Not compensated: saturation, current-loop lag, the inertia change of unequal radii, slip (and a
    traction limit) and sensor effects."""
    tau = u_task.copy()
    for _ in range(3):
        tau = u_task - effect_joint_torque(x, tau, eff, prm, fixture)
    out = np.empty(3)
    for i in range(3):
        t = tau[i]
        ts = eff[TS_R + i]
        if ts > 0.0:
            t = ts * np.arctanh(min(max(t / ts, -0.99), 0.99))
        d = eff[DZ_R + i]
        if d > 0.0:
            t += d * np.tanh(t / DEADZONE_SMOOTH)
        out[i] = t
    out[0] /= 1.0 + eff[K_R]
    out[1] /= 1.0 + eff[K_L]
    out[2] /= 1.0 + eff[K_P]
    return out


@njit(cache=True)
def ext_accelerations(x, tau, f, eff, prm, fixture):
    """q_ddot (6,) of the extended model (rolling-angle coordinates) under delivered torque tau."""
    gen = np.empty(6)
    acc = np.empty(6)
    _force_accel_into(x, tau, f, eff, prm, fixture, gen, np.empty(2), acc, np.empty(6), np.empty(2))
    return acc


SLIP_INERTIA_PASSES = 2  # fixed-point passes of the wheel inertia in the slip law (contraction ~I_a / (I_a + m r^2 / 2))


@njit(cache=True)
def _force_accel_into(x, tau, f, eff, prm, fixture, gen, slip, acc, g2, inertial):
    """Effect force (gen), slip rates (slip) and q_ddot (acc) at state x: with wheel slip on the floor, the
    slip law's wheel inertia torque I_a rho_i psi_dd_i from the accelerations, by ``SLIP_INERTIA_PASSES``
    fixed-point passes (without a traction limit the body force does not depend on it: the slip rates only)."""
    inertial[0] = 0.0
    inertial[1] = 0.0
    _effect_force_into(x, tau, eff, prm, fixture, gen, slip, inertial)
    _accelerations_into(x, tau, f, gen, eff, prm, fixture, acc, g2)
    if fixture != compiled.FLOOR or (eff[K_SLIP] == 0.0 and eff[T_TRAC] == 0.0):
        return
    rho = radius_ratios(eff)
    passes = SLIP_INERTIA_PASSES if eff[T_TRAC] > 0.0 else 1
    for _ in range(passes):
        for i in range(2):
            inertial[i] = prm[_IA] * rho[i] * acc[3 + i]
        _effect_force_into(x, tau, eff, prm, fixture, gen, slip, inertial)
        if eff[T_TRAC] > 0.0:
            _accelerations_into(x, tau, f, gen, eff, prm, fixture, acc, g2)


@njit(cache=True)
def _accelerations_into(x, tau, f, gen, eff, prm, fixture, acc, g2):
    """Write q_ddot (6,) into acc given the effect force gen (``_effect_force_into``); g2 (6,) scratch."""
    if fixture == compiled.FLOOR:
        compiled._accel_into(x, tau, f, gen, prm, acc)
    else:
        compiled._fixture_accel_into(x, tau, gen, prm, fixture, acc)
    if eff[DR_R] != 0.0 or eff[DR_L] != 0.0:
        rho = radius_ratios(eff)
        for i in range(6):
            g2[i] = gen[i]
        for _ in range(2):  # fixed point for the wheel inertias rho^2 I_a
            for i in range(2):
                g2[3 + i] = gen[3 + i] - prm[_IA] * (rho[i] * rho[i] - 1.0) * acc[3 + i]
            if fixture == compiled.FLOOR:
                compiled._accel_into(x, tau, f, g2, prm, acc)
            else:
                compiled._fixture_accel_into(x, tau, g2, prm, fixture, acc)


@njit(cache=True)
def slip_rates(x, tau, f, eff, prm, fixture):
    """Slip rates (2,) rad/s of the wheel encoders relative to the rolling angles at state x under delivered
    torque tau and force f (the slip law with the wheel's rolling inertia, as the integrator steps it)."""
    out = np.zeros(2)
    if (eff[K_SLIP] == 0.0 and eff[T_TRAC] == 0.0) or fixture != compiled.FLOOR:
        return out
    _force_accel_into(x, tau, f, eff, prm, fixture, np.empty(6), out, np.empty(6), np.empty(6), np.empty(2))
    return out


@njit(cache=True, nogil=True)
def slip_rate_samples(X, TAU, F, eff, prm, fixture):
    """Slip rates (N, 2) rad/s at each sample from states X (N, 12), delivered torques TAU (N, 3), forces F."""
    out = np.empty((X.shape[0], 2))
    for k in range(X.shape[0]):
        out[k] = slip_rates(X[k], TAU[k], F[k], eff, prm, fixture)
    return out


@njit(cache=True)
def lagged_torque_into(tc, t0, s, T, out):
    """Delivered torque s seconds into an interval commanded tc, from t0 (current-loop lag T)."""
    if T > 0.0:
        e = np.exp(-s / T)
        for i in range(3):
            out[i] = tc[i] + (t0[i] - tc[i]) * e
    else:
        for i in range(3):
            out[i] = tc[i]


@njit(cache=True)
def ext_derivative_into(z, tau, f, eff, prm, fixture, dz, gen, acc, g2, slip):
    """Write d/dt of z = (x (12,), slip angles (2,)) into dz (14,); gen, acc, g2 (6,), slip (2,) scratch."""
    x = z[:12]
    for i in range(6):
        dz[i] = x[6 + i]
    _force_accel_into(x, tau, f, eff, prm, fixture, gen, slip, acc, g2, np.empty(2))
    for i in range(6):
        dz[6 + i] = acc[i]
    dz[12] = slip[0]
    dz[13] = slip[1]



@njit(cache=True, nogil=True)
def ext_sample_accelerations(X, TAU, F, eff, prm, fixture):
    """q_ddot (N, 6) at each sample from states X, delivered torques TAU and forces F."""
    n = X.shape[0]
    out = np.empty((n, 6))
    gen, acc, g2, slip = np.empty(6), np.empty(6), np.empty(6), np.empty(2)
    inertial = np.empty(2)
    for k in range(n):
        _force_accel_into(X[k], TAU[k], F[k], eff, prm, fixture, gen, slip, acc, g2, inertial)
        out[k] = acc
    return out

