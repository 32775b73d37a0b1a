"""The sensor model, written once: what the joint encoders and the IMU read at a sample of a run of the
model (the paper's model is the extended model with every effect at zero), noise-free.

* Encoders (rad, rad/s, ``phi_r, phi_l, phi_p``): the wheel angles (rolling angle psi_i times the
  radius ratio rho_i = r / r_i) plus the slip angle, times the encoder scale error (1 + e_i); rates
  alike with the slip rate; the pivot reads phi_p.
* IMU (m/s^2, rad/s, in the IMU frame = the platform frame B'' rotated by psi about z): the specific
  force of the point (d_x, d_y) of B'' (lever arm from the pivot), the slope's in-plane gravity seen as
  -R^T g_plane (floor only), biases; z reads ``GRAVITY``; the rate alpha_dot + b_gz.
* IMU latency d_imu: the IMU sample stamped t_k was taken at t_k - d_imu, inside some zero-order-hold
  interval j; the reading runs linearly from its value just after sample j (under command u_j) to its
  value just before sample j + 1 (the *left limit*, still under u_j) -- not across the torque step at
  a sample (``delay_held``). Held at its first value before t_0.

The formulas (``wheel_encoder``, ``imu_specific_force``, ``gyro_rate``) are written once and registered
with numba (``register_jitable``): ``sensor_samples`` applies them to a whole run elementwise (numpy;
identification, the diagnosis, simulated recordings through ``sensor_outputs``), ``stepper_readings_into``
to the current sample of a stepped simulation (compiled; ``otbot_hw.simulation.sensing.StepperSensors``,
the direct and bus simulated robots). The motion at a sample (accelerations and slip rates) is one
evaluation of the extended model's derivative (``sample_motion_into``, the integrator's first stage), the
latency ``delay_held`` for both. So the batch and the stepped sensors agree to rounding
(``tests/test_sensor_agreement.py``).
"""
from __future__ import annotations

import numpy as np
from numba import njit
from numba.extending import register_jitable

from otbot_hw.model.constants import GRAVITY
from otbot_hw.model.effect_catalog import (B_AX, B_AY, B_GZ, D_IMU, D_X, D_Y, DR_R, E_R, G_X, G_Y, K_SLIP, PSI, T_I,
                                           T_TRAC)
from otbot_hw.model.effect_physics import actuated_torque, ext_derivative_into

CHANNELS = ("joint_pos", "joint_vel", "imu_accel", "imu_gyro")


@register_jitable(inline="always")
def imu_specific_force(alpha, alpha_d, xdd, ydd, alpha_dd, eff, floor):
    """IMU specific force (a_x, a_y) m/s^2 in the IMU frame (no latency; z reads ``GRAVITY``): platform
    angle alpha (rad) and rate alpha_d (rad/s), pivot acceleration (xdd, ydd) m/s^2 (ground frame),
    alpha_dd (rad/s^2); the slope acts on the ``floor`` fixture only. Scalars (compiled callers) or
    arrays (numpy, elementwise)."""
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
    return cp * ax + sp * ay + eff[B_AX], -sp * ax + cp * ay + eff[B_AY]


@register_jitable(inline="always")
def gyro_rate(alpha_d, eff):
    """Gyro z reading (rad/s): alpha_dot plus the gyro bias (x and y read 0)."""
    return alpha_d + eff[B_GZ]


@register_jitable(inline="always")
def wheel_encoder(psi, s, i, eff):
    """Reading of wheel encoder i (0 right, 1 left) for the rolling angle psi and the slip angle s (rad),
    or for their rates (rad/s): (1 + e_i) (rho_i psi + s), rho_i = r / r_i. Scalars or arrays."""
    return (1.0 + eff[E_R + i]) * (psi / (1.0 + eff[DR_R + i]) + s)


def imu_from_motion(alpha, alpha_d, xdd, ydd, alpha_dd, eff, floor: bool = True):
    """IMU specific force (N, 3) m/s^2 and rate (N, 3) rad/s from the platform motion (no latency),
    ``imu_specific_force`` and ``gyro_rate`` on arrays (N,) of alpha, alpha_dot, x_dd, y_dd, alpha_dd."""
    alpha, alpha_d = np.asarray(alpha, dtype=float), np.asarray(alpha_d, dtype=float)
    acc = np.empty((len(alpha), 3))
    acc[:, 0], acc[:, 1] = imu_specific_force(alpha, alpha_d, np.asarray(xdd, dtype=float),
                                              np.asarray(ydd, dtype=float), np.asarray(alpha_dd, dtype=float),
                                              eff, floor)
    acc[:, 2] = GRAVITY
    gyro = np.zeros((len(alpha), 3))
    gyro[:, 2] = gyro_rate(alpha_d, eff)
    return acc, gyro


@njit(cache=True, inline="always")
def sample_motion_into(x, tau, f, eff, prm, fixture, qdd, sd, z, dz, gen, acc, g2, slip):
    """Write the accelerations q_ddot (6,) and the wheel slip rates (2,) rad/s at state x (12,) under the
    delivered torque tau (3,) N m and pivot force f (2,) N into qdd, sd: the extended model's derivative
    (``effect_physics.ext_derivative_into``, the RK4's first stage); z, dz (14,), gen, acc, g2 (6,), slip
    (2,) scratch."""
    for i in range(12):
        z[i] = x[i]
    z[12] = 0.0
    z[13] = 0.0
    ext_derivative_into(z, tau, f, eff, prm, fixture, dz, gen, acc, g2, slip)
    for i in range(6):
        qdd[i] = dz[6 + i]
    sd[0] = dz[12]
    sd[1] = dz[13]


@njit(cache=True, nogil=True)
def sample_motion(X, TAU, F, eff, prm, fixture):
    """``sample_motion_into`` at N samples: accelerations (N, 6) and slip rates (N, 2)."""
    n = X.shape[0]
    QDD, SD = np.empty((n, 6)), np.empty((n, 2))
    z, dz, gen, acc, g2, slip = np.empty(14), np.empty(14), np.empty(6), np.empty(6), np.empty(6), np.empty(2)
    for k in range(n):
        sample_motion_into(X[k], TAU[k], F[k], eff, prm, fixture, QDD[k], SD[k], z, dz, gen, acc, g2, slip)
    return QDD, SD


def needs_left_limit(eff) -> bool:
    """Whether the IMU's value just before a sample differs from the one just after: with a latency (it
    interpolates inside an interval) and no current-loop lag (the delivered torque jumps at a command)."""
    return bool(eff[D_IMU] > 0.0 and eff[T_I] == 0.0)


def sensor_samples(X, S, TAU, F, TAU_L, F_L, QDD, SD, eff, prm, fixture):
    """The sensor model at N samples, before the IMU latency: states X (N, 12) (rolling-angle
    coordinates), wheel slip angles S (N, 2) rad, delivered torques TAU (N, 3) N m and pivot forces F
    (N, 2) N acting just after each sample, TAU_L, F_L just before it (the previous interval's; used for
    the left limit only, ``needs_left_limit``); QDD (N, 6), SD (N, 2) the accelerations and slip rates
    after each sample when the integrator already has them (``ext_rk4_zoh_samples``), or None to
    evaluate them (``sample_motion``).

    Returns POS, VEL (N, 3) rad, rad/s; ACC_R, ACC_L (N, 3) m/s^2 just after and just before each
    sample; GYRO (N, 3) rad/s; all in the recording's frames."""
    if QDD is None or SD is None:
        QDD, SD = sample_motion(X, TAU, F, eff, prm, fixture)
    n = len(X)
    floor = fixture == 0
    POS, VEL = X[:, 3:6].copy(), X[:, 9:12].copy()
    for i in range(2):
        POS[:, i] = wheel_encoder(X[:, 3 + i], S[:, i], i, eff)
        VEL[:, i] = wheel_encoder(X[:, 9 + i], SD[:, i], i, eff)
    ACC_R = np.empty((n, 3))
    ACC_R[:, 0], ACC_R[:, 1] = imu_specific_force(X[:, 2], X[:, 8], QDD[:, 0], QDD[:, 1], QDD[:, 2], eff, floor)
    ACC_R[:, 2] = GRAVITY
    if needs_left_limit(eff):
        QL, _ = sample_motion(X, TAU_L, F_L, eff, prm, fixture)
        ACC_L = np.empty((n, 3))
        ACC_L[:, 0], ACC_L[:, 1] = imu_specific_force(X[:, 2], X[:, 8], QL[:, 0], QL[:, 1], QL[:, 2], eff, floor)
        ACC_L[:, 2] = GRAVITY
    else:
        ACC_L = ACC_R
    GYRO = np.zeros((n, 3))
    GYRO[:, 2] = gyro_rate(X[:, 8], eff)
    return POS, VEL, ACC_R, ACC_L, GYRO


@njit(cache=True)
def stepper_readings_into(x, s, tau_state, u, f, u_last, f_last, has_last, eff, prm, fixture, out, work, imu=True):
    """The sensor model (the formulas ``sensor_samples`` applies to a run) at the current sample of a
    stepped simulation, into out (5, 3) (pos, vel, acc_r, acc_l, gyro): state x, accumulated slip s (2,),
    the delivered torque reached at the end of the last interval ``tau_state``, the command u (3,) and
    force f (2,) acting now, the last interval's u_last, f_last (``has_last`` False before the first
    step); ``work`` (``WORK``,) scratch. The delivered torque: with a current-loop lag ``tau_state``
    (continuous), else the actuated command (gain, saturation). ``imu`` False: the encoder rows only
    (rows 2-4 left as they were), without the accelerations unless a wheel slips (its rate is read)."""
    floor = fixture == 0
    if not imu and not (floor and (eff[K_SLIP] != 0.0 or eff[T_TRAC] != 0.0)):
        for i in range(2):  # no slip: the slip rates are zero (``effect_physics._effect_force_into``)
            out[0, i] = wheel_encoder(x[3 + i], s[i], i, eff)
            out[1, i] = wheel_encoder(x[9 + i], 0.0, i, eff)
        out[0, 2], out[1, 2] = x[5], x[11]
        return
    if eff[T_I] > 0.0:
        tau = tau_state
        tau_l = tau_state
    else:
        tau = actuated_torque(u, eff)
        tau_l = actuated_torque(u_last, eff) if has_last else tau
    f_l = f_last if has_last else f
    qdd, qdl, sd, sdl = work[0:6], work[6:12], work[12:14], work[14:16]
    z, dz, gen, acc, g2, slip = work[16:30], work[30:44], work[44:50], work[50:56], work[56:62], work[62:64]
    sample_motion_into(x, tau, f, eff, prm, fixture, qdd, sd, z, dz, gen, acc, g2, slip)
    for i in range(2):
        out[0, i] = wheel_encoder(x[3 + i], s[i], i, eff)
        out[1, i] = wheel_encoder(x[9 + i], sd[i], i, eff)
    out[0, 2], out[1, 2] = x[5], x[11]
    if not imu:
        return
    out[2, 0], out[2, 1] = imu_specific_force(x[2], x[8], qdd[0], qdd[1], qdd[2], eff, floor)
    if eff[D_IMU] > 0.0 and eff[T_I] == 0.0:  # needs_left_limit
        sample_motion_into(x, tau_l, f_l, eff, prm, fixture, qdl, sdl, z, dz, gen, acc, g2, slip)
        out[3, 0], out[3, 1] = imu_specific_force(x[2], x[8], qdl[0], qdl[1], qdl[2], eff, floor)
    else:
        out[3, 0], out[3, 1] = out[2, 0], out[2, 1]
    out[2, 2] = out[3, 2] = GRAVITY
    out[4, 0] = out[4, 1] = 0.0
    out[4, 2] = gyro_rate(x[8], eff)


#: Length of the work vector of ``stepper_readings_into``.
WORK = 64


def delay_held(t: np.ndarray, right: np.ndarray, left: np.ndarray, d: float) -> np.ndarray:
    """A signal sampled d seconds late whose samples jump at the sample instants t (N,) (uniform):
    ``right`` (N, k) just after each sample, ``left`` (N, k) just before; inside interval j the value
    runs linearly from right[j] to left[j + 1]. Held at its first value before t_0."""
    if d <= 0.0 or len(t) < 2:
        return right
    dt = t[1] - t[0]
    tq = t - d
    j = np.clip(np.floor((tq - t[0]) / dt + 1e-9).astype(int), 0, len(t) - 2)
    f = np.clip((tq - t[j]) / dt, 0.0, 1.0)[:, None]
    out = (1.0 - f) * right[j] + f * left[j + 1]
    out[tq <= t[0]] = right[0]
    return out


def delay(t: np.ndarray, y: np.ndarray, d: float) -> np.ndarray:
    """y (N, k) sampled d seconds late: y(t_k - d) by linear interpolation (held before t_0), any grid t."""
    if d == 0.0:
        return y
    out = np.empty_like(y)
    for j in range(y.shape[1]):
        out[:, j] = np.interp(t - d, t, y[:, j])
    return out


def left_inputs(tau: np.ndarray, u: np.ndarray, f: np.ndarray, eff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Delivered torques (N, 3) N m and pivot forces (N, 2) N just before each sample of a run whose
    delivered torques after the samples are ``tau`` and whose held commands and forces are ``u``, ``f``
    (N, ...; row k held on [t_k, t_k+1)): the previous interval's (the first sample's own before t_0).
    With a current-loop lag the delivered torque is continuous: ``tau`` itself."""
    from otbot_hw.model.effect_physics import actuated_torques

    tau_l, f_l = tau.copy(), f.copy()
    if len(tau) > 1:
        if eff[T_I] == 0.0:
            tau_l[1:] = actuated_torques(np.ascontiguousarray(u[:-1], dtype=float), eff)
        f_l[1:] = f[:-1]
    return tau_l, f_l


def sensor_outputs(traj, params, eff: np.ndarray, slip_rate: np.ndarray | None = None,
                   qdd: np.ndarray | None = None, forces: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Noise-free sensor readings of a run (``otbot_hw.simulation.simulator.Trajectory`` with its
    delivered torques ``tau`` and slip angles ``slip``; ``params`` an ``OtbotParams``), the sensor effects
    of ``eff`` applied. ``qdd`` (N, 6) and ``slip_rate`` (N, 2): the accelerations and slip rates at
    the samples when the integrator gave them (default: the trajectory's own, ``ext_rk4_zoh_samples``),
    else evaluated here (with the trajectory's pivot forces ``f``, or ``forces``).

    Returns ``joint_pos``, ``joint_vel`` (N, 3) rad, rad/s and ``imu_accel``, ``imu_gyro`` (N, 3)
    m/s^2, rad/s in the IMU frame (= B'' rotated by psi), as the recording stores them."""
    from otbot_hw.model.fixtures import fixture_code

    x = np.ascontiguousarray(traj.x, dtype=float)
    n = len(x)
    eff = np.asarray(eff, dtype=float)
    tau = np.ascontiguousarray(traj.tau, dtype=float)
    f = forces if forces is not None else getattr(traj, "f", None)
    f = np.zeros((n, 2)) if f is None else np.ascontiguousarray(f, dtype=float)
    tau_l, f_l = left_inputs(tau, np.asarray(traj.u, dtype=float), f, eff) if needs_left_limit(eff) else (tau, f)
    qdd = getattr(traj, "qdd", None) if qdd is None else qdd
    slip_rate = getattr(traj, "slip_rate", None) if slip_rate is None else slip_rate
    QDD = None if qdd is None else np.ascontiguousarray(qdd, dtype=float)
    SD = None if slip_rate is None else np.ascontiguousarray(slip_rate, dtype=float)
    pos, vel, acc_r, acc_l, gyro = sensor_samples(x, np.ascontiguousarray(traj.slip, dtype=float), tau, f, tau_l,
                                                  f_l, QDD, SD, eff, params.as_array(), fixture_code(traj.fixture))
    d = float(eff[D_IMU])
    return {"joint_pos": pos, "joint_vel": vel, "imu_accel": delay_held(traj.t, acc_r, acc_l, d),
            "imu_gyro": delay_held(traj.t, gyro, gyro, d)}
