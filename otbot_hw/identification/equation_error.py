"""Equation-error (linear least-squares) estimates of inertial parameters: a global start.

The inverse dynamics u = Delta(q)^T (M(q) q_dd + (C(q, q_d) - E_f) q_d) is linear in
the base inertial parameters

    pi = (m_c, m_c x_B, m_c y_B, J_c,  m_p, m_p x_F, m_p y_F, J_p,  I_a, b_w, b_p)

with J_c = I_c + m_c (x_B^2 + y_B^2) and J_p = I_p + m_p (x_F^2 + y_F^2) (inertias
about the pivot), so u = Y(q, q_d, q_dd) pi. Each body (chassis at heading
beta = theta = alpha - phi_p, platform at beta = alpha) contributes to the
generalized forces Q = M q_dd + (C - E_f) q_d, for mass m and first moments
(m x, m y) in its own frame and J about the pivot:

    Q_x     += m x_dd + m x (-s b_dd - c b_d^2) + m y (-c b_dd + s b_d^2)
    Q_y     += m y_dd + m x ( c b_dd - s b_d^2) + m y (-s b_dd - c b_d^2)
    Q_alpha += k_a [m x (-s x_dd + c y_dd) + m y (-c x_dd - s y_dd) + J b_dd]
    Q_phi_p += k_p [same bracket]

with (s, c) = (sin beta, cos beta), (k_a, k_p) = d beta / d(alpha, phi_p): (1, -1)
for the chassis and (1, 0) for the platform; the wheels add I_a phi_dd + b_w phi_d
and the pivot b_p phi_p_d. ``regressor`` builds Y; ``tests/test_identification``
checks Y pi against ``dynamics.inverse_dynamics``.

``estimate_body`` solves for one body's four parameters with everything else
known, from the measured signals only: wheel and pivot encoder angles and rates
(smoothed, Savitzky-Golay), the smoothed IMU pivot acceleration (B'') for x_dd, y_dd, and the
derivative of the smoothed encoder rates for the angular accelerations. Samples
near a torque step (a change of more than 20 % of the largest torque within one
sample) are left out (the smoothing blurs the jump there).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_filter

from otbot_hw.identification.errors import IdentificationError

PI_NAMES: tuple[str, ...] = ("m_c", "m_c*x_B", "m_c*y_B", "J_c", "m_p", "m_p*x_F", "m_p*y_F", "J_p",
                             "I_a", "b_w", "b_p")
BODY_SLICES = {"chassis": slice(0, 4), "platform": slice(4, 8)}
STEP_FRACTION = 0.2  # torque change within one sample, relative to the largest torque, that counts as a step


def base_parameters(values) -> np.ndarray:
    """pi (11,) from physical parameters (mapping or ``OtbotParams``)."""
    v = values.values() if hasattr(values, "values") and not isinstance(values, dict) else values
    mc, xb, yb, ic = v["m_c"], v["x_B"], v["y_B"], v["I_c"]
    mp, xf, yf, ip = v["m_p"], v["x_F"], v["y_F"], v["I_p"]
    return np.array([mc, mc * xb, mc * yb, ic + mc * (xb ** 2 + yb ** 2),
                     mp, mp * xf, mp * yf, ip + mp * (xf ** 2 + yf ** 2), v["I_a"], v["b_w"], v["b_p"]])


def body_parameters(body: str, pi4: np.ndarray) -> dict[str, float]:
    """Physical (m, I, x, y) of ``body`` from its four base parameters (m, m x, m y, J)."""
    m, mx, my, J = (float(v) for v in pi4)
    if not m > 0:
        raise IdentificationError(f"equation error gave a non-positive {body} mass {m:.4g} kg")
    x, y = mx / m, my / m
    inertia = J - m * (x * x + y * y)
    names = ("m_c", "I_c", "x_B", "y_B") if body == "chassis" else ("m_p", "I_p", "x_F", "y_F")
    return dict(zip(names, (m, inertia, x, y)))


def regressor(q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, l1: float, l2: float, r: float) -> np.ndarray:
    """Y (n, 3, 11): u_k = Y_k pi for samples q, qd, qdd (n, 6); geometry l1, l2, r in m."""
    q, qd, qdd = np.atleast_2d(q), np.atleast_2d(qd), np.atleast_2d(qdd)
    n = len(q)
    W = np.zeros((n, 6, 11))  # generalized-force columns
    xdd, ydd = qdd[:, 0], qdd[:, 1]
    bodies = ((0, q[:, 2] - q[:, 5], qd[:, 2] - qd[:, 5], qdd[:, 2] - qdd[:, 5], -1.0),
              (4, q[:, 2], qd[:, 2], qdd[:, 2], 0.0))
    for j, b, bd, bdd, kp in bodies:
        s, c = np.sin(b), np.cos(b)
        W[:, 0, j] = xdd
        W[:, 1, j] = ydd
        W[:, 0, j + 1] = -s * bdd - c * bd ** 2
        W[:, 1, j + 1] = c * bdd - s * bd ** 2
        W[:, 0, j + 2] = -c * bdd + s * bd ** 2
        W[:, 1, j + 2] = -s * bdd - c * bd ** 2
        tx = -s * xdd + c * ydd
        ty = -c * xdd - s * ydd
        for row, k in ((2, 1.0), (5, kp)):
            W[:, row, j + 1] += k * tx
            W[:, row, j + 2] += k * ty
            W[:, row, j + 3] += k * bdd
    W[:, 3, 8] = qdd[:, 3]
    W[:, 4, 8] = qdd[:, 4]
    W[:, 3, 9] = qd[:, 3]
    W[:, 4, 9] = qd[:, 4]
    W[:, 5, 10] = qd[:, 5]
    # Delta^T (3x6): [M_FIK^T  I]
    th = q[:, 2] - q[:, 5]
    st, ct = np.sin(th), np.cos(th)
    k = r / (2 * l2)
    D = np.zeros((n, 6, 3))
    D[:, 0, 0] = k * (l2 * ct - l1 * st)
    D[:, 0, 1] = k * (l2 * ct + l1 * st)
    D[:, 1, 0] = k * (l1 * ct + l2 * st)
    D[:, 1, 1] = k * (-l1 * ct + l2 * st)
    D[:, 2, 0] = k
    D[:, 2, 1] = -k
    D[:, 2, 2] = 1.0
    D[:, 3, 0] = D[:, 4, 1] = D[:, 5, 2] = 1.0
    return np.einsum("nij,nik->njk", D, W)


@dataclass
class MeasuredMotion:
    """States reconstructed from a recording's sensors: q, qd, qdd (n, 6), torque (n, 3), usable mask."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    torque: np.ndarray
    usable: np.ndarray


def motion_from_sensors(rec, l1: float, l2: float, r: float, window: float = 0.5) -> MeasuredMotion:
    """Reconstruct (q, q_d, q_dd) of a floor run from encoders and IMU (see the module docstring).

    ``window``: Savitzky-Golay smoothing window in s (cubic; the noise in the
    differentiated encoder rates biases the linear estimate, a wide window keeps it small).
    """
    if rec.joint_pos is None or rec.joint_vel is None:
        raise IdentificationError("equation-error start needs the joint encoders (topic /otbot/joints)")
    if rec.imu_accel is None:
        raise IdentificationError("equation-error start needs the IMU (topic /otbot/imu)")
    n = len(rec.t)
    dt = float(np.median(np.diff(rec.t)))
    w = int(round(window / dt)) | 1
    w = min(w, n if n % 2 else n - 1)
    if w < 5:
        raise IdentificationError(f"equation-error start needs at least 5 samples, got {n}")
    phi = np.asarray(rec.joint_pos, dtype=float)
    phid = savgol_filter(np.asarray(rec.joint_vel, dtype=float), w, 3, axis=0)
    phidd = savgol_filter(np.asarray(rec.joint_vel, dtype=float), w, 3, deriv=1, delta=dt, axis=0)
    k = r / (2 * l2)
    theta = -phi[0, 2] + k * ((phi[:, 0] - phi[0, 0]) - (phi[:, 1] - phi[0, 1]))
    alpha = theta + phi[:, 2]
    thd = k * (phid[:, 0] - phid[:, 1])
    thdd = k * (phidd[:, 0] - phidd[:, 1])
    q = np.zeros((n, 6))
    q[:, 2], q[:, 3:] = alpha, phi
    st, ct = np.sin(theta), np.cos(theta)
    qd = np.zeros((n, 6))
    qd[:, 0] = k * ((l2 * ct - l1 * st) * phid[:, 0] + (l2 * ct + l1 * st) * phid[:, 1])
    qd[:, 1] = k * ((l1 * ct + l2 * st) * phid[:, 0] + (-l1 * ct + l2 * st) * phid[:, 1])
    qd[:, 2] = thd + phid[:, 2]
    qd[:, 3:] = phid
    qdd = np.zeros((n, 6))
    a = savgol_filter(np.asarray(rec.imu_accel, dtype=float), w, 3, axis=0)
    ca, sa = np.cos(alpha), np.sin(alpha)
    qdd[:, 0] = ca * a[:, 0] - sa * a[:, 1]
    qdd[:, 1] = sa * a[:, 0] + ca * a[:, 1]
    qdd[:, 2] = thdd + phidd[:, 2]
    qdd[:, 3:] = phidd
    U = np.asarray(rec.torque, dtype=float)
    usable = np.ones(n, dtype=bool)
    # a step: a change within one sample of more than STEP_FRACTION of the largest torque (a ramp of a
    # designed excitation is smooth enough for the filter)
    jump_tol = max(STEP_FRACTION * float(np.max(np.abs(U))), 1e-9)
    jumps = np.nonzero(np.any(np.abs(np.diff(U, axis=0)) > jump_tol, axis=1))[0]
    half = w // 2
    for j in jumps:
        usable[max(0, j - half):j + half + 2] = False
    if usable.sum() < 4:
        raise IdentificationError("equation-error start: too few samples away from torque steps")
    return MeasuredMotion(q=q, qd=qd, qdd=qdd, torque=U, usable=usable)


def estimate_body(rec, known, body: str, t_max: float | None = None,
                  platform_moments: bool = False) -> dict[str, float]:
    """Linear least-squares estimate of one body's (mass, inertia, centre of mass) from a floor run.

    ``known``: the other parameters (``OtbotParams``); ``body``: "chassis" or "platform".
    Returns physical parameters, e.g. {m_p, I_p, x_F, y_F}. ``platform_moments`` (chassis only):
    solve the platform's first moments m_p (x_F, y_F) and its inertia about the pivot J_p too, its
    mass m_p held (the regressor's m_c and m_p columns are the same: only m_c + m_p enters a
    floor run); adds x_F, y_F, I_p. Raises ``IdentificationError`` when the sensors are missing
    or the result is not physical (mass <= 0).
    """
    if body not in BODY_SLICES:
        raise IdentificationError(f"body must be 'chassis' or 'platform', got {body!r}")
    mot = motion_from_sensors(rec, known.l1, known.l2, known.r)
    use = mot.usable.copy()
    if t_max is not None:
        use &= np.asarray(rec.t) - rec.t[0] <= t_max + 1e-9
    Y = regressor(mot.q[use], mot.qd[use], mot.qdd[use], known.l1, known.l2, known.r)
    pi = base_parameters(known)
    sl = BODY_SLICES[body]
    cols = list(range(11))[sl] + ([5, 6, 7] if platform_moments and body == "chassis" else [])
    mask = np.ones(11, dtype=bool)
    mask[cols] = False
    lhs = mot.torque[use] - Y[:, :, mask] @ pi[mask]
    A = Y[:, :, cols].reshape(-1, len(cols))
    b = lhs.reshape(-1)
    scale = np.linalg.norm(A, axis=0)
    if np.any(scale == 0):
        raise IdentificationError(f"equation-error start: the {body} parameters do not enter this motion")
    sol, *_ = np.linalg.lstsq(A / scale, b, rcond=None)
    sol = sol / scale
    out = body_parameters(body, sol[:4])
    if len(cols) > 4:
        mp = float(known.m_p)
        xf, yf = sol[4] / mp, sol[5] / mp
        out.update(x_F=float(xf), y_F=float(yf), I_p=float(sol[6] - mp * (xf * xf + yf * yf)))
    return out
