"""Regenerate ``ekf_reference.npz``: a sensed run and the pose EKF's estimates over it, as the code
of a checkout computed them (``tests/test_ekf_kernels.py`` checks the current EKF gives the same).

Run from the checkout whose EKF is the reference (it was main at b6993cc, before the EKF's cycle
became one compiled call): ``cd CHECKOUT && python /path/to/tests/data/make_ekf_reference.py [OUT]``.

The run: the first 6 s of the closed-loop figure-8 at 100 Hz on the paper's noise (seed 4), a 0.02
rad/s gyro bias, wheel slip bursts at 1.5 and 4 s (the joint rates and the heading rejected, the
heading re-anchored), the IMU reading every sample for 3 s, then every third sample (held readings:
the torque correction), the robot's torques; an absolute pose fix every 1.2 s. Stored: the EKF's
inputs and, per sample, pose, twist, std, gyro bias, the covariance's diagonal and the NIS per
update kind.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np

ROOT = Path.cwd() if (Path.cwd() / "otbot_hw").is_dir() else Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from otbot_hw.estimation import EstimatorConfig, PoseEKF  # noqa: E402
from otbot_hw.params import nominal  # noqa: E402
from otbot_hw.sensors import NoiseModel  # noqa: E402

OUT = Path(__file__).with_name("ekf_reference.npz")
KINDS = ("encoders", "heading", "zupt", "gyro", "accel", "fix")


def inputs() -> dict:
    """The sensed run (arrays of the npz's inputs)."""
    spec = importlib.util.spec_from_file_location("estimation_accuracy", ROOT / "benchmarks" / "estimation_accuracy.py")
    study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(study)
    U, F, x0, dt = study.closed_loop("figure8")
    n = int(6 / dt)
    sched = [(0.0, {"b_gz": 0.02}), (1.5, {"b_gz": 0.02, "k_slip": 0.05}), (1.8, {"b_gz": 0.02}),
             (4.0, {"b_gz": 0.02, "k_slip": 0.05}), (4.2, {"b_gz": 0.02})]
    rec = study.sensed_recording(nominal(), U[:n], F[:n], x0, dt, sched, NoiseModel.paper(), 4)
    new_imu = np.ones(len(rec), bool)
    new_imu[int(3 / dt):] = (np.arange(int(3 / dt), len(rec)) % 3) == 0
    rng = np.random.default_rng(7)
    fix_at = np.arange(120, len(rec), 120)
    fix_pose = rec.truth_q[fix_at, :3] + 0.002 * rng.standard_normal((len(fix_at), 3))
    return {"t": rec.t, "joint_pos": rec.joint_pos, "joint_vel": rec.joint_vel, "imu_accel": rec.imu_accel,
            "imu_gyro": rec.imu_gyro, "new_imu": new_imu, "torque": rec.torque, "pose0": rec.truth_q[0, :3],
            "fix_at": fix_at, "fix_pose": fix_pose, "fix_std": np.array(0.002), "period": np.array(dt)}


def run(d: dict, ekf: PoseEKF | None = None) -> dict:
    """The EKF over the inputs ``d``: per sample pose, twist, std (6), gyro bias, P's diagonal (14), NIS."""
    ekf = ekf or PoseEKF(nominal(), float(d["period"]), EstimatorConfig())
    n = len(d["t"])
    out = {"pose": np.empty((n, 3)), "twist": np.empty((n, 3)), "std": np.empty((n, 6)), "gyro_bias": np.empty(n),
           "var": np.empty((n, 14)), "nis": np.full((n, len(KINDS)), np.nan)}
    fixes = dict(zip(d["fix_at"].tolist(), d["fix_pose"]))
    cov = np.eye(3) * float(d["fix_std"]) ** 2

    def keep(k, e):
        out["pose"][k], out["twist"][k], out["std"][k], out["gyro_bias"][k] = e.pose, e.twist, e.std, e.gyro_bias
        out["var"][k] = np.diag(e.cov)
        out["nis"][k] = [e.nis.get(kind, np.nan) for kind in KINDS]

    keep(0, ekf.initialize(d["t"][0], d["pose0"], d["joint_pos"][0], imu_accel=d["imu_accel"][0],
                           imu_gyro=d["imu_gyro"][0]))
    for k in range(1, n):
        imu = (d["imu_accel"][k], d["imu_gyro"][k]) if d["new_imu"][k] else (None, None)
        e = ekf.step(d["t"][k], d["joint_pos"][k], d["joint_vel"][k], *imu, torque=d["torque"][k - 1])
        if k in fixes:
            ekf.fix(d["t"][k], fixes[k], cov)
            e = ekf.estimate
        keep(k, e)
    out["rejected"] = np.array([ekf.rejected[kind] for kind in KINDS])
    out["updates"] = np.array([ekf.updates[kind] for kind in KINDS])
    return out


def main() -> None:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else OUT
    d = inputs()
    ref = run(d)
    np.savez_compressed(out, **d, **{f"ref_{k}": v for k, v in ref.items()})
    print(f"{out}: {len(d['t'])} samples, rejected {dict(zip(KINDS, ref['rejected'].tolist()))}, "
          f"updates {dict(zip(KINDS, ref['updates'].tolist()))}")


if __name__ == "__main__":
    main()
