"""Extended Kalman filter for the platform pose and twist of Otbot (filterpy ``ExtendedKalmanFilter``).

State (14,), ground frame B unless said otherwise::

    0 x, 1 y (m)            pivot P               6 b_g (rad/s)          gyro z bias
    2 alpha (rad)           platform heading      7 b_ax, 8 b_ay (m/s^2) accelerometer bias in B''
    3 x_dot, 4 y_dot (m/s)                        9 kappa (rad)          wheel-heading offset
    5 alpha_dot (rad/s)                           10 e_p (rad)           pivot encoder quantization error
                                                  11 d (rad/s^2)         alpha_dd the model does not know
                                                  12 n_ax, 13 n_ay       noise of the driving accelerometer
                                                     (m/s^2)             reading, B''

The filterpy object ``kf`` holds the state ``kf.x``, its covariance ``kf.P`` and the last step's
transition ``kf.F`` and process noise ``kf.Q``. Its generic predict/update are not used: they neither
gate nor wrap angles, and numpy's small-matrix overhead makes them slow; the prediction and the gated
update are compiled kernels (``otbot_hw.estimation.kernels``) working on that state in place
(``benchmarks/estimation.py`` measures both).

Prediction (``EstimatorConfig.prediction``; the IMU was chosen by measurement, docs/estimation.md):

* ``imu``: the specific force in B'' less its bias, rotated by alpha, drives x_dot, y_dot. The reading
  taken at t_{k-1} (just after it, under the command of [t_{k-1}, t_k)) drives the step to t_k; a reading
  held over several steps (an IMU slower than the loop) keeps driving them, corrected by the acceleration
  change the paper's model gives for the torque change since the reading. The reading's own noise is
  the state (n_ax, n_ay), drawn afresh with each new reading and constant while it is held: white
  process noise in its place let a 1 kHz loop average ten copies of one noisy reading against the
  wheel rates (the twist overconfident by 2-3x). The yaw rate is no IMU input: alpha_dd comes from the paper's model under the commanded
  torque (``kernels.yaw_acceleration``), with the unknown horizontal force at the pivot eliminated by the
  accelerometer's measured acceleration (the model is linear in it), plus the state d -- the torques
  the model does not know (friction, torque-gain errors), a random walk -- and white noise
  (``model_angular_density``); the gyro is a measurement of alpha_dot + b_g. A gyro reading fed as the
  rate itself put its white noise (13.7 mrad/s per sample) into alpha_dot unfiltered, and the control law
  turned it into platform motion (docs/estimation.md, "In the loop").
* ``model``: the paper's multiplier-free dynamics (``otbot_hw.model.compiled``) under the commanded
  torque drive the twist, with white acceleration noise (alpha_dd also d); the IMU becomes a measurement
  (accelerometer of R(alpha)^T p_dd + b_a at the previous sample, under the same command). Also used
  while no IMU reading has arrived.

Updates, each gated by its squared Mahalanobis distance (chi-square at ``gate_probability``); a
rejected one is counted and not applied:

* ``encoders`` (3): the joint rates phi_dot = M_IIK(alpha - phi_p) p_dot (paper §2.3.2; phi_p read from
  the pivot encoder).
* ``heading`` (1): the wheel heading r/(2 l2)(phi_r - phi_l) + phi_p = alpha - kappa + e_p, the paper's
  holonomic constraint, whose constant kappa only wheel slip moves. Skipped while the joint rates are
  rejected (the wheels slip). Rejected for ``REANCHOR_AFTER`` (two samples at 100 Hz) with the rates
  accepted, the slip has moved the constant: kappa's variance grows by the innovation squared, and the
  wheel heading re-anchors on alpha.
  The pivot's quantization error e_p is a state, not white noise (``pivot_quantization``). Floored
  readings are first moved to the centre of their count (``encoder_quantization``), so the error is
  zero-mean. The wheels' share of the heading's quantization error renews with every count they roll
  and is taken as white. e_p also enters the chassis heading theta = alpha - phi_p of the joint-rate update.
* ``zupt`` (3): twist = 0 at a standstill (``standstill``: joints and gyro still).
* ``gyro`` (1): alpha_dot + b_g, at every new IMU reading. ``accel`` (2): the accelerometer as a
  measurement (``model`` prediction only).
* ``fix`` (3): an absolute pose with its covariance (``PoseEKF.fix``), alpha residual wrapped; the third
  rejected in a row re-anchors the pose on it (``FIX_REANCHOR_AFTER``: the gate must not starve the filter).

alpha stays continuous (never wrapped to +-pi, like the recordings); every angle *residual* is wrapped.
Biases: the gyro z bias is estimated (the wheel heading and joint rates observe it while moving, the
zero-velocity update at rest). The accelerometer x, y biases are observable only against the wheels'
velocity -- which wheel slip corrupts in the same way -- so they are estimated at standstill only and
*considered* otherwise (Schmidt-Kalman: their uncertainty counts, their value is not moved by a moving
robot's wheels). Not estimated: the gyro x, y and accelerometer z biases, which a planar estimator on
flat ground never uses.

Parts: ``ekf_state`` (state layout, ``Estimate``, ``EstimatorFault``), ``model_prediction`` (the
dynamic-model prediction), ``gyro_update`` (the gyro's update and the walk adaptation it drives),
``pivot_quantization`` (e_p), ``standstill`` (the zero-velocity detector), ``kernels`` (the compiled
hot path) and ``imu_cycle`` (the IMU-predicted cycle's prediction and encoder updates as one compiled
call). This module is the filter: set-up, one cycle's prediction and gated updates in order, the
heading's re-anchoring and the health checks.

Length: about 440 lines, most of them this docstring (the filter's model, in one place) and the cycle's
steps, which read in order here; splitting them further would scatter one sequence.
"""
from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import chi2

from otbot_hw.estimation import imu_cycle as cyc
from otbot_hw.estimation import kernels
from otbot_hw.estimation.config import EstimatorConfig
from otbot_hw.estimation.ekf_state import (  # noqa: F401 (the state layout and records, importable from here)
    A, BAX, BAY, BG, DA, EP, INITIAL_POSE_STD, INITIAL_TWIST_STD, KAPPA, N_STATE, NAX, NAY, REANCHOR_AFTER, STATE_NAMES,
    UPDATE_KINDS, VA, VX, VY, X, Y, Estimate, EstimatorFault, check_vector)
from otbot_hw.estimation.gyro_update import WALK_SCALE_MAX, GyroUpdate  # noqa: F401 (importable from here)
from otbot_hw.estimation.model_prediction import ModelPrediction
from otbot_hw.estimation.pivot_quantization import PivotQuantization
from otbot_hw.estimation.standstill import StandstillDetector
from otbot_hw.model.angles import wrap_angle  # noqa: F401  (the one angle wrap; importable from here)
from otbot_hw.params import OtbotParams

#: This many absolute fixes rejected in a row: the state, not the fixes, is wrong (the gate would reject
#: every later one too); the last of them re-anchors the pose on itself.
FIX_REANCHOR_AFTER = 3


class PoseEKF(ModelPrediction, GyroUpdate):
    """Pose EKF over one robot's encoders and IMU, stepped once per control period.

    ``params``: the robot's geometry (l1, l2, r) and, for the model prediction, its dynamics;
    ``period``: the nominal step (s; steps may be longer, e.g. after a dropped cycle);
    ``config``: noise and gates (default ``EstimatorConfig()``). Call ``initialize`` once, then
    ``step`` every cycle, ``fix`` whenever an absolute pose arrives. ``record_innovations = True``
    keeps (t, kind, nis, accepted) of every attempted update in ``innovations``.
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
        self._xs = np.empty(12)  # the model state the dynamic-model prediction evaluates at
        self.gate = {kind: float(chi2.ppf(cfg.gate_probability, dof)) for kind, dof in UPDATE_KINDS.items()}
        self.pivot = PivotQuantization(cfg.pivot_angle_sigma, params.l1)  # e_p: the pivot reading's error
        self._var_q = self.pivot.var
        self.standstill_detector = StandstillDetector(cfg)
        #: added to the angle readings: half a count for floored readings (the count's centre)
        half = 0.5 * math.sqrt(12) if cfg.encoder_quantization == "floor" else 0.0
        self._half_count = half * np.array([cfg.wheel_angle_sigma, cfg.wheel_angle_sigma, cfg.pivot_angle_sigma])
        self._R_rates = np.eye(3) * cfg.encoder_rate_sigma ** 2
        self._R_heading = np.array([[2 * self._k ** 2 * cfg.wheel_angle_sigma ** 2]])  # the wheels' share, white
        vz = cfg.standstill_angle * self._r / cfg.standstill_window
        az = cfg.standstill_angle / cfg.standstill_window
        self._R_zupt = np.diag([vz ** 2, vz ** 2, az ** 2])
        self._R_gyro = np.array([[cfg.gyro_sigma ** 2]])
        self._R_accel = np.eye(2) * cfg.accel_sigma ** 2
        self._var = (cfg.accel_sigma ** 2, cfg.gyro_sigma ** 2, cfg.gyro_bias_walk ** 2, cfg.accel_bias_walk ** 2)
        self._var_alpha_dd = cfg.model_angular_density ** 2
        self._var_da = cfg.angular_disturbance_walk ** 2
        self._nis_bounds: dict[float, float] = {}  # averaged-NIS bound per averaging weight (adaptation)
        # work arrays of the hot path
        self.kf.F = np.eye(N_STATE)
        self.kf.Q = np.zeros((N_STATE, N_STATE))
        self._H_rates = np.zeros((3, N_STATE))
        self._nu3 = np.zeros(3)
        self._H_heading = np.zeros((1, N_STATE))
        self._H_heading[0, A] = self._H_heading[0, EP] = 1.0
        self._H_heading[0, KAPPA] = -1.0
        self._H_zupt = np.zeros((3, N_STATE))
        self._H_zupt[0, VX] = self._H_zupt[1, VY] = self._H_zupt[2, VA] = 1.0
        self._H_fix = np.zeros((3, N_STATE))
        self._H_fix[0, X] = self._H_fix[1, Y] = self._H_fix[2, A] = 1.0
        self._H_gyro = np.zeros((1, N_STATE))
        self._H_gyro[0, VA] = self._H_gyro[0, BG] = 1.0
        self._zero2 = np.zeros(2)
        self._zero6 = np.zeros(6)
        self._zero3 = np.zeros(3)
        self._nu1 = np.zeros(1)
        self._res = np.zeros(cyc.N_RESULTS)
        self._s = s = np.zeros(cyc.N_SCALARS)  # imu_cycle's scalars: the constant ones here, the rest per step
        s[cyc.S_VAR_ACC], s[cyc.S_VAR_ALPHA_DD] = self._var[0], self._var_alpha_dd
        s[cyc.S_BG_WALK2], s[cyc.S_BA_WALK2] = self._var[2], self._var[3]
        s[cyc.S_L1], s[cyc.S_L2], s[cyc.S_R], s[cyc.S_K] = self._l1, self._l2, self._r, self._k
        s[cyc.S_COUNT], s[cyc.S_VAR_Q] = self.pivot.count, self.pivot.var
        self.record_innovations = False
        self.innovations: list[tuple[float, str, float, bool]] = []
        self._t: float | None = None
        self._estimate: Estimate | None = None

    # ------------------------------------------------------------------ set-up
    def initialize(self, t: float, pose, joint_pos, twist=(0.0, 0.0, 0.0), pose_std=None, *,
                   imu_accel=None, imu_gyro=None) -> Estimate:
        """Start at time t (s) from ``pose`` (x, y m, alpha rad) with std ``pose_std`` (default: exact,
        the start defines the frame), ``twist`` (std 0.01 m/s, rad/s) and the joint angles ``joint_pos``
        (3,) rad read then (they anchor the wheel heading). ``imu_accel``/``imu_gyro`` (3,) in B'': a
        reading taken at t (it drives the first step)."""
        if not math.isfinite(t):
            raise EstimatorFault(f"non-finite start time {t}")
        pose = check_vector(pose, 3, "pose", t)
        twist = check_vector(twist, 3, "twist", t)
        phi = check_vector(joint_pos, 3, "joint_pos", t) + self._half_count
        std = check_vector(INITIAL_POSE_STD if pose_std is None else pose_std, 3, "pose_std", t)
        if np.any(std < 0):
            raise ValueError(f"pose_std must be >= 0, got {std.tolist()}")
        cfg = self.config
        x = np.zeros(N_STATE)
        x[:3], x[3:6] = pose, twist
        x[KAPPA] = pose[2] - self._wheel_heading(phi)
        P = np.zeros((N_STATE, N_STATE))
        P[[X, Y, A], [X, Y, A]] = np.maximum(std, 1e-9) ** 2
        P[[VX, VY, VA], [VX, VY, VA]] = np.square(INITIAL_TWIST_STD)
        P[BG, BG] = cfg.gyro_bias_std ** 2
        P[BAX, BAX] = P[BAY, BAY] = cfg.accel_bias_std ** 2
        P[DA, DA] = cfg.angular_disturbance_std ** 2
        P[NAX, NAX] = P[NAY, NAY] = cfg.accel_sigma ** 2
        # kappa comes from the first (quantized) reading: its error is alpha's plus that reading's
        P[EP, EP] = P[KAPPA, EP] = P[EP, KAPPA] = self._var_q
        P[KAPPA, KAPPA] = P[A, A] + self._var_q + self._R_heading[0, 0]
        P[A, KAPPA] = P[KAPPA, A] = P[A, A]
        self.kf.x = x
        self.kf.P = P
        self._t = float(t)
        self._phi_p = float(phi[2])
        self.standstill_detector.reset(t, phi)
        self._acc = self._gyro = None            # newest IMU reading (B'')
        self._acc_t = self._acc_u = None         # its time, and the torque it was taken under
        self._acc_held = self._gyro_held = None  # the reading that drives the current step
        self._acc_noise_of = None                # the reading whose noise the states NAX, NAY are
        self._imu_t = None
        self._torque = None
        self.rejected = dict.fromkeys(UPDATE_KINDS, 0)
        self.updates = dict.fromkeys(UPDATE_KINDS, 0)
        self._nis = dict.fromkeys(UPDATE_KINDS, math.nan)
        self._standstill = False
        self._heading_off_since = None  # since when the wheel heading disagrees (rates accepted)
        self._gyro_off_since = None     # since when the gyro is rejected
        self._kappa_suspect = False     # a fix re-anchored alpha since the wheel heading last agreed
        self._fixes_rejected = 0        # absolute fixes rejected in a row
        self._gyro_nis_avg = 1.0        # the gyro's NIS averaged over walk_adaptation_window (expectation 1)
        self._gyro_disagrees = False    # that average is above its bound (the walk adapting)
        self._gyro_t = None             # time of the last gyro update
        self.walk_scale = 1.0           # factor on the variance of d's walk (adaptation, >= 1)
        self._t_prev = float(t)
        self.innovations = []
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
        command held on [t_prev, t) (the model prediction needs it; the IMU prediction uses it only to
        correct a reading held over several steps).
        Raises EstimatorFault on NaN/inf input, t not increasing, IMU silent longer than
        ``imu_timeout``, or a non-finite/non-positive covariance.
        """
        if self._t is None:
            raise EstimatorFault("step before initialize")
        if not math.isfinite(t):
            raise EstimatorFault(f"non-finite sample time {t}")
        if cyc.plain_vectors(joint_pos, joint_vel, joint_vel if torque is None else torque):  # the loop's case
            phi, phid = joint_pos + self._half_count, joint_vel
            if torque is not None:
                self._torque = torque
        else:  # anything else: converted, or the error that names it
            phi = check_vector(joint_pos, 3, "joint_pos", t) + self._half_count
            phid = check_vector(joint_vel, 3, "joint_vel", t)
        dt = t - self._t
        if not dt > 0:
            raise EstimatorFault(f"time does not increase: t = {t} s after {self._t} s")
        if torque is not None and self._torque is not torque:
            self._torque = check_vector(torque, 3, "torque", t)
        nis = self._nis
        for kind in nis:
            nis[kind] = math.nan
        # the previous sample's reading drives [t_prev, t); the new one is kept for the next step
        acc_prev, gyro_prev = self._acc, self._gyro
        held_t, held_u = self._acc_t, self._acc_u
        new_gyro = imu_gyro is not None
        if imu_accel is not None or new_gyro:
            self._take_imu(t, imu_accel, imu_gyro)
        elif self._imu_t is not None and t - self._imu_t > self.config.imu_timeout:
            raise EstimatorFault(f"IMU silent for {t - self._imu_t:.3f} s (timeout {self.config.imu_timeout} s) "
                                 f"at t = {t} s")
        self._acc_held = acc_prev if acc_prev is not None else self._acc
        self._gyro_held = gyro_prev if gyro_prev is not None else self._gyro
        if self.prediction == "imu":  # the common path: prediction and both encoder updates in one compiled call
            res = self._imu_cycle(dt, acc_prev, held_t, held_u, phi, phid)
        else:
            res = None
            # the pivot's motion under its reading, trapezoid: half with the rates before the prediction ...
            self.pivot.half_step(self.kf.x, self.kf.P, self._phi_p, dt)
            self._predict_model(dt)
        if self.walk_scale > 1.0:  # the adapted walk relaxes back to the configured one
            self.walk_scale = 1.0 + (self.walk_scale - 1.0) * math.exp(-dt / self.config.walk_adaptation_decay)
        if res is None:  # ... and half with the rates after it
            jump = self.pivot.motion(self.kf.x, self.kf.P, self._phi_p, float(phi[2]), dt)
        else:
            jump = float(res[cyc.R_JUMP])
        self._t_prev, self._t = self._t, float(t)
        self._phi_p = float(phi[2])
        if res is None:
            self._update_encoders(t, phi, phid)
        else:
            self._after_encoders(t, res)
        self._standstill = self.standstill_detector.still(
            t, phi, None if self._gyro is None else self._gyro[2], self.kf.x[BG], self.kf.P[BG, BG])
        touched = res is None or res[cyc.R_OK_HEAD] == 0.0  # updates after the kernel's health check
        if self._standstill:
            self._update("zupt", t, -self.kf.x[3:6], self._H_zupt, self._R_zupt)
            touched = True
        if new_gyro:
            self._update_gyro(t)
            touched = True
        touched = self.pivot.constrain(self.kf.x, self.kf.P, jump, self.config.gate_probability) or touched
        if touched or res[cyc.R_HEALTHY] == 0.0:
            self._check_health(t)
        self._estimate = self._make_estimate()
        return self._estimate

    def fix(self, t: float, pose, cov) -> bool:
        """Absolute pose fix (landmark, motion capture) at the current step's time: pose (3,) x, y (m),
        alpha (rad, any branch: the residual is wrapped), cov (3, 3) m^2, rad^2. Returns whether the gate
        accepted it (False for the one that re-anchors after ``FIX_REANCHOR_AFTER`` rejections: it is
        applied, and counted as rejected and as an update)."""
        if self._t is None:
            raise EstimatorFault("fix before initialize")
        if abs(t - self._t) > 1e-9 * max(1.0, abs(t)):
            raise EstimatorFault(f"fix at t = {t} s, but the estimate is at t = {self._t} s: "
                                 f"a fix applies at the current step's time")
        z = check_vector(pose, 3, "pose fix", t)
        Rf = np.asarray(cov, dtype=float).reshape(3, 3)
        if not kernels.all_finite(Rf):
            raise EstimatorFault(f"non-finite pose fix covariance at t = {t} s")
        if not np.allclose(Rf, Rf.T) or np.linalg.eigvalsh(Rf).min() <= 0:
            raise ValueError("fix covariance must be symmetric positive definite (m^2, rad^2)")
        nu = z - self.kf.x[:3]
        nu[2] = wrap_angle(nu[2])
        ok = self._update("fix", t, nu, self._H_fix, Rf)
        self._fixes_rejected = 0 if ok else self._fixes_rejected + 1
        if self._fixes_rejected >= FIX_REANCHOR_AFTER:
            # the gate starves the filter: every fix is "an outlier" because the state is off (a wrong
            # re-anchoring, a slip the gate let through). The pose's variance grows by the innovation squared
            # and it re-anchors on the fix; the wheel heading that then disagrees moves kappa, not alpha back
            P = self.kf.P
            for i in (X, Y, A):
                P[i, i] += nu[i] * nu[i]
            self._update("fix", t, nu, self._H_fix, Rf, force=True)
            self._fixes_rejected = 0
            self._kappa_suspect = True
        self._check_health(t)
        self._estimate = self._make_estimate()
        return ok

    # ------------------------------------------------------------------ pieces
    def _wheel_heading(self, phi) -> float:
        """r/(2 l2)(phi_r - phi_l) + phi_p (rad): alpha less the holonomic constant."""
        return self._k * (phi[0] - phi[1]) + phi[2]

    def _take_imu(self, t: float, acc, gyro) -> None:
        if acc is None or gyro is None:
            raise EstimatorFault(f"IMU sample at t = {t} s lacks {'accel' if acc is None else 'gyro'}")
        if cyc.plain_vectors(acc, gyro, acc):
            a, g = acc, gyro
        else:
            a = check_vector(acc, 3, "imu_accel", t)
            g = check_vector(gyro, 3, "imu_gyro", t)
        self._imu_t = t
        self._acc, self._gyro = a, g
        self._acc_t, self._acc_u = t, None  # the torque the reading was taken under is known one step later

    def _update(self, kind: str, t: float, nu: np.ndarray, H: np.ndarray, R: np.ndarray, force: bool = False) -> bool:
        """Gated update (``kernels.gated_update``); the accelerometer biases move only at standstill."""
        d2, ok = kernels.gated_update(self.kf.x, self.kf.P, nu, H, R, self.gate[kind], force, kind == "zupt")
        self._count(kind, t, d2, ok)
        return ok

    def _count(self, kind: str, t: float, d2: float, ok: bool) -> None:
        self._nis[kind] = d2
        if self.record_innovations:
            self.innovations.append((t, kind, d2, ok))
        if ok:
            self.updates[kind] += 1
        else:
            self.rejected[kind] += 1

    def _imu_cycle(self, dt: float, acc_prev, held_t, held_u, phi: np.ndarray, phid: np.ndarray) -> np.ndarray:
        """The IMU prediction and both encoder updates (``imu_cycle.imu_cycle``); returns its results."""
        kf, s = self.kf, self._s
        held = None
        if acc_prev is not None and self._torque is not None:
            if held_t == self._t:  # taken at the start of this interval: under this interval's torque
                if self._acc is acc_prev:
                    self._acc_u = self._torque
            elif held_u is not None:  # an older reading still driving: add what the torque changed since
                held = held_u
        s[cyc.S_HELD] = held is not None
        fx, fy = self._acc_held[0], self._acc_held[1]
        s[cyc.S_DT], s[cyc.S_FX], s[cyc.S_FY] = dt, fx, fy
        s[cyc.S_PHI_OLD], s[cyc.S_PHI_NEW], s[cyc.S_PHI_R], s[cyc.S_PHI_L] = self._phi_p, phi[2], phi[0], phi[1]
        s[cyc.S_HAVE_TORQUE] = self._torque is not None
        s[cyc.S_NEW_NOISE] = self._acc_held is not self._acc_noise_of  # a new reading: its noise drawn afresh
        self._acc_noise_of = self._acc_held
        s[cyc.S_DA_WALK2] = self._var_da * self.walk_scale
        s[cyc.S_GATE_ENC], s[cyc.S_GATE_HEAD] = self.gate["encoders"], self.gate["heading"]
        cyc.imu_cycle(kf.x, kf.P, kf.F, kf.Q, self._zero3 if self._torque is None else self._torque,
                      self._zero3 if held is None else held, self._prm, s,
                      phid, self._H_rates, self._nu3, self._R_rates, self._H_heading, self._nu1, self._R_heading,
                      self._res)
        return self._res

    def _after_encoders(self, t: float, res: np.ndarray) -> None:
        """``imu_cycle``'s two updates counted as ``_update`` counts them, then the heading's outcome."""
        ok = res[cyc.R_OK_ENC] == 1.0
        self._count("encoders", t, float(res[cyc.R_NIS_ENC]), ok)
        if not ok:
            self._heading_off_since = None
            return
        ok = res[cyc.R_OK_HEAD] == 1.0
        self._count("heading", t, float(res[cyc.R_NIS_HEAD]), ok)
        self._heading_outcome(t, ok, res[cyc.R_NU_HEAD])

    def _update_encoders(self, t: float, phi: np.ndarray, phid: np.ndarray) -> None:
        """Joint rates, then the wheel heading (see the module docstring for slip and re-anchoring); the
        model prediction's path (the IMU's runs both updates in ``imu_cycle``)."""
        x = self.kf.x
        kernels.joint_rates(x, phi[2], self._l1, self._l2, self._r, self._H_rates, self._nu3, phid)
        if not self._update("encoders", t, self._nu3, self._H_rates, self._R_rates):
            self._heading_off_since = None
            return
        nu = wrap_angle(self._wheel_heading(phi) - (x[A] - x[KAPPA] + x[EP]))
        self._heading_outcome(t, self._update("heading", t, np.array([nu]), self._H_heading, self._R_heading), nu)

    def _heading_outcome(self, t: float, ok: bool, nu: float) -> None:
        """A wheel heading rejected for ``REANCHOR_AFTER`` with the rates accepted re-anchors (``nu``: its
        residual, rad). Which state moves: kappa (slip moved the constant) -- unless the gyro disagrees with
        the yaw prediction right now (its averaged NIS above its bound, ``_adapt_walk``: the model is wrong,
        the wheels are right), then alpha; after a fix re-anchored alpha, kappa. The adapted walk itself
        (``walk_scale``) was the test before: it stays up for seconds after the gyro's average crossed its
        bound, which gyro noise alone does (5 of 20 nominal bus corridors), and a slip burst in those seconds
        re-anchored alpha on the wheel heading the burst had moved -- 67 mrad off for good, every fix
        rejected after it (docs/estimation.md, "Slip bursts and absolute fixes in the loop")."""
        if self._rejected_long("_heading_off_since", t, ok):
            i = A if self._gyro_disagrees and not self._kappa_suspect else KAPPA
            self.kf.P[i, i] += nu * nu
            self._update("heading", t, np.array([nu]), self._H_heading, self._R_heading, force=True)
            self._kappa_suspect = False
        elif ok:
            self._kappa_suspect = False

    # ------------------------------------------------------------------ health and output
    def _check_health(self, t: float) -> None:
        x, P = self.kf.x, self.kf.P
        if cyc.healthy(x, P):
            return
        if not (kernels.all_finite(x) and kernels.all_finite(P)):
            raise EstimatorFault(f"the filter diverged at t = {t} s: non-finite state or covariance")
        d = P.diagonal()
        if d.min() <= 0:
            raise EstimatorFault(f"the filter diverged at t = {t} s: covariance not positive "
                                 f"({STATE_NAMES[int(d.argmin())]} variance {d.min():.3g})")

    def _make_estimate(self) -> Estimate:
        x, P = self.kf.x, self.kf.P
        v = np.empty(14)  # pose, twist, their std, accelerometer biases: one new array, four views
        cyc.estimate_vectors(x, P, v)
        return Estimate(t=self._t, pose=v[0:3], twist=v[3:6], std=v[6:12], cov=P.copy(), gyro_bias=float(x[BG]),
                        standstill=self._standstill, nis=dict(self._nis), rejected=dict(self.rejected),
                        updates=dict(self.updates), accel_bias=v[12:14])
