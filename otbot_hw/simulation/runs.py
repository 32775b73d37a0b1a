"""Simulated runs turned into recordings: what the robot's sensors would have logged."""
from __future__ import annotations

import numpy as np

from otbot_hw.params import OtbotParams
from otbot_hw.recording import Recording, source_metadata
from otbot_hw.sensors import NoiseModel, measure
from otbot_hw.simulation.simulator import ForceSchedule, simulate, simulate_extended


def simulated_recording(params: OtbotParams, torques: np.ndarray, dt: float, noise: NoiseModel | None = None,
                        seed: int | None = 0, fixture: str = "floor", forces: ForceSchedule | None = None,
                        x0: np.ndarray | None = None, extra_metadata: dict | None = None,
                        progress=None) -> Recording:
    """Simulate ``torques`` (N, 3) N m held for ``dt`` s each and record N+1 samples.

    Sample k is at t_k = k dt: the command u_k (the last command repeats at t_N),
    encoder and IMU readings with ``noise`` (seeded by ``seed``) and ground truth. ``progress(done, N)``
    is called after each chunk of the integration (``simulator.simulate``).
    """
    noise = noise or NoiseModel()
    traj = simulate(params, torques, dt, x0=x0, forces=forces, fixture=fixture, progress=progress)
    rng = np.random.default_rng(seed)
    s = measure(traj.x, traj.u, traj.f, params, noise, rng, fixture)
    meta = {
        **source_metadata(simulated=True),
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


def extended_recording(model, torques: np.ndarray, dt: float, noise: NoiseModel | None = None,
                       seed: int | None = 0, fixture: str = "floor", extra_metadata: dict | None = None,
                       progress=None) -> Recording:
    """Like ``simulated_recording``, for the extended model ``model`` (``otbot_hw.model.effects.ExtendedModel``:
    the paper's parameters plus missing-physics effects); sensor effects are applied before the noise.

    Ground truth q holds the rolling angles of the wheels (equal to the wheel angles without a radius
    asymmetry); the effects are written to the ``effects`` metadata entry. ``progress(done, N)``: as in
    ``simulated_recording``.
    """
    from otbot_hw.model.sensor_model import sensor_outputs

    noise = noise or NoiseModel()
    traj = simulate_extended(model.params, model.eff, torques, dt, fixture=fixture, progress=progress)
    s = sensor_outputs(traj, model.params, model.eff)
    rng = np.random.default_rng(seed)
    n = len(traj.t)
    acc = s["imu_accel"] + noise.accel * rng.standard_normal((n, 3))
    gyro = s["imu_gyro"] + noise.gyro * rng.standard_normal((n, 3))
    pos = s["joint_pos"] + noise.enc_angle * rng.standard_normal((n, 3))
    vel = s["joint_vel"] + noise.enc_rate * rng.standard_normal((n, 3))
    meta = {**source_metadata(simulated=True), "sample_period": dt, "fixture": fixture, "params": model.params.to_dict(),
            "effects": model.active_effects(), "noise": noise.to_dict(), "seed": seed,
            "initial_state": traj.x[0].tolist()}
    meta.update(extra_metadata or {})
    return Recording(t=traj.t, torque=traj.u, joint_pos=pos, joint_vel=vel, imu_accel=acc, imu_gyro=gyro,
                     truth_q=traj.x[:, :6].copy(), truth_qd=traj.x[:, 6:].copy(), truth_force=np.zeros((n, 2)),
                     metadata=meta)
