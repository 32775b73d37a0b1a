"""Extended Kalman filter for the platform pose and twist of Otbot (filterpy ``ExtendedKalmanFilter``).

State (10,), ground frame B unless said otherwise::

    0 x, 1 y (m)            pivot P               5 alpha_dot (rad/s)
    2 alpha (rad)           platform heading      6 b_g (rad/s)      gyro z bias
    3 x_dot, 4 y_dot (m/s)                        7 b_ax, 8 b_ay (m/s^2) accelerometer x, y bias in B''
                                                  9 kappa (rad)      wheel-heading offset
                                                  10 e_p (rad)       pivot encoder quantization error

The filterpy object ``kf`` holds x and P (and the last prior/posterior, gain, innovation); the
prediction and the updates are written here on that state, because the generic ones neither gate
nor wrap and cost tens of microseconds in numpy's small-matrix overhead (``benchmarks/estimation.py``).

Prediction (``EstimatorConfig.prediction``, chosen by measurement in docs/estimation.md):

* ``imu``: the specific force in B'' (less its bias) rotated by alpha drives x_dot, y_dot; the gyro
  (less its bias) drives alpha, and alpha_dot is the newest gyro reading less the bias. The IMU
  reading taken at t_{k-1} (just after it, under the command of [t_{k-1}, t_k)) drives the step to
  t_k; a reading held over several steps (IMU slower than the loop) keeps driving them, with its
  noise counted once per IMU period, not once per step.
* ``model``: the paper's multiplier-free dynamics (``otbot_hw.model.compiled``) under the commanded
  torque drive all of the twist, with white acceleration noise; the IMU is then a measurement (the gyro
  of alpha_dot + b_g, the accelerometer of R(alpha)^T p_dd + b_a at the previous sample). Used also
  when no IMU reading has ever arrived.

Updates, each gated by its Mahalanobis distance (chi-square, ``gate_probability``), a rejected one
counted and not applied:

* ``encoders`` (4): the joint rates phi_dot = M_IIK(alpha - phi_p) p_dot (paper §2.3.2, phi_p from the
  pivot encoder) and the wheel heading r/(2 l2)(phi_r - phi_l) + phi_p = alpha - kappa + e_c (the
  holonomic constraint of the paper, whose constant kappa only wheel slip changes). A rejected encoder
  update is taken as slip: kappa's variance grows by the heading innovation squared, so the next update
  re-anchors the wheel heading instead of pulling alpha. The pivot angle's quantization error e_p is not
  white: it stays put while the pivot reading stays (on every straight of the corridor the pivot barely
  turns), so it is a state, drawn afresh whenever the reading changes; a white model would let repeated
  readings of one quantized angle shrink alpha's variance far below its error. The wheels'
  share of the heading's quantization error renews with every count they roll and is taken as white.
* ``zupt`` (3): twist = 0 when no joint moved more than ``standstill_angle`` for ``standstill_window``
  and the gyro agrees; its sigma is what that window allows (standstill_angle r / window).
* ``gyro`` (1), ``accel`` (2): the IMU as measurement (prediction ``model`` only).
* ``fix`` (3): an absolute pose with its covariance (``PoseEKF.fix``), alpha residual wrapped.

alpha stays continuous (never wrapped to +-pi, like the recordings); every angle *residual* is wrapped.
Biases estimated: the gyro z bias and the accelerometer x, y biases -- all three are observable through
the encoders (alpha_dot and the velocity are measured). Not estimated: the gyro x, y biases and the
accelerometer z bias, which a planar estimator on flat ground never uses.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import chi2

from otbot_hw.estimation.config import EstimatorConfig
from otbot_hw.model import compiled
from otbot_hw.params import OtbotParams

N_STATE = 11
X, Y, A, VX, VY, VA, BG, BAX, BAY, KAPPA, EP = range(N_STATE)
#: Update kinds and their dimensions.
UPDATE_KINDS = {"encoders": 3, "heading": 1, "zupt": 3, "gyro": 1, "accel": 2, "fix": 3}
STATE_NAMES = ("x", "y", "alpha", "x_dot", "y_dot", "alpha_dot", "gyro_bias", "accel_bias_x", "accel_bias_y",
               "kappa", "pivot_quantization")
TWO_PI = 2 * math.pi

#: Prior std of the twist at ``initialize`` (m/s, m/s, rad/s) and default pose std (m, m, rad).
INITIAL_TWIST_STD = (0.01, 0.01, 0.01)
INITIAL_POSE_STD = (1e-6, 1e-6, 1e-6)


class EstimatorFault(RuntimeError):
    """NaN or stale sensor data, non-monotonic time, a diverged filter. str() says which, in words."""


def wrap_angle(a: float) -> float:
    """a wrapped into [-pi, pi) (rad)."""
    return (a + math.pi) % TWO_PI - math.pi


@dataclass(frozen=True)
class Estimate:
    """What the EKF believes at t (s), after using that sample's sensors.

    pose (3,) x, y (m), alpha (rad) of the pivot P / platform in B; twist (3,) m/s, m/s, rad/s;
    std (6,) their standard deviations; cov (11, 11) the full covariance (state order of the module
    docstring); gyro_bias (rad/s); accel_bias (2,) m/s^2 in B''; standstill: a zero-velocity update
    was applied; nis: normalized innovation squared of each update kind this step (nan: none);
    rejected / updates: cumulative gate rejections / accepted updates per kind.
    """

    t: float
    pose: np.ndarray
    twist: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    gyro_bias: float
    standstill: bool
    nis: dict
    rejected: dict
    updates: dict
    accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(2))


def _finite(*arrays) -> bool:
    """Whether every value is finite (a NaN or inf makes the sum non-finite)."""
    return all(math.isfinite(float(np.sum(a))) for a in arrays)


class PoseEKF:
    """Pose EKF over one robot's encoders and IMU, stepped once per control period.

    ``params``: the robot's geometry (l1, l2, r) and, for the model prediction, its dynamics;
    ``period``: the nominal step (s; steps may be longer, e.g. after a dropped cycle);
    ``config``: noise and gates (default ``EstimatorConfig()``). Call ``initialize`` once, then
    ``step`` every cycle, ``fix`` whenever an absolute pose arrives.
    """

    def __init__(self, params: OtbotParams, period: float, config: EstimatorConfig | None = None):
        if not (period > 0 and math.isfinite(period)):
            raise ValueError(f"period must be a finite number of seconds > 0, got {period}")
        self.params = params
        self.period = float(period)
        self.config = cfg = config or EstimatorConfig()
        self.kf = ExtendedKalmanFilter(dim_x=N_STATE, dim_z=3)
        self._l1, self._l2, self._r = params.l1, params.l2, params.r
        self._k = params.r / (2 * params.l2)
        self._prm = params.as_array()
        self.gate = {kind: float(chi2.ppf(cfg.gate_probability, dof)) for kind, dof in UPDATE_KINDS.items()}
        #: variance of an encoder angle's quantization error (rad^2) and one count (rad)
        self._var_q = cfg.encoder_angle_sigma ** 2
        self._count = math.sqrt(12) * cfg.encoder_angle_sigma
        self._R_rates = np.eye(3) * cfg.encoder_rate_sigma ** 2
        self._R_heading = np.array([[2 * self._k ** 2 * self._var_q]])  # the wheels' share, white
        vz = cfg.standstill_angle * self._r / cfg.standstill_window
        az = cfg.standstill_angle / cfg.standstill_window
        self._R_zupt = np.diag([vz ** 2, vz ** 2, az ** 2])
        self._R_gyro = np.array([[cfg.gyro_sigma ** 2]])
        self._R_accel = np.eye(2) * cfg.accel_sigma ** 2
        self._I = np.eye(N_STATE)
        self._zero2 = np.zeros(2)
        self._zero6 = np.zeros(6)
        self.record_innovations = False
        #: (t, kind, nis, accepted) of every update attempted while ``record_innovations`` is on.
        self.innovations: list[tuple[float, str, float, bool]] = []
        self._t: float | None = None
        self._estimate: Estimate | None = None

    # ------------------------------------------------------------------ set-up
    def initialize(self, t: float, pose, joint_pos, twist=(0.0, 0.0, 0.0), pose_std=None, *,
                   imu_accel=None, imu_gyro=None) -> Estimate:
        """Start at time t (s) from ``pose`` (x, y m, alpha rad) with std ``pose_std`` (default 1 mm,
        1 mrad), ``twist`` (std 0.01 m/s, rad/s) and the joint angles ``joint_pos`` (3,) rad read then
        (they anchor the wheel heading). ``imu_accel``/``imu_gyro`` (3,) in B'': a reading taken at t."""
        pose = np.asarray(pose, dtype=float).reshape(3)
        twist = np.asarray(twist, dtype=float).reshape(3)
        phi = np.asarray(joint_pos, dtype=float).reshape(3)
        std = np.asarray(INITIAL_POSE_STD if pose_std is None else pose_std, dtype=float).reshape(3)
        if not (math.isfinite(t) and _finite(pose, twist, phi, std)):
            raise EstimatorFault("initialize: time, pose, twist, joint angles and pose std must be finite")
        if np.any(std < 0):
            raise ValueError(f"pose_std must be >= 0, got {std}")
        cfg = self.config
        x = np.zeros(N_STATE)
        x[:3], x[3:6] = pose, twist
        x[KAPPA] = pose[2] - self._wheel_heading(phi)
        P = np.zeros((N_STATE, N_STATE))
        P[[X, Y, A], [X, Y, A]] = np.maximum(std, 1e-9) ** 2
        P[[VX, VY, VA], [VX, VY, VA]] = np.square(INITIAL_TWIST_STD)
        P[BG, BG] = cfg.gyro_bias_std ** 2
        P[BAX, BAX] = P[BAY, BAY] = cfg.accel_bias_std ** 2
        # kappa is set from the first (quantized) reading: its error is alpha's plus that reading's
        P[EP, EP] = P[KAPPA, EP] = P[EP, KAPPA] = self._var_q
        P[KAPPA, KAPPA] = P[A, A] + self._var_q + self._R_heading[0, 0]
        P[A, KAPPA] = P[KAPPA, A] = P[A, A]
        self.kf.x = x
        self.kf.P = P
        self._t = float(t)
        self._phi_p = float(phi[2])
        self._still_ref = phi.copy()
        self._still_since = float(t)
        self._acc = self._gyro = None          # newest IMU reading (B'')
        self._acc_held = self._gyro_held = None  # reading that drives the current step
        self._imu_t = None
        self._imu_period = self.period
        self._torque = None
        self.rejected = dict.fromkeys(UPDATE_KINDS, 0)
        self.updates = dict.fromkeys(UPDATE_KINDS, 0)
        self._nis = dict.fromkeys(UPDATE_KINDS, math.nan)
        self._standstill = False
        self._heading_streak = 0
        if imu_accel is not None or imu_gyro is not None:
            self._take_imu(float(t), imu_accel, imu_gyro)
        self._estimate = self._make_estimate()
        return self._estimate

    @property
    def estimate(self) -> Estimate:
        """The latest estimate."""
        if self._estimate is None:
            raise EstimatorFault("the estimator was not initialized")
        return self._estimate

    @property
    def prediction(self) -> str:
        """What drives the current prediction: ``imu`` or ``model``."""
        return "imu" if self.config.prediction == "imu" and self._acc_held is not None else "model"

    # ------------------------------------------------------------------ one cycle
    def step(self, t: float, joint_pos, joint_vel, imu_accel=None, imu_gyro=None, torque=None) -> Estimate:
        """Predict from the previous step's time to t, then update with the sensors sampled at t.

        joint_pos/joint_vel (3,) rad, rad/s (phi_r, phi_l, phi_p); imu_accel (3,) m/s^2 and imu_gyro
        (3,) rad/s in B'' -- None when this sample brought no NEW IMU reading; torque (3,) N m: the
        command held on [t_prev, t) (needed by the model prediction). Raises EstimatorFault on NaN/inf
        input, t not increasing, IMU silent longer than ``imu_timeout``, or a non-finite/non-positive
        covariance.
        """
        if self._t is None:
            raise EstimatorFault("step before initialize")
        phi = np.asarray(joint_pos, dtype=float)
        phid = np.asarray(joint_vel, dtype=float)
        if not _finite(t, phi, phid):
            raise EstimatorFault(f"non-finite encoder data at t = {t} s: joint_pos {list(phi)}, "
                                 f"joint_vel {list(phid)}")
        dt = t - self._t
        if not dt > 0:
            raise EstimatorFault(f"time does not increase: t = {t} s after {self._t} s")
        if torque is not None:
            u = np.asarray(torque, dtype=float)
            if not _finite(u):
                raise EstimatorFault(f"non-finite torque at t = {t} s: {list(u)}")
            self._torque = u
        nis = self._nis
        for kind in nis:
            nis[kind] = math.nan
        # the reading of the previous sample drives [t_prev, t); the new one is kept for the next step
        acc_prev, gyro_prev = self._acc, self._gyro
        if imu_accel is not None or imu_gyro is not None:
            self._take_imu(t, imu_accel, imu_gyro)
        elif self._imu_t is not None and t - self._imu_t > self.config.imu_timeout:
            raise EstimatorFault(f"IMU silent for {t - self._imu_t:.3f} s (timeout {self.config.imu_timeout} s) "
                                 f"at t = {t} s")
        self._acc_held = acc_prev if acc_prev is not None else self._acc
        self._gyro_held = gyro_prev if gyro_prev is not None else self._gyro
        new_gyro = imu_gyro is not None
        if self.prediction == "imu":
            self._predict_imu(dt, new_gyro)
        else:
            self._predict_model(dt, phi)
        self._renew_quantization(float(phi[2]), dt)
        self._t = float(t)
        self._phi_p = float(phi[2])
        self._update_encoders(t, phi, phid)
        self._standstill = self._detect_standstill(t, phi)
        if self._standstill:
            self._update_zupt(t)
        if self.prediction == "model" and new_gyro:
            self._update_gyro(t)
        self._check_health(t)
        self._estimate = self._make_estimate()
        return self._estimate

    def fix(self, t: float, pose, cov) -> bool:
        """Absolute pose fix (landmark, motion capture) at the current step's time: pose (3,) x, y (m),
        alpha (rad, any branch: the residual is wrapped), cov (3, 3). Returns whether the gate accepted it."""
        if self._t is None:
            raise EstimatorFault("fix before initialize")
        if abs(t - self._t) > 1e-9 * max(1.0, abs(t)):
            raise EstimatorFault(f"fix at t = {t} s, but the estimate is at t = {self._t} s: "
                                 f"a fix applies at the current step's time")
        z = np.asarray(pose, dtype=float).reshape(3)
        Rf = np.asarray(cov, dtype=float).reshape(3, 3)
        if not _finite(z, Rf):
            raise EstimatorFault(f"non-finite pose fix at t = {t} s")
        if not np.allclose(Rf, Rf.T) or np.linalg.eigvalsh(Rf).min() <= 0:
            raise ValueError("fix covariance must be symmetric positive definite (m^2, rad^2)")
        x = self.kf.x
        nu = z - x[:3]
        nu[2] = wrap_angle(nu[2])
        H = np.zeros((3, N_STATE))
        H[0, X] = H[1, Y] = H[2, A] = 1.0
        ok = self._update("fix", t, nu, H, Rf)
        self._check_health(t)
        self._estimate = self._make_estimate()
        return ok

    # ------------------------------------------------------------------ helpers
    def _wheel_heading(self, phi) -> float:
        """r/(2 l2)(phi_r - phi_l) + phi_p (rad): alpha less the holonomic constant."""
        return self._k * (phi[0] - phi[1]) + phi[2]

    def _take_imu(self, t: float, acc, gyro) -> None:
        if acc is None or gyro is None:
            raise EstimatorFault(f"IMU sample at t = {t} s lacks {'accel' if acc is None else 'gyro'}")
        a = np.asarray(acc, dtype=float)
        g = np.asarray(gyro, dtype=float)
        if not _finite(a, g):
            raise EstimatorFault(f"non-finite IMU data at t = {t} s: accel {list(a)}, gyro {list(g)}")
        if self._imu_t is not None and t > self._imu_t:
            self._imu_period = t - self._imu_t
        self._imu_t = t
        self._acc, self._gyro = a, g

    def _predict_imu(self, dt: float, new_gyro: bool) -> None:
        """Strapdown step: x_dd, y_dd = R(alpha) (f'' - b_a) under the held reading; alpha_dot = the
        newest gyro reading less b_g (kept from the last update while no new reading arrives), alpha
        integrated by the trapezoid between the two rates."""
        kf, cfg = self.kf, self.config
        x, P = kf.x, kf.P
        a = self._acc_held
        bg = x[BG]
        va0 = x[VA]
        va1 = self._gyro[2] - bg if new_gyro else va0
        am = x[A] + 0.25 * (va0 + va1) * dt  # heading at mid-step
        c, s = math.cos(am), math.sin(am)
        fx, fy = a[0] - x[BAX], a[1] - x[BAY]
        ax, ay = c * fx - s * fy, s * fx + c * fy
        dax, day = -ay, ax  # d(R f)/d alpha
        h2 = 0.5 * dt * dt
        F = self._I.copy()
        F[X, VX] = F[Y, VY] = dt
        F[X, A], F[Y, A] = h2 * dax, h2 * day
        F[VX, A], F[VY, A] = dt * dax, dt * day
        F[X, BAX], F[X, BAY], F[Y, BAX], F[Y, BAY] = -h2 * c, h2 * s, -h2 * s, -h2 * c
        F[VX, BAX], F[VX, BAY], F[VY, BAX], F[VY, BAY] = -dt * c, dt * s, -dt * s, -dt * c
        x[X] += x[VX] * dt + h2 * ax
        x[Y] += x[VY] * dt + h2 * ay
        x[VX] += ax * dt
        x[VY] += ay * dt
        # white noise of one IMU sample, spread over the steps it is held for
        hold = max(self._imu_period, dt)
        qv = cfg.accel_sigma ** 2 * dt * hold
        Q = np.zeros((N_STATE, N_STATE))
        Q[X, X] = Q[Y, Y] = qv * 0.25 * dt * dt
        Q[X, VX] = Q[VX, X] = Q[Y, VY] = Q[VY, Y] = qv * 0.5 * dt
        Q[VX, VX] = Q[VY, VY] = qv
        if new_gyro:
            F[A, VA] = F[A, BG] = 0.5 * dt
            F[A, BG] = -0.5 * dt
            F[VA, VA] = 0.0
            F[VA, BG] = -1.0
            g2 = cfg.gyro_sigma ** 2
            Q[A, A] = 0.25 * dt * dt * g2
            Q[A, VA] = Q[VA, A] = 0.5 * dt * g2
            Q[VA, VA] = g2
            x[A] += 0.5 * (va0 + va1) * dt
            x[VA] = va1
        else:
            F[A, VA] = dt
            x[A] += va0 * dt
        self._bias_noise(Q, dt)
        kf.F, kf.Q = F, Q
        kf.P = F @ P @ F.T + Q
        kf.x_prior = x.copy()
        kf.P_prior = kf.P.copy()

    def _renew_quantization(self, phi_p: float, dt: float) -> None:
        """e_p renews (a fresh draw) when the pivot reading changes; while the reading stays, the error
        moves only by the pivot's own motion under one count (estimated from the twist)."""
        P = self.kf.P
        if phi_p != self._phi_p:
            P[EP, :] = 0.0
            P[:, EP] = 0.0
            P[EP, EP] = self._var_q
            self.kf.x[EP] = 0.0
            return
        x = self.kf.x
        th = x[A] - phi_p
        rate = (math.sin(th) * x[VX] - math.cos(th) * x[VY]) / self._l1 + x[VA]  # phi_p dot (M_IIK row 3)
        P[EP, EP] += min(self._var_q, (rate * dt) ** 2)

    def _bias_noise(self, Q: np.ndarray, dt: float) -> None:
        cfg = self.config
        Q[BG, BG] = cfg.gyro_bias_walk ** 2 * dt
        Q[BAX, BAX] = Q[BAY, BAY] = cfg.accel_bias_walk ** 2 * dt

    def _model_acceleration(self, s: np.ndarray, phi_p: float, u: np.ndarray) -> np.ndarray:
        """p_dd (3,) of the paper's model at state s (pose, twist) and pivot angle phi_p under u."""
        xs = np.empty(12)
        xs[0:3] = s[0:3]
        xs[3] = xs[4] = 0.0
        xs[5] = phi_p
        xs[6:9] = s[3:6]
        th = s[2] - phi_p
        c, si = math.cos(th), math.sin(th)
        l1, l2, r = self._l1, self._l2, self._r
        vx, vy, va = s[3], s[4], s[5]
        xs[9] = ((l1 * c - l2 * si) * vx + (l2 * c + l1 * si) * vy) / (r * l1)
        xs[10] = ((l1 * c + l2 * si) * vx + (-l2 * c + l1 * si) * vy) / (r * l1)
        xs[11] = (si * vx - c * vy) / l1 + va
        return compiled.accelerations(xs, u, self._zero2, self._zero6, self._prm)[:3]

    def _model_jacobian(self, s: np.ndarray, phi_p: float, u: np.ndarray):
        """(p_dd (3,), d p_dd / d (alpha, x_dot, y_dot, alpha_dot) (3, 4)) by forward differences."""
        f0 = self._model_acceleration(s, phi_p, u)
        J = np.empty((3, 4))
        for j, (i, h) in enumerate(((A, 1e-6), (VX, 1e-6), (VY, 1e-6), (VA, 1e-6))):
            sp = s.copy()
            sp[i] += h
            J[:, j] = (self._model_acceleration(sp, phi_p, u) - f0) / h
        return f0, J

    def _predict_model(self, dt: float, phi) -> None:
        """Dynamic-model step: p_dd from the multiplier-free dynamics under the held torque."""
        if self._torque is None:
            raise EstimatorFault("the model prediction needs the commanded torque (none given yet)")
        kf, cfg = self.kf, self.config
        u = self._torque
        if self._acc_held is not None and self._gyro_held is not None:
            self._update_accel(self._t, self._acc_held, u)  # reading at t_prev under the same command
        x, P = kf.x, kf.P
        f0, J = self._model_jacobian(x, self._phi_p, u)
        h2 = 0.5 * dt * dt
        F = self._I.copy()
        F[X, VX] = F[Y, VY] = F[A, VA] = dt
        cols = [A, VX, VY, VA]
        F[np.ix_([X, Y, A], cols)] += h2 * J
        F[np.ix_([VX, VY, VA], cols)] += dt * J
        x[0:3] += x[3:6] * dt + h2 * f0
        x[3:6] += f0 * dt
        Q = np.zeros((N_STATE, N_STATE))
        for (p, v), q in (((X, VX), cfg.model_accel_density), ((Y, VY), cfg.model_accel_density),
                          ((A, VA), cfg.model_angular_density)):
            q2 = q * q
            Q[p, p] = q2 * dt ** 3 / 3
            Q[p, v] = Q[v, p] = q2 * dt * dt / 2
            Q[v, v] = q2 * dt
        self._bias_noise(Q, dt)
        kf.F, kf.Q = F, Q
        kf.P = F @ P @ F.T + Q
        kf.x_prior = x.copy()
        kf.P_prior = kf.P.copy()

    def _update(self, kind: str, t: float, nu: np.ndarray, H: np.ndarray, R: np.ndarray,
                gate: bool = True) -> bool:
        """Gated Kalman update with innovation nu; True when accepted. The accelerometer biases are
        *considered* (Schmidt-Kalman: their uncertainty enters S, their value is not updated) except by
        the zero-velocity update: while the robot moves, wheel slip looks like an accelerometer bias."""
        kf = self.kf
        P = kf.P
        PHt = P @ H.T
        S = H @ PHt + R
        Sinv = np.linalg.inv(S)
        d2 = float(nu @ Sinv @ nu)
        self._nis[kind] = d2
        ok = d2 <= self.gate[kind] or not gate
        if self.record_innovations:
            self.innovations.append((t, kind, d2, ok))
        if not ok:
            self.rejected[kind] += 1
            return False
        K = PHt @ Sinv
        if kind != "zupt":
            K[BAX:BAY + 1] = 0.0
        kf.x += K @ nu
        A = K @ PHt.T
        P = P - A - A.T + K @ S @ K.T
        kf.P = 0.5 * (P + P.T)
        kf.y, kf.S, kf.SI, kf.K = nu, S, Sinv, K
        kf.x_post = kf.x.copy()
        kf.P_post = kf.P.copy()
        self.updates[kind] += 1
        return True

    def _update_encoders(self, t: float, phi: np.ndarray, phid: np.ndarray) -> None:
        """Joint rates through M_IIK, then the wheel heading (skipped while the rates are rejected: the
        wheels slip). A heading rejected twice in a row with the rates accepted means the slip has moved
        the holonomic constant: kappa's variance grows by the innovation squared and the wheel heading
        re-anchors on alpha."""
        x = self.kf.x
        th = x[A] - phi[2]
        c, s = math.cos(th), math.sin(th)
        l1, l2, r = self._l1, self._l2, self._r
        n = 1.0 / (r * l1)
        M = n * np.array([[l1 * c - l2 * s, l2 * c + l1 * s, 0.0],
                          [l1 * c + l2 * s, -l2 * c + l1 * s, 0.0],
                          [r * s, -r * c, r * l1]])
        dM = n * np.array([[-l1 * s - l2 * c, -l2 * s + l1 * c],
                           [-l1 * s + l2 * c, l2 * s + l1 * c],
                           [r * c, r * s]])
        v = x[3:6]
        H = np.zeros((3, N_STATE))
        H[:, 3:6] = M
        H[:, A] = dM @ v[:2]
        if not self._update("encoders", t, phid - M @ v, H, self._R_rates):
            self._heading_streak = 0
            return
        Hh = np.zeros((1, N_STATE))
        Hh[0, A] = Hh[0, EP] = 1.0
        Hh[0, KAPPA] = -1.0
        nu = np.array([wrap_angle(self._wheel_heading(phi) - (x[A] - x[KAPPA] + x[EP]))])
        if self._update("heading", t, nu, Hh, self._R_heading):
            self._heading_streak = 0
            return
        self._heading_streak += 1
        if self._heading_streak >= 2:
            self.kf.P[KAPPA, KAPPA] += nu[0] * nu[0]
            self._heading_streak = 0
            self._update("heading", t, nu, Hh, self._R_heading)

    def _detect_standstill(self, t: float, phi: np.ndarray) -> bool:
        cfg = self.config
        if float(np.max(np.abs(phi - self._still_ref))) > cfg.standstill_angle:
            self._still_ref = phi.copy()
            self._still_since = t
            return False
        if t - self._still_since < cfg.standstill_window - 1e-9:
            return False
        if self._gyro is not None:
            x, P = self.kf.x, self.kf.P
            tol = 5.0 * math.sqrt(cfg.gyro_sigma ** 2 + P[BG, BG])
            if abs(self._gyro[2] - x[BG]) > tol:
                return False
        return True

    def _update_zupt(self, t: float) -> None:
        H = np.zeros((3, N_STATE))
        H[0, VX] = H[1, VY] = H[2, VA] = 1.0
        self._update("zupt", t, -self.kf.x[3:6], H, self._R_zupt)

    def _update_gyro(self, t: float) -> None:
        x = self.kf.x
        H = np.zeros((1, N_STATE))
        H[0, VA] = H[0, BG] = 1.0
        nu = np.array([self._gyro[2] - x[VA] - x[BG]])
        self._update("gyro", t, nu, H, self._R_gyro)

    def _update_accel(self, t: float, acc: np.ndarray, u: np.ndarray) -> None:
        """The accelerometer reading at t (under u) as a measurement of R(alpha)^T p_dd + b_a."""
        x = self.kf.x
        f0, J = self._model_jacobian(x, self._phi_p, u)
        a = x[A]
        c, s = math.cos(a), math.sin(a)
        RT = np.array([[c, s], [-s, c]])
        dRT = np.array([[-s, c], [-c, -s]])
        H = np.zeros((2, N_STATE))
        cols = [A, VX, VY, VA]
        H[:, cols] = RT @ J[:2]
        H[:, A] += dRT @ f0[:2]
        H[0, BAX] = H[1, BAY] = 1.0
        nu = acc[:2] - (RT @ f0[:2] + x[[BAX, BAY]])
        self._update("accel", t, nu, H, self._R_accel)

    def _check_health(self, t: float) -> None:
        x, P = self.kf.x, self.kf.P
        d = P.diagonal()
        if not (math.isfinite(float(x.sum())) and math.isfinite(float(P.sum())) and d.min() > 0):
            raise EstimatorFault(f"the filter diverged at t = {t} s: non-finite state or covariance "
                                 f"(min variance {d.min():.3g})")

    def _make_estimate(self) -> Estimate:
        x, P = self.kf.x, self.kf.P
        return Estimate(t=self._t, pose=x[0:3].copy(), twist=x[3:6].copy(), std=np.sqrt(P.diagonal()[:6]),
                        cov=P.copy(), gyro_bias=float(x[BG]), standstill=self._standstill, nis=dict(self._nis),
                        rejected=dict(self.rejected), updates=dict(self.updates), accel_bias=x[7:9].copy())
