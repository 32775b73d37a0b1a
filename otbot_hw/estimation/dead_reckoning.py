"""The two single-sensor baselines the EKF is compared with (docs/estimation.md).

* ``imu_dead_reckoning``: the paper's approach (§1.5.1): alpha from the integrated gyro, the pivot
  velocity from the specific force in B'' rotated by alpha and integrated, the position from the
  velocity; no bias model, nothing else corrects it.
* ``wheel_odometry``: the encoders alone: alpha from the holonomic constraint
  alpha = r/(2 l2)(phi_r - phi_l) + phi_p + K0, the position from the joint-angle increments through
  the forward kinematics p_dot = M_FIK(theta) phi_dot (paper §2.3.1) at mid-step.
"""
from __future__ import annotations

import numpy as np

from otbot_hw.model.kinematics import fik_entries
from otbot_hw.params import OtbotParams
from otbot_hw.recording import Recording


def imu_dead_reckoning(rec: Recording, pose0, twist0=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """(pose (N, 3), twist (N, 3)) from the IMU alone, starting at pose0/twist0. The reading of sample
    k (taken just after t_k, under the command of [t_k, t_k+1)) drives that interval."""
    if rec.imu_accel is None:
        raise ValueError("IMU dead reckoning needs the /otbot/imu topic")
    n = len(rec)
    pose = np.empty((n, 3))
    twist = np.empty((n, 3))
    pose[0], twist[0] = pose0, twist0
    twist[0, 2] = rec.imu_gyro[0, 2]
    for k in range(n - 1):
        dt = rec.t[k + 1] - rec.t[k]
        w0, w1 = rec.imu_gyro[k, 2], rec.imu_gyro[k + 1, 2]
        a_mid = pose[k, 2] + 0.25 * (w0 + w1) * dt
        c, s = np.cos(a_mid), np.sin(a_mid)
        fx, fy = rec.imu_accel[k, 0], rec.imu_accel[k, 1]
        acc = np.array([c * fx - s * fy, s * fx + c * fy])
        pose[k + 1, :2] = pose[k, :2] + twist[k, :2] * dt + 0.5 * acc * dt * dt
        twist[k + 1, :2] = twist[k, :2] + acc * dt
        pose[k + 1, 2] = pose[k, 2] + 0.5 * (w0 + w1) * dt
        twist[k + 1, 2] = w1
    return pose, twist


def wheel_odometry(rec: Recording, params: OtbotParams, pose0) -> np.ndarray:
    """Pose (N, 3) from the joint encoders alone, starting at pose0."""
    if rec.joint_pos is None:
        raise ValueError("wheel odometry needs the /otbot/joints topic")
    phi = rec.joint_pos
    k = params.r / (2 * params.l2)
    l1, l2, r = params.l1, params.l2, params.r
    heading = k * (phi[:, 0] - phi[:, 1]) + phi[:, 2]
    pose = np.empty((len(rec), 3))
    pose[:, 2] = heading - heading[0] + pose0[2]
    dphi = np.diff(phi, axis=0)
    th = 0.5 * (pose[1:, 2] + pose[:-1, 2]) - 0.5 * (phi[1:, 2] + phi[:-1, 2])  # theta at mid-step
    b00, b01, b10, b11, _ = fik_entries(np.sin(th), np.cos(th), l1, l2, r)  # M_FIK (``model.kinematics``)
    dx = b00 * dphi[:, 0] + b01 * dphi[:, 1]
    dy = b10 * dphi[:, 0] + b11 * dphi[:, 1]
    pose[0, :2] = pose0[:2]
    pose[1:, 0] = pose0[0] + np.cumsum(dx)
    pose[1:, 1] = pose0[1] + np.cumsum(dy)
    return pose
