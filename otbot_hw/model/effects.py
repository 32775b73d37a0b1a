"""Extended Otbot model: the paper's dynamics plus the physical effects it leaves out.

The paper (§1.5.2) assumes ideal torque motors, no caster dynamics, perfect rolling,
a flat floor and viscous motor friction only. This module adds those effects back,
each switched off by a zero parameter, without touching the compiled paper model:
physics enters through its ``gen`` hook (an extra generalized force, 6,), actuator
effects transform the commanded torque, sensor effects transform the outputs.

Effect parameters form one flat vector ``eff`` (order ``EFFECT_PARAM_NAMES``, all
zeros = the paper's model):

=============  =========  ====================================================================
name           unit       meaning
=============  =========  ====================================================================
c_r, c_l, c_p  N m        Coulomb friction at the right/left wheel and pivot motor shafts
s_w            N m        Stribeck excess friction at both wheel motors, s_w exp(-(w/v_s)^2) sgn w
v_s            rad/s      Stribeck velocity (only used when s_w != 0)
c_rr           1          rolling-resistance coefficient: torque c_rr (m_c+m_p) g / 2 r per wheel
f_cst          N          caster drag: a Coulomb-like force at the caster point opposing its velocity
k_slip         rad/(s N m) longitudinal slip: wheel spins k_slip * (ground torque) faster than it rolls
g_x, g_y       m/s^2      floor slope: in-plane gravity component, ground frame (recording start frame)
c_air          N s^2/m^2  air drag at the pivot: F = -c_air |v| v
k_r, k_l, k_p  1          torque gain error: delivered torque = (1 + k) * command
u_max_r, ...   N m        torque saturation of the right/left wheel and pivot motors (0 = none;
  u_max_l,                ``u_max`` sets all three)
  u_max_p
T_i            s          current-loop lag: first-order lag of the delivered torque (0 = none)
db_w           N m s/rad  viscous asymmetry: b_right = b_w + db_w, b_left = b_w - db_w
dr_r, dr_l     1          wheel radii: r_right = r (1 + dr_r), r_left = r (1 + dr_l) (r: the nominal radius)
t_trac         N m        traction limit of each wheel: ground torque t_trac tanh(tau_tr / t_trac) (0 = none)
n_cst          1          number of casters (1..4) sharing the caster drag f_cst equally
x_c1 .. y_c4   m          caster contact points in the chassis frame B' (from the robot configuration)
b_ax, b_ay     m/s^2      IMU accelerometer bias (x, y of the IMU frame)
b_gz           rad/s      gyro bias (z)
d_x, d_y       m          IMU position in the platform frame B'' (lever arm from the pivot)
psi            rad        IMU yaw misalignment: IMU frame = B'' rotated by psi about z
d_imu          s          IMU latency: the IMU sample stamped t_k was taken at t_k - d_imu
e_r, e_l       1          encoder scale error of the wheel encoders: reading = (1 + e) * angle
=============  =========  ====================================================================

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
* Wheel slip is a quasi-static longitudinal slip law (wheel inertia neglected in the split;
  ``slip_state``): tau_tr_i = delivered torque minus motor friction at the rolling speed.
  Without a traction limit the contact creeps at s_dot = k_slip * tau_tr and passes tau_tr.
  With one, the traction curve tau_g(s_dot) = t_trac tanh(s_dot / (k_slip t_trac)) (linear
  creep k_slip at small slip, saturating at t_trac) and the wheel's balance
  tau_tr - b_i s_dot = tau_g give s_dot: creep below the limit, spin-up above it until the
  motor's viscous friction takes the excess. The body is driven by tau_g; the encoders read
  psi_i + s_i: odometry and IMU disagree, energy is lost at the contact. Slip states s_r, s_l
  (rad) are integrated.
* Casters: ``n_cst`` contacts at (x_ci, y_ci) in the chassis frame B' (the robot
  configuration's ``casters``, ``otbot_hw.diagnose.geometry``; default one at
  ``CASTER_POSITION``), each with drag f_cst / n_cst opposing its contact velocity.
* Rolling resistance assumes the weight shared equally by the two wheels.
* Current-loop lag is integrated exactly inside each zero-order-hold interval
  (tau_a(t) = tau_c + (tau_a0 - tau_c) exp(-t / T_i)), so small T_i never makes RK4 unstable.
* Floor slope, rolling resistance, caster drag, slip and air drag act only on the
  ``floor`` fixture; on the stand/locked fixtures the slope turns the platform only.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from otbot_hw.model import compiled
from otbot_hw.params import OtbotParams

GRAVITY = 9.80665
WIDTH_PER_NM_PIVOT = 0.005  # rad/s per N m of friction level: smoothed sign width at the pivot motor
WIDTH_PER_NM_WHEEL = 0.025  # rad/s per N m ... at a wheel motor
WIDTH_MIN_PIVOT = 0.001  # rad/s, narrowest sign at the pivot
WIDTH_MIN_WHEEL = 0.002  # rad/s, narrowest sign at a wheel
WIDTH_PER_N_CASTER = 5e-5  # m/s per N of caster drag: smoothed direction of a caster contact
WIDTH_MIN_CASTER = 1e-3  # m/s
CASTER_POSITION = (0.15, 0.0)  # m, default single caster contact in the chassis frame B'
MAX_CASTERS = 4

#: (name, unit, lower bound, upper bound, description)
EFFECT_PARAMS: tuple[tuple[str, str, float, float, str], ...] = (
    ("c_r", "N m", 0.0, 2.0, "Coulomb friction, right wheel motor"),
    ("c_l", "N m", 0.0, 2.0, "Coulomb friction, left wheel motor"),
    ("c_p", "N m", 0.0, 2.0, "Coulomb friction, pivot motor"),
    ("s_w", "N m", 0.0, 2.0, "Stribeck excess friction, wheel motors"),
    ("v_s", "rad/s", 0.05, 5.0, "Stribeck velocity"),
    ("c_rr", "1", 0.0, 0.1, "rolling-resistance coefficient"),
    ("f_cst", "N", 0.0, 200.0, "caster drag force"),
    ("k_slip", "rad/(s N m)", 0.0, 1.0, "longitudinal slip rate per transmitted torque"),
    ("g_x", "m/s^2", -2.0, 2.0, "floor slope: gravity component along ground x"),
    ("g_y", "m/s^2", -2.0, 2.0, "floor slope: gravity component along ground y"),
    ("c_air", "N s^2/m^2", 0.0, 50.0, "air drag coefficient at the pivot"),
    ("k_r", "1", -0.5, 0.5, "torque gain error, right wheel"),
    ("k_l", "1", -0.5, 0.5, "torque gain error, left wheel"),
    ("k_p", "1", -0.5, 0.5, "torque gain error, pivot"),
    ("u_max_r", "N m", 0.0, 100.0, "torque saturation, right wheel motor (0 = none)"),
    ("u_max_l", "N m", 0.0, 100.0, "torque saturation, left wheel motor (0 = none)"),
    ("u_max_p", "N m", 0.0, 100.0, "torque saturation, pivot motor (0 = none)"),
    ("T_i", "s", 0.0, 0.2, "current-loop time constant (0 = none)"),
    ("db_w", "N m s/rad", -0.2, 0.2, "viscous friction asymmetry of the wheels"),
    ("dr_r", "1", -0.1, 0.1, "right wheel radius change relative to the nominal r"),
    ("dr_l", "1", -0.1, 0.1, "left wheel radius change relative to the nominal r"),
    ("t_trac", "N m", 0.0, 50.0, "traction limit per wheel (0 = none)"),
    ("b_ax", "m/s^2", -2.0, 2.0, "accelerometer bias x"),
    ("b_ay", "m/s^2", -2.0, 2.0, "accelerometer bias y"),
    ("b_gz", "rad/s", -0.5, 0.5, "gyro bias z"),
    ("d_x", "m", -0.5, 0.5, "IMU position x in B''"),
    ("d_y", "m", -0.5, 0.5, "IMU position y in B''"),
    ("psi", "rad", -0.5, 0.5, "IMU yaw misalignment"),
    ("d_imu", "s", 0.0, 0.1, "IMU latency"),
    ("e_r", "1", -0.2, 0.2, "right wheel encoder scale error"),
    ("e_l", "1", -0.2, 0.2, "left wheel encoder scale error"),
    ("n_cst", "1", 1.0, float(MAX_CASTERS), "number of casters"),
) + tuple((f"{a}_c{i}", "m", -1.0, 1.0, f"caster {i} contact {a} in B'") for i in range(1, MAX_CASTERS + 1)
          for a in ("x", "y"))
EFFECT_PARAM_NAMES: tuple[str, ...] = tuple(p[0] for p in EFFECT_PARAMS)
EFFECT_INDEX: dict[str, int] = {n: i for i, n in enumerate(EFFECT_PARAM_NAMES)}
EFFECT_UNITS: dict[str, str] = {p[0]: p[1] for p in EFFECT_PARAMS}
EFFECT_BOUNDS: dict[str, tuple[float, float]] = {p[0]: (p[2], p[3]) for p in EFFECT_PARAMS}
N_EFFECT = len(EFFECT_PARAMS)
(C_R, C_L, C_P, S_W, V_S, C_RR, F_CST, K_SLIP, G_X, G_Y, C_AIR, K_R, K_L, K_P, U_MAX_R, U_MAX_L, U_MAX_P, T_I, DB_W,
 DR_R, DR_L, T_TRAC, B_AX, B_AY, B_GZ, D_X, D_Y, PSI, D_IMU, E_R, E_L, N_CST) = range(N_EFFECT - 2 * MAX_CASTERS)
X_C1 = N_CST + 1  # x_ci at X_C1 + 2 (i - 1), y_ci one after
#: effect entries that describe where things are, not an effect (active only with their effect)
GEOMETRY_PARAMS: tuple[str, ...] = ("n_cst",) + tuple(n for n in EFFECT_PARAM_NAMES if n[1:3] == "_c" and n[3:].isdigit())

_L1, _L2, _IA, _BW, _R, _MC, _MP, _XB, _YB, _XF, _YF = 0, 1, 11, 12, 2, 3, 7, 5, 6, 9, 10


def effect_vector(values: dict[str, float] | None = None) -> np.ndarray:
    """Flat effect vector (N_EFFECT,) from ``{name: value}``; unnamed effects are 0 (v_s defaults 0.5)."""
    eff = np.zeros(N_EFFECT)
    eff[V_S] = 0.5
    eff[N_CST] = 1.0
    eff[X_C1], eff[X_C1 + 1] = CASTER_POSITION
    for k, v in (values or {}).items():
        if k not in EFFECT_INDEX:
            raise ValueError(f"unknown effect parameter '{k}' (known: {', '.join(EFFECT_PARAM_NAMES)})")
        if not np.isfinite(v):
            raise ValueError(f"effect parameter {k} must be finite, got {v}")
        eff[EFFECT_INDEX[k]] = float(v)
    if eff[V_S] <= 0:
        raise ValueError(f"v_s must be > 0 rad/s, got {eff[V_S]}")
    for i in (DR_R, DR_L):
        if abs(eff[i]) >= 0.5:
            raise ValueError(f"{EFFECT_PARAM_NAMES[i]} must be in (-0.5, 0.5), got {eff[i]}")
    if eff[N_CST] not in range(1, MAX_CASTERS + 1):
        raise ValueError(f"n_cst must be a whole number of casters 1..{MAX_CASTERS}, got {eff[N_CST]}")
    return eff


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
    """Commanded torque (3,) -> torque the drives deliver in steady state (gain, then each motor's saturation)."""
    out = np.empty(3)
    out[0] = (1.0 + eff[K_R]) * u[0]
    out[1] = (1.0 + eff[K_L]) * u[1]
    out[2] = (1.0 + eff[K_P]) * u[2]
    for i in range(3):
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
def radius_ratios(eff):
    """rho_i = r / r_i (right, left): the nominal radius over each wheel's own."""
    return 1.0 / (1.0 + eff[DR_R]), 1.0 / (1.0 + eff[DR_L])


K_SLIP_MIN = 1e-4  # rad/(s N m): creep of the traction curve when k_slip = 0 (rigid up to the limit)


@njit(cache=True)
def slip_state(tau_tr, b_i, eff):
    """(slip rate sigma rad/s, ground torque tau_g N m) of a wheel transmitting tau_tr.

    Without a traction limit: tau_g = tau_tr and sigma = k_slip tau_g (linear creep). With one
    (t_trac > 0) the traction curve tau_g(sigma) = t_trac tanh(sigma / (k_slip t_trac)) and the
    wheel's balance tau_tr - b_i sigma = tau_g(sigma) (the motor's viscous friction acts on the
    spin rolling + sigma) give sigma, solved by safeguarded Newton (the balance is monotone):
    creep below the limit, spin-up until the viscous friction takes the excess above it."""
    T = eff[T_TRAC]
    k = eff[K_SLIP]
    if T <= 0.0:
        return k * tau_tr, tau_tr
    kk = max(k, K_SLIP_MIN)
    b = max(b_i, 1e-3)
    # g(s) = tau_tr - b s - T tanh(s / (kk T)) decreases; the root lies between 0 and tau_tr / b
    lo, hi = min(0.0, tau_tr / b), max(0.0, tau_tr / b)
    s = min(max(kk * tau_tr, lo), hi) if abs(tau_tr) < T else (tau_tr - np.sign(tau_tr) * T) / b
    for _ in range(60):
        th = np.tanh(s / (kk * T))
        g = tau_tr - b * s - T * th
        if abs(g) < 1e-12 * (1.0 + abs(tau_tr)):
            break
        if g > 0.0:
            lo = s
        else:
            hi = s
        dg = -b - (1.0 - th * th) / kk
        s_new = s - g / dg
        s = s_new if lo < s_new < hi else 0.5 * (lo + hi)
    return s, T * np.tanh(s / (kk * T))


@njit(cache=True)
def slip_rate_series(tau_tr, b_i, eff):
    """Slip rates (N,) for transmitted torques tau_tr (N,) (``slip_state``)."""
    out = np.empty(len(tau_tr))
    for j in range(len(tau_tr)):
        out[j] = slip_state(tau_tr[j], b_i, eff)[0]
    return out


@njit(cache=True)
def effect_force(x, tau, eff, prm, fixture):
    """Extra generalized force (6,) of the effects at state x under delivered torque tau.

    Excludes the inertia correction of unequal wheel radii (see ``ext_accelerations``).
    The compiled model itself adds tau and the paper's viscous friction b_w psi_dot.
    """
    gen = np.empty(6)
    _effect_force_into(x, tau, eff, prm, fixture, gen, np.empty(2))
    return gen


@njit(cache=True)
def _effect_force_into(x, tau, eff, prm, fixture, gen, slip):
    """Write ``effect_force`` into gen (6,) and ``slip_rates`` into slip (2,) (one slip law solve
    serves both)."""
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
        t_tr = tau[i] - b_i * w - _motor_friction(w, i, eff, prm)
        if slipping:
            sigma, t_g = slip_state(t_tr, b_i, eff)
            slip[i] = sigma
            motor = rho[i] * (t_g if traction else t_tr)
        else:
            motor = rho[i] * t_tr
        gen[3 + i] = motor - (tau[i] - bw * psid)
    gen[5] = -_motor_friction(x[11], 2, eff, prm)
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
    l1, l2, r = prm[_L1], prm[_L2], prm[_R]
    th = x[2] - x[5]
    s, c = np.sin(th), np.cos(th)
    k = r / (2.0 * l2)
    out = gen[3:6].copy()
    out[0] += k * ((l2 * c - l1 * s) * gen[0] + (l1 * c + l2 * s) * gen[1] + gen[2])
    out[1] += k * ((l2 * c + l1 * s) * gen[0] + (-l1 * c + l2 * s) * gen[1] - gen[2])
    out[2] += gen[2]
    return out


@njit(cache=True)
def compensated_command(x, u_task, eff, prm, fixture):
    """Command (3,) N m under which the extended model's drives act like the paper model's torque
    ``u_task``: the delivered torque tau solves tau + Delta^T gen(x, tau) = u_task (fixed point; gen
    depends on tau only through unequal wheel radii, a contraction of factor |dr_r|, |dr_l|), then each
    motor's gain error is divided out. Not compensated: saturation, current-loop lag, the inertia
    change of unequal radii, slip (and a traction limit) and sensor effects."""
    tau = u_task.copy()
    for _ in range(3):
        tau = u_task - effect_joint_torque(x, tau, eff, prm, fixture)
    out = np.empty(3)
    out[0] = tau[0] / (1.0 + eff[K_R])
    out[1] = tau[1] / (1.0 + eff[K_L])
    out[2] = tau[2] / (1.0 + eff[K_P])
    return out


@njit(cache=True)
def ext_accelerations(x, tau, f, eff, prm, fixture):
    """q_ddot (6,) of the extended model (rolling-angle coordinates) under delivered torque tau."""
    gen = np.empty(6)
    _effect_force_into(x, tau, eff, prm, fixture, gen, np.empty(2))
    acc = np.empty(6)
    _accelerations_into(x, tau, f, gen, eff, prm, fixture, acc, np.empty(6))
    return acc


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
def slip_rates(x, tau, eff, prm, fixture):
    """Slip rates (2,) rad/s of the wheel encoders relative to the rolling angles."""
    out = np.zeros(2)
    if (eff[K_SLIP] == 0.0 and eff[T_TRAC] == 0.0) or fixture != compiled.FLOOR:
        return out
    rho = radius_ratios(eff)
    for i in range(2):
        w = rho[i] * x[9 + i]
        b_i = prm[_BW] + eff[DB_W] * (1.0 if i == 0 else -1.0)
        out[i] = slip_state(tau[i] - b_i * w - _motor_friction(w, i, eff, prm), b_i, eff)[0]
    return out


@njit(cache=True, nogil=True)
def slip_rate_samples(X, TAU, eff, prm, fixture):
    """Slip rates (N, 2) rad/s at each sample from states X (N, 12) and delivered torques TAU (N, 3)."""
    out = np.empty((X.shape[0], 2))
    for k in range(X.shape[0]):
        out[k] = slip_rates(X[k], TAU[k], eff, prm, fixture)
    return out


@njit(cache=True)
def _lagged_into(tc, t0, s, T, out):
    """Delivered torque s seconds into an interval commanded tc, from t0 (current-loop lag T)."""
    if T > 0.0:
        e = np.exp(-s / T)
        for i in range(3):
            out[i] = tc[i] + (t0[i] - tc[i]) * e
    else:
        for i in range(3):
            out[i] = tc[i]


@njit(cache=True)
def _zderiv_into(z, tau, f, eff, prm, fixture, dz, gen, acc, g2, slip):
    """Write d/dt of z = (x (12,), slip angles (2,)) into dz (14,); gen, acc, g2 (6,), slip (2,) scratch."""
    x = z[:12]
    for i in range(6):
        dz[i] = x[6 + i]
    _effect_force_into(x, tau, eff, prm, fixture, gen, slip)
    _accelerations_into(x, tau, f, gen, eff, prm, fixture, acc, g2)
    for i in range(6):
        dz[6 + i] = acc[i]
    dz[12] = slip[0]
    dz[13] = slip[1]


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
    _ext_rk4_into(x0, tau0, U, F, dt, substeps, prm, eff, fixture, X, TAU, S, np.empty((0, 6)), np.empty((0, 2)))
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
    _ext_rk4_into(x0, tau0, U, F, dt, substeps, prm, eff, fixture, X, TAU, S, QDD, SD)
    return X, TAU, S, QDD, SD


@njit(cache=True, nogil=True)
def _ext_rk4_into(x0, tau0, U, F, dt, substeps, prm, eff, fixture, X, TAU, S, QDD, SD):
    """The RK4 of ``ext_rk4_zoh`` writing into X, TAU, S; and into QDD, SD when they have N+1 rows."""
    n = U.shape[0]
    samples = QDD.shape[0] == n + 1
    z = np.zeros(14)
    z[:12] = x0
    X[0] = x0
    h = dt / substeps
    T = eff[T_I]
    ta = tau0.copy()
    k1, k2, k3, k4, zs = np.empty(14), np.empty(14), np.empty(14), np.empty(14), np.empty(14)
    gen, acc, g2, slip = np.empty(6), np.empty(6), np.empty(6), np.empty(2)
    t1, t2, t3 = np.empty(3), np.empty(3), np.empty(3)
    for k in range(n):
        tc = actuated_torque(U[k], eff)
        f = F[k]
        _lagged_into(tc, ta, 0.0, T, TAU[k])
        for j in range(substeps):
            s0 = j * h
            _lagged_into(tc, ta, s0, T, t1)
            _lagged_into(tc, ta, s0 + 0.5 * h, T, t2)
            _lagged_into(tc, ta, s0 + h, T, t3)
            _zderiv_into(z, t1, f, eff, prm, fixture, k1, gen, acc, g2, slip)
            if samples and j == 0:  # the state X[k] under TAU[k] (t1 at s0 = 0)
                for i in range(6):
                    QDD[k, i] = k1[6 + i]
                SD[k, 0] = k1[12]
                SD[k, 1] = k1[13]
            for i in range(14):
                zs[i] = z[i] + 0.5 * h * k1[i]
            _zderiv_into(zs, t2, f, eff, prm, fixture, k2, gen, acc, g2, slip)
            for i in range(14):
                zs[i] = z[i] + 0.5 * h * k2[i]
            _zderiv_into(zs, t2, f, eff, prm, fixture, k3, gen, acc, g2, slip)
            for i in range(14):
                zs[i] = z[i] + h * k3[i]
            _zderiv_into(zs, t3, f, eff, prm, fixture, k4, gen, acc, g2, slip)
            for i in range(14):
                z[i] = z[i] + (h / 6.0) * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
        _lagged_into(tc, ta, dt, T, t1)
        for i in range(3):
            ta[i] = t1[i]
        X[k + 1] = z[:12]
        S[k + 1] = z[12:14]
    if n > 0:
        _lagged_into(actuated_torque(U[n - 1], eff), ta, 0.0, T, TAU[n])
    else:
        TAU[0] = tau0
    if samples:
        f = F[n - 1] if n > 0 else np.zeros(2)
        _zderiv_into(z, TAU[n], f, eff, prm, fixture, k1, gen, acc, g2, slip)
        for i in range(6):
            QDD[n, i] = k1[6 + i]
        SD[n, 0] = k1[12]
        SD[n, 1] = k1[13]


@njit(cache=True, nogil=True)
def ext_sample_accelerations(X, TAU, F, eff, prm, fixture):
    """q_ddot (N, 6) at each sample from states X, delivered torques TAU and forces F."""
    n = X.shape[0]
    out = np.empty((n, 6))
    gen, acc, g2, slip = np.empty(6), np.empty(6), np.empty(6), np.empty(2)
    for k in range(n):
        _effect_force_into(X[k], TAU[k], eff, prm, fixture, gen, slip)
        _accelerations_into(X[k], TAU[k], F[k], gen, eff, prm, fixture, acc, g2)
        out[k] = acc
    return out


def sensor_outputs(traj, params: OtbotParams, eff: np.ndarray,
                   slip_rate: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Noise-free sensor readings of an extended run (``ExtendedTrajectory``; the sensor effects applied).
    ``slip_rate`` (N, 2): the slip rates at the samples when known (``ext_rk4_zoh_samples``).

    Returns ``joint_pos``, ``joint_vel`` (N, 3) rad, rad/s and ``imu_accel``, ``imu_gyro``
    (N, 3) m/s^2, rad/s in the IMU frame (= B'' rotated by psi), as the recording stores them.
    """
    x, qdd = traj.x, traj.qdd
    rho = radius_ratios(eff)
    pos = x[:, 3:6].copy()
    vel = x[:, 9:12].copy()
    slip_d = np.zeros((len(x), 2))
    if slip_rate is not None:
        slip_d = slip_rate
    elif eff[K_SLIP] != 0.0 or eff[T_TRAC] != 0.0:
        from otbot_hw.model.fixtures import fixture_code
        code = fixture_code(traj.fixture)
        prm = params.as_array()
        slip_d = slip_rate_samples(np.ascontiguousarray(x), np.ascontiguousarray(traj.tau), eff, prm, code)
    for i in range(2):
        scale = 1.0 + eff[E_R + i]
        pos[:, i] = scale * (rho[i] * x[:, 3 + i] + traj.slip[:, i])
        vel[:, i] = scale * (rho[i] * x[:, 9 + i] + slip_d[:, i])
    floor = traj.fixture == "floor"
    acc, gyro = imu_from_motion(x[:, 2], x[:, 8], qdd[:, 0], qdd[:, 1], qdd[:, 2], eff, floor=floor)
    if eff[D_IMU] > 0.0:
        # the IMU reads the motion d_imu earlier, inside some ZOH interval: interpolate between that
        # interval's own ends (sample j with command u_j, sample j+1 still under u_j), not across the
        # torque step at a sample
        ql = left_accelerations(traj, params, eff)
        acc_l, _ = imu_from_motion(x[:, 2], x[:, 8], ql[:, 0], ql[:, 1], ql[:, 2], eff, floor=floor)
        acc = delay_held(traj.t, acc, acc_l, eff[D_IMU])
        gyro = delay(traj.t, gyro, eff[D_IMU])
    return {"joint_pos": pos, "joint_vel": vel, "imu_accel": acc, "imu_gyro": gyro}


def left_accelerations(traj, params: OtbotParams, eff: np.ndarray) -> np.ndarray:
    """q_ddot (N, 6) at each sample under the *previous* interval's delivered torque (the left limit at
    a command step; equal to ``traj.qdd`` with a current-loop lag, whose torque is continuous). The
    pivot force enters the accelerations linearly, so it cancels in the correction and is not needed."""
    from otbot_hw.model.fixtures import fixture_code

    if eff[T_I] > 0.0 or len(traj.x) < 2:
        return traj.qdd.copy()
    tau_l = traj.tau.copy()
    tau_l[1:] = actuated_torques(np.ascontiguousarray(traj.u[:-1]), eff)
    tau_l[0] = traj.tau[0]
    code = fixture_code(traj.fixture)
    prm = params.as_array()
    zero = np.zeros((len(traj.x), 2))
    right = ext_sample_accelerations(traj.x, np.ascontiguousarray(traj.tau), zero, eff, prm, code)
    left = ext_sample_accelerations(traj.x, tau_l, zero, eff, prm, code)
    return traj.qdd + (left - right)


def delay_held(t: np.ndarray, right: np.ndarray, left: np.ndarray, d: float) -> np.ndarray:
    """A signal sampled d seconds late whose samples jump at the sample instants: ``right`` (N, k) just
    after each sample, ``left`` (N, k) just before; inside interval j the value runs linearly from
    right[j] to left[j + 1]. Held at its first value before t_0."""
    dt = t[1] - t[0]
    tq = t - d
    j = np.clip(np.floor((tq - t[0]) / dt + 1e-9).astype(int), 0, len(t) - 2)
    f = np.clip((tq - t[j]) / dt, 0.0, 1.0)[:, None]
    out = (1.0 - f) * right[j] + f * left[j + 1]
    out[tq <= t[0]] = right[0]
    return out


def imu_from_motion(alpha, alpha_d, xdd, ydd, alpha_dd, eff, floor: bool = True):
    """IMU specific force (N, 3) and rate (N, 3) from the platform motion (no latency).

    Lever arm (d_x, d_y) in B'', the slope's gravity component (seen as -R^T g_plane),
    yaw misalignment psi and biases applied; z reads GRAVITY.
    """
    c, s = np.cos(alpha), np.sin(alpha)
    ax = c * xdd + s * ydd
    ay = -s * xdd + c * ydd
    if floor:
        ax = ax - (c * eff[G_X] + s * eff[G_Y])
        ay = ay - (-s * eff[G_X] + c * eff[G_Y])
    dx, dy = eff[D_X], eff[D_Y]
    ax = ax - alpha_dd * dy - alpha_d ** 2 * dx
    ay = ay + alpha_dd * dx - alpha_d ** 2 * dy
    cp, sp = np.cos(eff[PSI]), np.sin(eff[PSI])
    acc = np.empty((len(alpha), 3))
    acc[:, 0] = cp * ax + sp * ay + eff[B_AX]
    acc[:, 1] = -sp * ax + cp * ay + eff[B_AY]
    acc[:, 2] = GRAVITY
    gyro = np.zeros((len(alpha), 3))
    gyro[:, 2] = alpha_d + eff[B_GZ]
    return acc, gyro


def delay(t: np.ndarray, y: np.ndarray, d: float) -> np.ndarray:
    """y sampled d seconds late: y(t_k - d) by linear interpolation (held before t_0)."""
    if d == 0.0:
        return y
    out = np.empty_like(y)
    for j in range(y.shape[1]):
        out[:, j] = np.interp(t - d, t, y[:, j])
    return out


#: Catalog parameters that set several effect-vector entries at once (tied values).
TIED_PARAMS: dict[str, tuple[str, ...]] = {"c_w": ("c_r", "c_l"), "u_max": ("u_max_r", "u_max_l", "u_max_p")}


@dataclass(frozen=True)
class ExtendedModel:
    """The paper's parameters plus an effect vector: what simulation, identification and control use."""

    params: OtbotParams
    eff: np.ndarray

    @classmethod
    def paper(cls, params: OtbotParams) -> "ExtendedModel":
        return cls(params, effect_vector())

    def get(self, name: str) -> float:
        """Value of a nominal parameter, an effect-vector entry or a tied catalog parameter."""
        if name in TIED_PARAMS:
            return float(self.eff[EFFECT_INDEX[TIED_PARAMS[name][0]]])
        if name in EFFECT_INDEX:
            return float(self.eff[EFFECT_INDEX[name]])
        return float(getattr(self.params, name))

    def with_values(self, values: dict[str, float]) -> "ExtendedModel":
        """A copy with some nominal/effect/tied parameters set."""
        eff = self.eff.copy()
        nominal = {}
        for k, v in values.items():
            if k in TIED_PARAMS:
                for t in TIED_PARAMS[k]:
                    eff[EFFECT_INDEX[t]] = v
            elif k in EFFECT_INDEX:
                eff[EFFECT_INDEX[k]] = v
            else:
                nominal[k] = float(v)
        params = self.params.replace(**nominal) if nominal else self.params
        return ExtendedModel(params, eff)

    def active_effects(self) -> dict[str, float]:
        """Effect entries that differ from the paper's model (the Stribeck speed only with Stribeck
        friction, the caster geometry only with caster drag)."""
        base = effect_vector()
        return {n: float(self.eff[i]) for i, n in enumerate(EFFECT_PARAM_NAMES)
                if self.eff[i] != base[i] and not (n == "v_s" and self.eff[S_W] == 0.0)
                and not (n in GEOMETRY_PARAMS and self.eff[F_CST] == 0.0)}

    # -- model files: the parameter YAML plus an optional ``effects`` section ----------------
    @classmethod
    def from_dict(cls, data, source: str = "<dict>") -> "ExtendedModel":
        """Parameters and effects from the YAML structure. ``effects`` maps effect-parameter names
        (``EFFECT_PARAMS``; ``c_w`` sets both wheels) to ``{value, unit[, std]}``; absent = paper's model."""
        from otbot_hw.params import EFFECTS_SECTION, OtbotParams, ParameterError, read_entry

        params = OtbotParams.from_dict(data, source, allow_effects=True)
        block = data.get(EFFECTS_SECTION) or {}
        if not isinstance(block, dict):
            raise ParameterError(f"{source}: section '{EFFECTS_SECTION}' must be a mapping of effect parameters")
        values: dict[str, float] = {}
        for name, entry in block.items():
            key = f"{EFFECTS_SECTION}.{name}"
            if name not in EFFECT_INDEX and name not in TIED_PARAMS:
                raise ParameterError(f"{source}: unknown effect parameter '{key}' "
                                     f"(known: {', '.join(EFFECT_PARAM_NAMES + tuple(TIED_PARAMS))})")
            v, _ = read_entry(source, key, entry, parameter_unit(name))
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise ParameterError(f"{source}: '{key}' value must be a finite number, got {v!r}")
            v = float(v)
            lo, hi = parameter_bounds(name)
            if not lo <= v <= hi:
                raise ParameterError(f"{source}: '{key}' = {v} is outside its physical range [{lo}, {hi}]")
            values[name] = v
        try:
            return cls(params, effect_vector()).with_values(values).checked()
        except ValueError as exc:
            raise ParameterError(f"{source}: {exc}") from None

    @classmethod
    def load(cls, path=None) -> "ExtendedModel":
        """Load a parameter YAML with or without ``effects`` (default: ``config/otbot.yaml``)."""
        from otbot_hw.params import DEFAULT_PARAMS_FILE, read_yaml

        p = path if path is not None else DEFAULT_PARAMS_FILE
        return cls.from_dict(read_yaml(p, "parameter file"), source=str(p))

    def checked(self) -> "ExtendedModel":
        """Self, after the cross-checks ``effect_vector`` applies (ValueError otherwise)."""
        effect_vector({n: float(v) for n, v in zip(EFFECT_PARAM_NAMES, self.eff)})
        return self

    def to_dict(self, effect_std: dict[str, float] | None = None) -> dict:
        """The YAML structure: the parameter sections plus ``effects`` (active entries only)."""
        out = self.params.to_dict()
        effect_std = effect_std or {}
        active = self.active_effects()
        if active:
            block = {}
            for n, v in active.items():
                entry = {"value": v, "unit": EFFECT_UNITS[n]}
                s = effect_std.get(n, effect_std.get(next((t for t, m in TIED_PARAMS.items() if n in m), ""), None))
                if s is not None and np.isfinite(s):
                    entry["std"] = float(s)
                block[n] = entry
            out["effects"] = block
        return out

    def save(self, path, header: str = "", effect_std: dict[str, float] | None = None) -> None:
        """Write the model as YAML (``config/otbot.yaml`` layout plus the ``effects`` section)."""
        from otbot_hw.params import write_yaml

        write_yaml(path, self.to_dict(effect_std), header)


def parameter_unit(name: str) -> str:
    """Unit of a nominal, effect or tied parameter name."""
    from otbot_hw.params import UNITS

    if name in TIED_PARAMS:
        return EFFECT_UNITS[TIED_PARAMS[name][0]]
    return EFFECT_UNITS.get(name) or UNITS[name]


def parameter_bounds(name: str) -> tuple[float, float]:
    """Physical bounds of a nominal, effect or tied parameter."""
    from otbot_hw.params import _RULES

    if name in TIED_PARAMS:
        return EFFECT_BOUNDS[TIED_PARAMS[name][0]]
    if name in EFFECT_BOUNDS:
        return EFFECT_BOUNDS[name]
    rule = _RULES[name]
    return (1e-9, np.inf) if rule == "positive" else (0.0, np.inf) if rule == "nonnegative" else (-np.inf, np.inf)
