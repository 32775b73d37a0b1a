"""Simulated runs turned into recordings: what the robot's sensors would have logged."""
from __future__ import annotations

import numpy as np

from otbot_hw.params import OtbotParams
from otbot_hw.recording import Recording
from otbot_hw.sensors import NoiseModel, measure
from sim.simulator import ForceSchedule, simulate


def simulated_recording(params: OtbotParams, torques: np.ndarray, dt: float, noise: NoiseModel | None = None,
                        seed: int | None = 0, fixture: str = "floor", forces: ForceSchedule | None = None,
                        x0: np.ndarray | None = None, extra_metadata: dict | None = None) -> Recording:
    """Simulate ``torques`` (N, 3) N m held for ``dt`` s each and record N+1 samples.

    Sample k is at t_k = k dt: the command u_k (the last command repeats at t_N),
    encoder and IMU readings with ``noise`` (seeded by ``seed``) and ground truth.
    """
    noise = noise or NoiseModel()
    traj = simulate(params, torques, dt, x0=x0, forces=forces, fixture=fixture)
    rng = np.random.default_rng(seed)
    s = measure(traj.x, traj.u, traj.f, params, noise, rng, fixture)
    meta = {
        "source": "simulation",
        "sample_period": dt,
        "fixture": fixture,
        "params": params.to_dict(),
        "noise": noise.to_dict(),
        "seed": seed,
        "initial_state": traj.x[0].tolist(),
    }
    if forces is not None:
        meta["forces"] = [vars(f) for f in forces.forces]
    meta.update(extra_metadata or {})
    return Recording(t=traj.t, torque=traj.u, joint_pos=s.joint_pos, joint_vel=s.joint_vel,
                     imu_accel=s.imu_accel, imu_gyro=s.imu_gyro, truth_q=traj.q.copy(),
                     truth_qd=traj.qd.copy(), truth_force=traj.f, metadata=meta)
