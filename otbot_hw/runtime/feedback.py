"""Where the loop's state comes from: the EKF on the robot's sensors, or a simulator's ground truth.

A feedback source turns each ``Snapshot`` into a ``StateEstimate``: the platform pose and twist the
controller is fed (``TaskState(p=pose, p_dot=twist, phi_p)``) and the loop records on
``/otbot/estimate``.

* ``EkfFeedback``: ``otbot_hw.estimation.PoseEKF`` (filterpy EKF; see ESTIMATOR contract): initialized
  at the first sample with the known start pose, then one ``step`` per sample with the encoders, the
  IMU only when it brought a new reading, and the command held over the last period; then, when an
  absolute pose source (``fixes``, e.g. ``sim.mocap.MotionCapture``) has a fix for this sample, that
  fix with its covariance (gated like every update). Its ``EstimatorFault`` (NaN or stale data,
  diverged filter) is a loop fault. phi_p is the pivot encoder.
* ``TruthFeedback``: the back end's ``Robot.truth()`` (a simulator); std 0. Only for simulations: a
  robot without ground truth makes it raise ``FeedbackUnavailable``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from otbot_hw.estimation import EstimatorFault, PoseEKF
from otbot_hw.robot import Robot, Snapshot

FEEDBACKS = ("ekf", "truth")


class FeedbackUnavailable(RuntimeError):
    """The requested feedback cannot run here (no ground truth on this back end)."""


@dataclass(slots=True)
class StateEstimate:
    """State at sample time t (s): pose (x, y m, alpha rad, frame B), twist (m/s, rad/s), std (6,) of
    both, gyro z bias (rad/s), pivot angle phi_p (rad); rejected/updates: the estimator's cumulative
    innovation counts per update kind (empty for truth)."""

    t: float
    pose: np.ndarray
    twist: np.ndarray
    std: np.ndarray
    phi_p: float
    gyro_bias: float = 0.0
    rejected: dict = field(default_factory=dict)
    updates: dict = field(default_factory=dict)


class TruthFeedback:
    """Ground truth of a simulated back end (``robot.truth()`` after each read)."""

    name = "truth"
    faults: tuple = ()

    def start(self, snapshot: Snapshot, robot: Robot) -> StateEstimate:
        return self.step(snapshot, robot, None)

    def step(self, snapshot: Snapshot, robot: Robot, u_prev) -> StateEstimate:
        x = robot.truth()
        if x is None:
            raise FeedbackUnavailable("truth feedback needs a simulated back end that knows the true state "
                                      "(this robot has none)")
        return StateEstimate(snapshot.t, x[0:3], x[6:9], _ZERO6, float(x[5]))


_ZERO6 = np.zeros(6)


class EkfFeedback:
    """The pose EKF on the snapshot's sensors. ``params``: the controller's ``OtbotParams``;
    ``period`` s; ``initial_pose`` (3,) the known start pose (m, m, rad); ``config``: an
    ``EstimatorConfig`` (default: its own defaults, the sensor model's sigma); ``fixes``: an absolute
    pose source, ``poll(sample_index, period, robot)`` -> (pose (3,) m, m, rad; cov (3, 3)) or None."""

    name = "ekf"

    def __init__(self, params, period: float, initial_pose, config=None, initial_std=None, fixes=None):
        self.faults = (EstimatorFault,)
        self.ekf = PoseEKF(getattr(params, "params", params), period, config)
        self.initial_pose = np.asarray(initial_pose, dtype=float).reshape(3)
        self.initial_std = initial_std
        self.fixes = fixes
        self._imu_time = None
        self._last = None

    def gates(self) -> dict | None:
        """Accepted and rejected updates so far per kind (encoders, heading, zupt, gyro, accel, fix), from the
        latest estimate (None before the first)."""
        if self._last is None:
            return None
        return {"updates": dict(self._last.updates), "rejected": dict(self._last.rejected)}

    def _record(self, est, snapshot: Snapshot) -> StateEstimate:
        # the Estimate's vectors and counts are its own (new arrays and dicts per estimate, never
        # changed after): taken as they are, no copies per cycle
        self._last = est
        return StateEstimate(est.t, est.pose, est.twist, est.std[:6], float(snapshot.joint_pos[2]), est.gyro_bias,
                             est.rejected, est.updates)

    def start(self, snapshot: Snapshot, robot: Robot) -> StateEstimate:
        self._imu_time = snapshot.imu_time
        # the start sample's IMU reading (taken with the first command acting) drives the first interval
        est = self.ekf.initialize(snapshot.t, self.initial_pose, snapshot.joint_pos, pose_std=self.initial_std,
                                  imu_accel=snapshot.imu_accel, imu_gyro=snapshot.imu_gyro)
        return self._record(est, snapshot)

    def step(self, snapshot: Snapshot, robot: Robot, u_prev) -> StateEstimate:
        fresh = snapshot.imu_time is not None and snapshot.imu_time != self._imu_time
        self._imu_time = snapshot.imu_time
        est = self.ekf.step(snapshot.t, snapshot.joint_pos, snapshot.joint_vel,
                            snapshot.imu_accel if fresh else None, snapshot.imu_gyro if fresh else None,
                            torque=u_prev)
        if self.fixes is not None:
            fix = self.fixes.poll(snapshot.cycle, robot.period, robot)
            if fix is not None:
                self.ekf.fix(snapshot.t, *fix)
                est = self.ekf.estimate
        return self._record(est, snapshot)
