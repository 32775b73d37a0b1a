"""The pose EKF run over a recording (``otbot estimate``, studies): one ``PoseEKF.step`` per sample.

Sample k of a recording holds the command u_k held on [t_k, t_k+1) and the sensors at t_k, so the
step to t_k gets u_{k-1}. A sample's IMU reading counts as new when it differs from the previous
sample's (a loop that runs faster than its IMU records the held reading again).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from otbot_hw.estimation.config import EstimatorConfig
from otbot_hw.estimation.ekf import N_STATE, Estimate, EstimatorFault, PoseEKF
from otbot_hw.params import OtbotParams
from otbot_hw.recording import TOPIC_IMU, TOPIC_JOINTS, Recording, RecordingError


@dataclass
class EstimationRun:
    """The EKF's output over a recording: per sample k, pose, twist (N, 3), std (N, 6), cov (N, 14, 14),
    gyro_bias (N,), standstill (N,) bool; nis {kind: (N,)} (nan where not updated); innovations:
    (t, kind, nis, accepted) of every attempted update; gate {kind: threshold}; rejected, updates:
    final counts per kind; prediction: what drove the prediction (imu or model); notes: what the
    EKF could not use, in words."""

    t: np.ndarray
    pose: np.ndarray
    twist: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    gyro_bias: np.ndarray
    standstill: np.ndarray
    nis: dict
    innovations: list
    gate: dict
    rejected: dict
    updates: dict
    prediction: str
    notes: list = field(default_factory=list)


def initial_state(rec: Recording, initial_pose=None) -> tuple[np.ndarray, np.ndarray, str]:
    """(pose (3,), twist (3,), source): ``initial_pose``, else truth at t0, else the metadata's
    ``initial_state``, else the origin at rest."""
    if initial_pose is not None:
        return np.asarray(initial_pose, dtype=float).reshape(3), np.zeros(3), "given"
    if rec.truth_q is not None:
        return rec.truth_q[0, :3].copy(), rec.truth_qd[0, :3].copy(), "truth"
    x0 = rec.metadata.get("initial_state")
    if isinstance(x0, list) and len(x0) == 12 and all(isinstance(v, (int, float)) for v in x0):
        x0 = np.asarray(x0, dtype=float)
        return x0[:3].copy(), x0[6:9].copy(), "metadata initial_state"
    return np.zeros(3), np.zeros(3), "origin"


def new_imu_samples(rec: Recording) -> np.ndarray:
    """(N,) bool: sample k carries a new IMU reading (it differs from sample k-1's)."""
    if rec.imu_accel is None:
        return np.zeros(len(rec), bool)
    both = np.hstack([rec.imu_accel, rec.imu_gyro])
    new = np.ones(len(rec), bool)
    new[1:] = np.any(both[1:] != both[:-1], axis=1)
    return new


def run_recording(rec: Recording, params: OtbotParams, config: EstimatorConfig | None = None,
                  initial_pose=None, fixes=None, record_innovations: bool = True) -> EstimationRun:
    """Run the EKF over ``rec``. ``fixes``: optional {sample index: (pose (3,), cov (3, 3))} of absolute
    pose fixes applied after that sample's step. Raises RecordingError when the recording has no
    encoders, EstimatorFault (naming the sample) on NaN data or time going backwards."""
    if rec.joint_pos is None:
        raise RecordingError(f"the recording has no {TOPIC_JOINTS}: the EKF needs the wheel and pivot encoders "
                             f"(the pivot angle enters the kinematics; without the wheels the pose drifts "
                             f"without bound)")
    if len(rec) < 2:
        raise RecordingError("the recording has fewer than 2 samples: nothing to estimate")
    if not np.all(np.isfinite(rec.t)) or np.any(np.diff(rec.t) <= 0):
        k = int(np.argmax(~(np.diff(rec.t) > 0))) + 1
        raise EstimatorFault(f"sample {k}: time does not increase (t = {rec.t[k]} s after {rec.t[k - 1]} s)")
    config = config or EstimatorConfig()
    notes = []
    has_imu = rec.imu_accel is not None
    if not has_imu and config.prediction == "imu":
        config = dataclasses.replace(config, prediction="model")
        notes.append(f"no {TOPIC_IMU}: prediction from the dynamic model under the recorded torques; the gyro and "
                     f"accelerometer biases stay at their priors")
    n = len(rec)
    ekf = PoseEKF(params, rec.sample_period, config)
    ekf.record_innovations = record_innovations
    pose0, twist0, _ = initial_state(rec, initial_pose)
    new_imu = new_imu_samples(rec)
    out = {"pose": np.empty((n, 3)), "twist": np.empty((n, 3)), "std": np.empty((n, 6)),
           "cov": np.empty((n, N_STATE, N_STATE)), "gyro_bias": np.empty(n), "standstill": np.zeros(n, bool)}
    nis = {kind: np.full(n, np.nan) for kind in ekf.gate}
    fixes = fixes or {}

    def keep(k: int, e: Estimate) -> None:
        out["pose"][k], out["twist"][k], out["std"][k] = e.pose, e.twist, e.std
        out["cov"][k], out["gyro_bias"][k], out["standstill"][k] = e.cov, e.gyro_bias, e.standstill
        for kind, v in e.nis.items():
            nis[kind][k] = v

    k = 0
    try:
        imu0 = {"imu_accel": rec.imu_accel[0], "imu_gyro": rec.imu_gyro[0]} if has_imu else {}
        keep(0, ekf.initialize(rec.t[0], pose0, rec.joint_pos[0], twist0, **imu0))
        for k in range(1, n):
            imu = (rec.imu_accel[k], rec.imu_gyro[k]) if new_imu[k] else (None, None)
            e = ekf.step(rec.t[k], rec.joint_pos[k], rec.joint_vel[k], *imu, torque=rec.torque[k - 1])
            if k in fixes:
                ekf.fix(rec.t[k], *fixes[k])
                e = ekf.estimate
            keep(k, e)
    except EstimatorFault as exc:
        raise EstimatorFault(f"sample {k} (t = {rec.t[k]:.6g} s): {exc}") from None
    return EstimationRun(t=rec.t.copy(), nis=nis, innovations=ekf.innovations, gate=dict(ekf.gate),
                         rejected=dict(ekf.rejected), updates=dict(ekf.updates), prediction=config.prediction,
                         notes=notes, **out)


def with_estimate(rec: Recording, run: EstimationRun, config: EstimatorConfig | None = None) -> Recording:
    """A copy of ``rec`` carrying ``run`` as its /otbot/estimate topic (metadata ``estimator`` says how)."""
    meta = dict(rec.metadata)
    meta["estimator"] = {"prediction": run.prediction, "config": (config or EstimatorConfig()).to_dict(),
                         "rejected": run.rejected, "updates": run.updates, "notes": run.notes}
    return dataclasses.replace(rec, estimate_pose=run.pose, estimate_twist=run.twist, estimate_std=run.std,
                               estimate_gyro_bias=run.gyro_bias, metadata=meta, events=list(rec.events))


def estimate_recording(rec: Recording, params: OtbotParams, config: EstimatorConfig | None = None,
                       initial_pose=None) -> Recording:
    """Run the EKF over a recording; returns a copy with estimate_pose/twist/std/gyro_bias filled
    (the /otbot/estimate topic). Initial pose: ``initial_pose``, else truth at t0 if present, else the
    metadata initial_state, else the origin."""
    return with_estimate(rec, run_recording(rec, params, config, initial_pose, record_innovations=False), config)
