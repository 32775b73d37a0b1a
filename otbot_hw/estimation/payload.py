"""Online payload estimation: the platform + load's m_p, I_p, x_F, y_F from torques and the motion.

**Linear in the parameters.** The platform (with whatever it carries) is one rigid body; its
parameters enter the dynamics only through

    theta = (m_p, m_p x_F, m_p y_F, J_P),   J_P = I_p + m_p (x_F^2 + y_F^2)  (inertia about the pivot),

and linearly (``otbot_hw.model.dynamics.mass_matrix``/``coriolis_matrix``: the platform's entries are
those of ``theta``). In task space the platform's share of u = M_bar p_dd + C_bar p_dot is
M_FIK^T w, with w = W(alpha, p_dot, p_dd) theta the generalized force (f_x, f_y N, n_alpha N m)
that accelerates the platform (its Newton-Euler equations at the pivot):

    f_x = m_p x_dd - (mx sin a + my cos a) a_dd - (mx cos a - my sin a) a_d^2
    f_y = m_p y_dd + (mx cos a - my sin a) a_dd - (mx sin a + my cos a) a_d^2
    n   = (-mx sin a - my cos a) x_dd + (mx cos a - my sin a) y_dd + J_P a_dd

so u - u_rest = Y theta with Y = M_FIK(theta_c)^T W (3 x 4) and u_rest the torque of the robot
without its platform (chassis, wheels, friction; the parameter file's values). Tested against the
full model (``tests/test_payload.py``).

**Estimator: exponentially-weighted recursive least squares in information form, with the parameter
file's values as a persistent prior** (chosen over a parameter-augmented EKF: the model is exactly
linear in theta, so least squares is optimal and needs no linearization or tuning of a process noise
on the pose; the pose EKF already gives the motion it needs, and keeping the two apart means a wrong
payload cannot corrupt the pose estimate). Per update, with forgetting factor lam (time constant
``window`` s, applied only while the data inform, so holding still does not erase what was learnt):

    Lambda <- lam Lambda + (1 - lam) Lambda_0 + Y^T R^-1 Y,   eta <- lam eta + (1 - lam) eta_0 + Y^T R^-1 y,
    theta = Lambda^-1 eta,  cov(theta) = Lambda^-1,

Lambda_0 = diag(prior_std)^-2, eta_0 = Lambda_0 theta_file: directions the motion does not excite
(e.g. J_P while alpha is held) stay at the file's values with the prior's std instead of winding up.
R is the residual variance per motor, estimated on line (floor ``torque_sigma``), so the covariance
is scaled by how well the model explains the torques. Accelerations come from differencing the
feedback's twist (the pose EKF on encoders and IMU); Y and y are both low-passed by the same filter
(``cutoff``), which keeps u - u_rest = Y theta exact for a constant theta, and decimated to
``update_rate`` so successive updates are nearly independent.

**Change detection.** A one-sided CUSUM on the normalized residual z = r^T S^-1 r / 3
(S = Y cov Y^T + R, E[z] = 1 when the model fits): g <- max(0, g + z - 1 - drift); g > threshold
flags a step change of the load (a box put on or taken off); the information is reset to the prior
and the payload re-estimated.

Units: kg, kg m (first moments), kg m^2, m; torques N m; frames: x_F, y_F in the platform frame B''.
Pure: no runtime imports.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Mapping

import numpy as np
from numba import njit

from otbot_hw.control.task_model import task_space_matrices
from otbot_hw.model.kinematics import fik_entries
from otbot_hw.params import ParameterError, read_entry

PAYLOAD_NAMES = ("m_p", "I_p", "x_F", "y_F")
THETA_NAMES = ("m_p", "m_p x_F", "m_p y_F", "J_P")
_L1, _L2, _R, _MP, _IP, _XF, _YF = 0, 1, 2, 7, 8, 9, 10


def theta_from_payload(m_p: float, I_p: float, x_F: float, y_F: float) -> np.ndarray:
    """theta = (m_p kg, m_p x_F kg m, m_p y_F kg m, J_P kg m^2) of the physical parameters."""
    return np.array([m_p, m_p * x_F, m_p * y_F, I_p + m_p * (x_F * x_F + y_F * y_F)])


def payload_from_theta(theta, cov=None) -> tuple[np.ndarray, np.ndarray | None]:
    """(m_p, I_p, x_F, y_F) of theta and, given cov(theta) (4x4), their std (first-order propagation)."""
    m, mx, my, jp = (float(v) for v in theta)
    mm = m if abs(m) > 1e-9 else 1e-9
    x, y = mx / mm, my / mm
    val = np.array([m, jp - (mx * mx + my * my) / mm, x, y])
    if cov is None:
        return val, None
    G = np.array([[1.0, 0.0, 0.0, 0.0],
                  [(mx * mx + my * my) / mm ** 2, -2 * mx / mm, -2 * my / mm, 1.0],
                  [-mx / mm ** 2, 1 / mm, 0.0, 0.0],
                  [-my / mm ** 2, 0.0, 1 / mm, 0.0]])
    var = np.einsum("ij,jk,ik->i", G, np.asarray(cov, dtype=float), G)
    return val, np.sqrt(np.maximum(var, 0.0))


@njit(cache=True)
def regressor_sample(alpha, phi_p, pd, pdd, u, prm, out):
    """Fill out (15,) with Y (3x4, row-major) and y = u - u_rest (3,) for one sample (see the module
    docstring; entries beyond 15 are left alone); prm: the parameter file's ``as_array()`` (its platform
    entries are ignored)."""
    q = prm.copy()
    q[_MP] = 0.0
    q[_IP] = 0.0
    q[_XF] = 0.0
    q[_YF] = 0.0
    Mb = np.empty((3, 3))
    Cb = np.empty((3, 3))
    task_space_matrices(alpha, phi_p, pd, q, Mb, Cb)
    sa, ca = np.sin(alpha), np.cos(alpha)
    ad, add = pd[2], pdd[2]
    W = np.zeros((3, 4))
    W[0, 0] = pdd[0]
    W[0, 1] = -sa * add - ca * ad * ad
    W[0, 2] = -ca * add + sa * ad * ad
    W[1, 0] = pdd[1]
    W[1, 1] = ca * add - sa * ad * ad
    W[1, 2] = -sa * add - ca * ad * ad
    W[2, 1] = -sa * pdd[0] + ca * pdd[1]
    W[2, 2] = -ca * pdd[0] - sa * pdd[1]
    W[2, 3] = add
    th = alpha - phi_p
    F = np.empty((3, 3))  # M_FIK (``otbot_hw.model.kinematics``)
    F[0, 0], F[0, 1], F[1, 0], F[1, 1], k = fik_entries(np.sin(th), np.cos(th), prm[_L1], prm[_L2], prm[_R])
    F[0, 2] = 0.0
    F[1, 2] = 0.0
    F[2, 0] = k
    F[2, 1] = -k
    F[2, 2] = 1.0
    for i in range(3):  # Y = F^T W
        for j in range(4):
            s = 0.0
            for a in range(3):
                s += F[a, i] * W[a, j]
            out[4 * i + j] = s
        s = u[i]
        for j in range(3):
            s -= Mb[i, j] * pdd[j] + Cb[i, j] * pd[j]
        out[12 + i] = s


class LowPass:
    """Second-order Butterworth low-pass (cutoff Hz at ``rate`` Hz) on a vector of channels, sample by sample."""

    def __init__(self, cutoff: float, rate: float, channels: int):
        from scipy.signal import butter

        wn = min(0.99, 2.0 * cutoff / rate)
        self.b, self.a = butter(2, wn)
        self.z = np.zeros((2, channels))
        self.primed = False

    def step(self, x: np.ndarray) -> np.ndarray:
        b, a, z = self.b, self.a, self.z
        if not self.primed:  # start at steady state on the first sample
            self.primed = True
            from scipy.signal import lfilter_zi

            z[:] = np.outer(lfilter_zi(b, a), x)
        y = b[0] * x + z[0]
        z0 = b[1] * x - a[1] * y + z[1]
        z[1] = b[2] * x - a[2] * y
        z[0] = z0
        return y


@dataclass(frozen=True)
class AdaptationConfig:
    """Online payload adaptation (``daemon.adaptation`` in config/robot.yaml; ``otbot track --adapt``).

    enabled: the daemon adapts; max_mass (kg): largest platform + load mass; the centre must lie within
    the platform's ``radius`` (config/otbot.yaml); window (s): forgetting time constant; cutoff (Hz):
    low-pass of torques and regressor; update_rate (Hz): estimator updates; torque_sigma (N m): floor of
    the residual std per motor; prior_mass_std (kg), prior_moment_std (kg m), prior_inertia_std
    (kg m^2): the file values' prior; confident_mass_std (kg), confident_centre_std (m),
    confident_inertia_std (kg m^2): the estimate is used once its std is below these; ramp (s): time
    constant of the law's blend to a new estimate (bumpless); cusum_drift, cusum_threshold: change
    detector (dimensionless, on z); min_alpha_accel (rad/s^2): I_p counts as confident only after 0.5 s
    (forgetting-weighted) of samples with |alpha_dd| (low-passed) above this: below it the platform's
    angular acceleration is differencing noise, and noise in a regressor biases its coefficient towards
    zero (errors in variables), which the covariance does not show; warm_up (s): informative updates
    needed (after a start or a detected change) before any estimate counts as confident; min_accel
    (m/s^2): a sample informs only when its low-passed |(x_dd, y_dd)| or |alpha_dd| is above this or
    min_alpha_accel (at rest or cruising the differenced twist is noise, which would pull the estimate
    towards zero)."""

    enabled: bool = False
    max_mass: float = 300.0
    window: float = 30.0
    cutoff: float = 3.0
    update_rate: float = 25.0
    torque_sigma: float = 0.05
    prior_mass_std: float = 100.0
    prior_moment_std: float = 20.0
    prior_inertia_std: float = 20.0
    confident_mass_std: float = 3.0
    confident_centre_std: float = 0.05
    confident_inertia_std: float = 0.5
    ramp: float = 0.5
    cusum_drift: float = 4.0
    cusum_threshold: float = 60.0
    min_alpha_accel: float = 0.5
    warm_up: float = 0.5
    min_accel: float = 0.1

    UNITS = {"max_mass": "kg", "window": "s", "cutoff": "Hz", "update_rate": "Hz", "torque_sigma": "N m",
             "prior_mass_std": "kg", "prior_moment_std": "kg m", "prior_inertia_std": "kg m^2",
             "confident_mass_std": "kg", "confident_centre_std": "m", "confident_inertia_std": "kg m^2",
             "ramp": "s", "cusum_drift": "1", "cusum_threshold": "1", "min_alpha_accel": "rad/s^2",
             "warm_up": "s", "min_accel": "m/s^2"}

    @classmethod
    def from_section(cls, data: Mapping | None, source: str = "config/robot.yaml") -> "AdaptationConfig":
        """From the ``daemon.adaptation`` mapping (absent keys keep their defaults); ``ParameterError``
        names a bad key."""
        if data is None:
            return cls()
        if not isinstance(data, Mapping):
            raise ParameterError(f"{source}: 'daemon.adaptation' must be a mapping")
        bad = set(data) - {"enabled", *cls.UNITS}
        if bad:
            raise ParameterError(f"{source}: 'daemon.adaptation' has unknown key(s) {sorted(bad)} "
                                 f"(known: enabled, {', '.join(cls.UNITS)})")
        kw: dict[str, Any] = {}
        if "enabled" in data:
            if not isinstance(data["enabled"], bool):
                raise ParameterError(f"{source}: 'daemon.adaptation.enabled' must be true or false")
            kw["enabled"] = data["enabled"]
        for key, unit in cls.UNITS.items():
            if key not in data:
                continue
            v, _ = read_entry(source, f"daemon.adaptation.{key}", data[key], unit)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ParameterError(f"{source}: 'daemon.adaptation.{key}' must be a number > 0 ({unit}), got {v!r}")
            kw[key] = float(v)
        return cls(**kw)

    @classmethod
    def load(cls, path=None) -> "AdaptationConfig":
        """The ``daemon.adaptation`` section of the hardware YAML ``path`` (default config/robot.yaml)."""
        from otbot_hw.params import DEFAULT_CONFIG_DIR, read_yaml

        path = path or DEFAULT_CONFIG_DIR / "robot.yaml"
        data = read_yaml(path) or {}
        daemon = data.get("daemon") if isinstance(data, Mapping) else None
        return cls.from_section(daemon.get("adaptation") if isinstance(daemon, Mapping) else None, str(path))

    def with_(self, **kw) -> "AdaptationConfig":
        return replace(self, **kw)


@dataclass
class PayloadEstimate:
    """m_p (kg), I_p (kg m^2), x_F, y_F (m, frame B'') with std; theta and its covariance; ``confident``
    per physical parameter (std below the configured thresholds)."""

    value: np.ndarray
    std: np.ndarray
    theta: np.ndarray
    cov: np.ndarray
    confident: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {n: {"value": float(self.value[i]), "std": float(self.std[i])} for i, n in enumerate(PAYLOAD_NAMES)}


class PayloadEstimator:
    """Recursive estimate of theta from samples of the motion and the torques that caused it.

    ``params``: the parameter file (``OtbotParams``: chassis, wheels, friction taken as known; its
    platform values are the prior); ``config``: ``AdaptationConfig``; ``period`` (s): the sample period.
    Feed ``observe`` once per sample; ``estimate()`` any time."""

    def __init__(self, params, config: AdaptationConfig, period: float):
        self.params = params
        self.config = config
        self.period = float(period)
        self.prm = np.ascontiguousarray(params.as_array(), dtype=float)
        self.theta0 = theta_from_payload(params.m_p, params.I_p, params.x_F, params.y_F)
        c = config
        self.L0 = np.diag(1.0 / np.array([c.prior_mass_std, c.prior_moment_std, c.prior_moment_std,
                                          c.prior_inertia_std]) ** 2)
        self.eta0 = self.L0 @ self.theta0
        self.decimate = max(1, int(round(1.0 / (c.update_rate * self.period))))
        h = self.decimate * self.period
        self.lam = math.exp(-h / c.window)
        self.lam_noise = math.exp(-h / (0.5 * c.window))
        self._buf = np.empty(18)  # Y (12), y (3), p_dd (3): filtered together
        self.reset()

    def reset(self) -> None:
        """Forget everything learnt: back to the file's values with the prior's covariance."""
        self.L = self.L0.copy()
        self.eta = self.eta0.copy()
        self.theta = self.theta0.copy()
        self.noise_var = np.full(3, self.config.torque_sigma ** 2)
        self._noise_acc = np.zeros(3)
        self._noise_w = 0.0
        self.cusum = 0.0
        self.filter = LowPass(self.config.cutoff, 1.0 / self.period, 18)
        self._prev = None
        self._k = 0
        self.updates = 0
        self.settled = 0  # updates since the last reset, for the CUSUM's warm-up
        self.alpha_excitation = 0.0  # (forgetting) count of updates with |alpha_dd| >= min_alpha_accel

    def observe(self, t: float, alpha: float, phi_p: float, p_dot, u_prev) -> bool:
        """One sample at time t (s): platform angle alpha, pivot angle phi_p (rad), twist p_dot (m/s, rad/s),
        and u_prev (3,) N m, the torques that acted over the interval up to t. Returns True when this
        sample flagged a step change of the load (the estimate has been reset)."""
        pd = np.asarray(p_dot, dtype=float)
        prev = self._prev
        self._prev = (float(t), float(alpha), float(phi_p), pd.copy())
        if prev is None:
            return False
        h = t - prev[0]
        if not abs(h - self.period) < 0.25 * self.period:  # a gap (unpowered, a fault): start over
            self.filter = LowPass(self.config.cutoff, 1.0 / self.period, 18)
            return False
        pdd = (pd - prev[3]) / h
        pm = 0.5 * (pd + prev[3])
        regressor_sample(0.5 * (alpha + prev[1]), 0.5 * (phi_p + prev[2]), pm, pdd,
                         np.ascontiguousarray(u_prev, dtype=float), self.prm, self._buf)
        self._buf[15:] = pdd
        f = self.filter.step(self._buf)
        self._k += 1
        if self._k % self.decimate:
            return False
        c = self.config
        if math.hypot(f[15], f[16]) < c.min_accel and abs(f[17]) < c.min_alpha_accel:
            return False  # no acceleration above the differencing noise: nothing to learn, nothing forgotten
        return self.update(f[:12].reshape(3, 4), f[12:15])

    def update(self, Y: np.ndarray, y: np.ndarray) -> bool:
        """One least-squares update with regressor Y (3x4) and y = u - u_rest (3,) N m. Returns True on a
        detected change (then reset)."""
        c = self.config
        P = np.linalg.inv(self.L)
        r = y - Y @ self.theta
        S = Y @ P @ Y.T + np.diag(self.noise_var)
        z = float(r @ np.linalg.solve(S, r)) / 3.0
        info = Y.T @ (Y / self.noise_var[:, None])
        excited = float(np.trace(P @ info)) > 1e-3
        if excited:
            # the residual's variance per motor, from excited updates only (floor: torque_sigma)
            self._noise_acc = self.lam_noise * self._noise_acc + r * r
            self._noise_w = self.lam_noise * self._noise_w + 1.0
            self.noise_var = np.maximum(self._noise_acc / self._noise_w, c.torque_sigma ** 2)
            if self.settled > 2 * c.update_rate:  # the residual scale is known: watch for a change
                self.cusum = max(0.0, self.cusum + z - 1.0 - c.cusum_drift)
                if self.cusum > c.cusum_threshold:
                    self.reset()
                    return True
            lam = self.lam
            self.L = lam * self.L + (1 - lam) * self.L0 + Y.T @ (Y / self.noise_var[:, None])
            self.eta = lam * self.eta + (1 - lam) * self.eta0 + Y.T @ (y / self.noise_var)
            self.theta = np.linalg.solve(self.L, self.eta)
            self.updates += 1
            self.settled += 1
            # J_P is told only by samples whose alpha_dd is above the differencing noise
            self.alpha_excitation = lam * self.alpha_excitation + float(abs(Y[2, 3]) >= c.min_alpha_accel)
        return False

    def estimate(self) -> PayloadEstimate:
        cov = np.linalg.inv(self.L)
        val, std = payload_from_theta(self.theta, cov)
        c = self.config
        warm = self.settled >= c.warm_up * c.update_rate  # informative updates enough to know the residual scale
        conf = {"m_p": warm and std[0] <= c.confident_mass_std,
                "x_F": warm and std[2] <= c.confident_centre_std and std[0] <= c.confident_mass_std,
                "y_F": warm and std[3] <= c.confident_centre_std and std[0] <= c.confident_mass_std,
                "I_p": warm and std[1] <= c.confident_inertia_std and self.alpha_excitation >= 0.5 * c.update_rate}
        return PayloadEstimate(val, std, self.theta.copy(), cov, conf)


def bounds_violation(value, std, max_mass: float, radius: float, k: float = 3.0) -> str | None:
    """Why (m_p, I_p, x_F, y_F) with std lies outside the physical bounds by more than k std — mass in
    (0, max_mass] kg, centre within ``radius`` m of the pivot, I_p > 0 — or None."""
    m, ip, x, y = (float(v) for v in value)
    sm, si, sx, sy = (float(v) for v in std)
    if m + k * sm <= 0:
        return f"m_p = {m:.1f} ± {sm:.1f} kg is not positive"
    if m - k * sm > max_mass:
        return f"m_p = {m:.1f} ± {sm:.1f} kg exceeds max_mass {max_mass:g} kg"
    d = math.hypot(x, y)
    sd = math.hypot(sx, sy)
    if d - k * sd > radius:
        return f"centre (x_F, y_F) = ({x:.3f}, {y:.3f}) ± ({sx:.3f}, {sy:.3f}) m lies outside the platform radius {radius:g} m"
    if ip + k * si <= 0:
        return f"I_p = {ip:.2f} ± {si:.2f} kg m^2 is not positive"
    return None
