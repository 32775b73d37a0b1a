"""Residuals of a (possibly extended) model against a recording.

Two families:

* **Equation residuals** from measured states (no simulation). Encoder rates are
  smoothed and differentiated with Savitzky-Golay filters; the platform heading comes
  from the holonomic constraint (alpha = 0 at the recording start). Every compared
  signal passes the *same* filter: accelerations are the SG derivative of rates, so
  commands and IMU readings enter as the SG derivative of their running integral.
  - torque residual (N, 3) N m per joint: r = B^-1 (a_model - a_meas), B = d a / d tau,
    i.e. the command minus the torque the model needs for the measured motion
    (a = task accelerations (x_dd, y_dd, alpha_dd) on the floor, joint accelerations
    on a fixture). Unmodelled friction shows as +friction.
  - IMU kinematic residual (N, 3): measured (a_x, a_y, g_z) minus the IMU reading
    predicted from the encoder motion through the model's sensor transforms.
* **Simulation residual** per channel (CHANNELS): measurement minus the output of a
  simulation of the whole run from the initial state estimated from the encoders
  (``otbot_hw.diagnose.simulated_run``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.signal import savgol_filter

from otbot_hw.diagnose.data import CHANNELS, DiagnosisData
from otbot_hw.model import compiled
from otbot_hw.model import effect_physics as phys
from otbot_hw.model import effects as fx
from otbot_hw.model import sensor_model
from otbot_hw.model.effects import ExtendedModel
from otbot_hw.model.fixtures import fixture_code
from otbot_hw.model.kinematics import fik_entries


@dataclass
class Motion:
    """Motion estimated from the encoders (rolling-angle coordinates): q, qd, qdd (N, 6);
    a_meas (N, 3) the accelerations the torque residual compares; tau (N, 3) filtered delivered torque."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    a_meas: np.ndarray
    tau: np.ndarray


def delivered_torque_intervals(u: np.ndarray, dt: float, eff: np.ndarray, tau0: np.ndarray) -> np.ndarray:
    """Mean delivered torque (N, 3) over each ZOH interval [t_k, t_k+1) (``actuated_torque``: gain, dead
    zone, soft limit, saturation; then the exact lag)."""
    tc = phys.actuated_torques(np.ascontiguousarray(u, dtype=float), np.asarray(eff, dtype=float))
    T = eff[fx.T_I]
    if T <= 0:
        return tc
    out = np.empty_like(tc)
    ta = tau0.copy()
    e = np.exp(-dt / T)
    frac = T / dt * (1.0 - e)
    for k in range(len(u)):
        out[k] = tc[k] + (ta - tc[k]) * frac
        ta = tc[k] + (ta - tc[k]) * e
    return out


TORQUE_CACHE_SIZE = 64  # delivered-torque series kept per recording (one per actuator-effect combination)


ACTUATOR_ENTRIES = [fx.K_R, fx.K_L, fx.K_P, fx.U_MAX_R, fx.U_MAX_L, fx.U_MAX_P, fx.T_I] + \
    [fx.DZ_R + i for i in range(3)] + [fx.TS_R + i for i in range(3)]  # what the delivered torque depends on


def _actuator_key(eff: np.ndarray) -> tuple:
    return tuple(eff[ACTUATOR_ENTRIES])


def _bounded(data: DiagnosisData, name: str, key, compute):
    """``compute()`` kept in the recording's memo dict ``name`` under ``key`` (at most ``TORQUE_CACHE_SIZE``
    entries; read-only arrays)."""
    cache = data.memo(name, dict)
    value = cache.get(key)  # one lookup: another prediction thread may clear the cache meanwhile
    if value is None:
        if len(cache) > TORQUE_CACHE_SIZE:
            cache.clear()
        value = compute()
        value.flags.writeable = False
        cache[key] = value
    return value


def _delivered_torque(data: DiagnosisData, eff: np.ndarray) -> np.ndarray:
    """Delivered torque over each interval (``delivered_torque_intervals``), kept per actuator-effect values."""
    return _bounded(data, "delivered_torque", _actuator_key(eff),
                    lambda: delivered_torque_intervals(data.u, data.dt, eff, initial_tau(data)))


def _filtered_torque(data: DiagnosisData, eff: np.ndarray) -> np.ndarray:
    """``integral_rate`` of the delivered torque (what the torque residual compares), kept likewise."""
    return _bounded(data, "filtered_torque", _actuator_key(eff),
                    lambda: integral_rate(data, _delivered_torque(data, eff)))


def initial_tau(data: DiagnosisData) -> np.ndarray:
    """Delivered torque before t_0: zero when the robot starts at rest, else the first command."""
    v0 = data.enc_vel[0] if data.enc_vel is not None and np.all(np.isfinite(data.enc_vel[0])) else np.zeros(3)
    return np.zeros(3) if np.all(np.abs(v0) < 0.05) else data.u[0].copy()


def integral_rate(data: DiagnosisData, y: np.ndarray) -> np.ndarray:
    """SG derivative of the running integral of a sample-and-hold signal y (N, k): the same
    smoothing the acceleration estimate applies, so both can be compared sample by sample."""
    cum = np.vstack([np.zeros((1, y.shape[1])), np.cumsum(y[:-1] * data.dt, axis=0)])
    return data.smooth(cum, deriv=1)


def joint_rates(data: DiagnosisData) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed joint rates and accelerations (N, 3) from the encoder readings (raw units; copies of
    the recording's memo)."""
    vel, acc = data.memo("joint_rates", lambda: _joint_rates(data))
    return vel.copy(), acc.copy()


def _joint_rates(data: DiagnosisData) -> tuple[np.ndarray, np.ndarray]:
    vel = data.enc_vel.copy() if data.enc_vel is not None else np.full_like(data.enc_pos, np.nan)
    dpos = data.smooth(data.enc_pos, deriv=1)
    for j in range(3):
        if not np.all(np.isfinite(vel[:, j])):
            vel[:, j] = dpos[:, j]
    return data.smooth(vel), data.smooth(vel, deriv=1)


def start_rates(data: DiagnosisData, smoothed: np.ndarray) -> np.ndarray:
    """Joint rates (N, 3) with row 0 replaced by the best initial-rate estimate.

    A joint whose first raw reading is within 3 sigma of zero starts at rest (0 exactly:
    runs start from standstill and the platform's slow velocity decay would carry an
    initial noise error through the whole simulation); otherwise a short (5-sample)
    quadratic Savitzky-Golay fit at the edge, which is less biased than the long window.
    """
    out = smoothed.copy()
    raw = data.enc_vel
    short = savgol_filter(np.where(np.isfinite(raw), raw, smoothed), 5, 2, axis=0, mode="interp") \
        if raw is not None else smoothed
    for j, ch in enumerate(("w_r", "w_l", "w_p")):
        if raw is not None and ch not in data.unusable and np.isfinite(raw[0, j]):
            out[0, j] = 0.0 if abs(raw[0, j]) < 3.0 * data.noise_sigma(ch) else short[0, j]
    return out


def estimate_motion(data: DiagnosisData, model: ExtendedModel, smooth_rates: bool = True,
                   accelerations: bool = True) -> Motion:
    """Undo the model's encoder effects and build q, qd, qdd (rolling angles) from the encoders.

    ``smooth_rates=False`` keeps the raw encoder rates (unbiased at the ends of the record,
    used for the initial state); accelerations are always the SG derivative.
    ``accelerations=False``: positions and rates only (qdd and a_meas zero, tau None), what the
    initial state needs.
    """
    p, eff = model.params, model.eff
    pos = data.enc_pos.astype(float).copy()
    vel, acc = joint_rates(data)
    if not smooth_rates:
        vel = data.memo("start_rates", lambda: start_rates(data, joint_rates(data)[0])).copy()
    tau_i = _delivered_torque(data, eff)
    if accelerations:
        tau = _filtered_torque(data, eff)
    else:
        tau, acc = None, np.zeros_like(acc)
    rho = (1.0 / (1.0 + eff[fx.DR_R]), 1.0 / (1.0 + eff[fx.DR_L]))
    for i in range(2):
        s = 1.0 + eff[fx.E_R + i]
        pos[:, i] /= s
        vel[:, i] /= s
        acc[:, i] /= s
    if (eff[fx.K_SLIP] != 0.0 or eff[fx.T_TRAC] != 0.0) and data.fixture == "floor":
        # the slip law on the delivered torque (motor friction neglected here); its integral and derivative
        b = p.b_w + eff[fx.DB_W] * np.array([1.0, -1.0])
        rate_i = np.column_stack([phys.slip_rate_series(np.ascontiguousarray(tau_i[:, i]), b[i], eff) for i in range(2)])
        slip_ang = np.vstack([np.zeros((1, 2)), np.cumsum(rate_i[:-1] * data.dt, axis=0)])
        rate = integral_rate(data, rate_i)
        rate_d = data.smooth(rate, deriv=1) if accelerations else np.zeros_like(rate)
        for i in range(2):
            pos[:, i] -= slip_ang[:, i]
            vel[:, i] -= rate[:, i]
            acc[:, i] -= rate_d[:, i]
    for i in range(2):
        pos[:, i] /= rho[i]
        vel[:, i] /= rho[i]
        acc[:, i] /= rho[i]
    n = len(data)
    q = np.zeros((n, 6))
    qd = np.zeros((n, 6))
    qdd = np.zeros((n, 6))
    q[:, 3:] = pos
    qd[:, 3:] = vel
    qdd[:, 3:] = acc
    if data.fixture == "floor":
        k = p.r / (2 * p.l2)
        g = k * (pos[:, 0] - pos[:, 1]) + pos[:, 2]
        q[:, 2] = g - g[0]
        th = q[:, 2] - pos[:, 2]
        c, s = np.cos(th), np.sin(th)
        thd = k * (vel[:, 0] - vel[:, 1])
        # M_FIK(theta) and its derivative in theta (the entries at theta + pi/2: sin -> cos, cos -> -sin)
        b00, b01, b10, b11, kf = fik_entries(s, c, p.l1, p.l2, p.r)
        e00, e01, e10, e11, _ = fik_entries(c, -s, p.l1, p.l2, p.r)
        qd[:, 0] = b00 * vel[:, 0] + b01 * vel[:, 1]
        qd[:, 1] = b10 * vel[:, 0] + b11 * vel[:, 1]
        qd[:, 2] = kf * (vel[:, 0] - vel[:, 1]) + vel[:, 2]
        qdd[:, 0] = b00 * acc[:, 0] + b01 * acc[:, 1] + thd * (e00 * vel[:, 0] + e01 * vel[:, 1])
        qdd[:, 1] = b10 * acc[:, 0] + b11 * acc[:, 1] + thd * (e10 * vel[:, 0] + e11 * vel[:, 1])
        qdd[:, 2] = kf * (acc[:, 0] - acc[:, 1]) + acc[:, 2]
        a_meas = qdd[:, :3].copy()
    else:
        q[:, 2] = pos[:, 2] - pos[0, 2]
        qd[:, 2] = vel[:, 2]
        qdd[:, 2] = acc[:, 2]
        if data.fixture == "locked":
            q[:, 3:5] = pos[0, :2]
            qd[:, 3:5] = 0.0
            qdd[:, 3:5] = 0.0
        a_meas = qdd[:, 3:].copy()
    return Motion(q=q, qd=qd, qdd=qdd, a_meas=a_meas, tau=tau)


@njit(cache=True, nogil=True)
def _torque_residual(Q, QD, A, TAU, eff, prm, fixture):
    n = Q.shape[0]
    out = np.zeros((n, 3))
    f = np.zeros(2)
    x = np.empty(12)
    B = np.empty((3, 3))
    for k in range(n):
        x[:6] = Q[k]
        x[6:] = QD[k]
        acc0 = phys.ext_accelerations(x, TAU[k], f, eff, prm, fixture)
        lo = 0 if fixture == compiled.FLOOR else 3
        a0 = acc0[lo:lo + 3]
        for i in range(3):
            t = TAU[k].copy()
            t[i] += 1.0
            ai = phys.ext_accelerations(x, t, f, eff, prm, fixture)
            for j in range(3):
                B[j, i] = ai[lo + j] - a0[j]
        d = a0 - A[k]
        if fixture == compiled.LOCKED:
            out[k, 2] = d[2] / B[2, 2] if B[2, 2] != 0.0 else 0.0
        elif abs(np.linalg.det(B)) > 1e-12:
            out[k] = np.linalg.solve(B, d)
        else:  # a torque that does not move the robot (saturated traction): the least-norm torque
            out[k] = np.linalg.lstsq(B, d)[0]
    return out


def torque_residual(data: DiagnosisData, model: ExtendedModel, motion: Motion | None = None) -> np.ndarray:
    """Per-joint inverse-dynamics residual (N, 3) N m (command minus torque needed; 0 where not observable)."""
    m = motion or estimate_motion(data, model)
    x_q = m.q.copy()
    return _torque_residual(x_q, m.qd, m.a_meas, m.tau, model.eff, model.params.as_array(),
                            fixture_code(data.fixture))


def imu_residual(data: DiagnosisData, model: ExtendedModel, motion: Motion | None = None) -> np.ndarray | None:
    """Measured minus encoder-predicted IMU (N, 3): a_x, a_y (m/s^2), g_z (rad/s); None without an IMU."""
    if data.imu_acc is None:
        return None
    m = motion or estimate_motion(data, model)
    eff = model.eff
    acc, gyro = sensor_model.imu_from_motion(m.q[:, 2], m.qd[:, 2], m.qdd[:, 0], m.qdd[:, 1], m.qdd[:, 2], eff,
                                   floor=data.fixture == "floor")
    pred = np.column_stack([acc[:, 0], acc[:, 1], gyro[:, 2]])
    pred = sensor_model.delay(data.t, pred, eff[fx.D_IMU])
    out = data.memo("filtered_imu", lambda: _filtered_imu(data)) - pred
    for j, ch in enumerate(("a_x", "a_y", "g_z")):
        if ch in data.unusable:
            out[:, j] = np.nan
    return out


def _filtered_imu(data: DiagnosisData) -> np.ndarray:
    """Measured (a_x, a_y, g_z) (N, 3) through the filters the IMU residual compares them after."""
    meas = np.column_stack([data.imu_acc[:, 0], data.imu_acc[:, 1], data.imu_gyro[:, 2]])
    meas = np.where(np.isfinite(meas), meas, 0.0)  # unusable columns are blanked by imu_residual
    return np.column_stack([integral_rate(data, meas[:, :2]), data.smooth(meas[:, 2:])])
