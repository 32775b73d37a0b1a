"""Regenerate ``direct_reference.npz``: ``sim.direct.DirectSimRobot`` run for 1500 samples on four effect
settings, as the code of a checkout computed them (``tests/test_direct_reference.py`` checks that the
current code gives the same bits).

Run from the checkout whose simulator is the reference (it was main at 31ef067, before issue 19's
closing speed work on the direct robot): ``cd CHECKOUT && python /path/to/tests/data/make_direct_reference.py [OUT]``.

The runs (1 kHz, 1.5 s each, paper noise seed 3, IMU at 100 Hz, encoder counts, rate and torque
resolution, motor limits the torques exceed, a pivot force from 0.3 to 0.6 s, a quick stop at sample
700 and enable again at 800, the robot's parameters or effects changed in place mid-run the ways
``sim.load_schedule`` and ``sim.effect_schedule`` change them):

* ``paper``: the paper's model (``OtbotParams``), a 40 kg load put on at sample 1000 (``set_params``);
* ``drive_sensor``: effects that act only on the drives and the sensors (gain errors, saturation, IMU
  latency and misalignment, biases, encoder scale): the integrator's paper shortcut; the load put on
  as ``sim.load_schedule`` does (``params`` and ``_prm`` assigned);
* ``forces``: Coulomb and Stribeck friction, rolling resistance, caster drag, slope;
* ``slip_lag``: wheel slip, a current-loop lag and an IMU latency; k_slip raised in place at sample 500
  (``sim.effect_schedule``).

Stored per setting: the digest (SHA-256) of every channel's bytes, and every 50th row of each channel
(a readable difference when the digests disagree).
"""
from __future__ import annotations

import dataclasses
import hashlib
import sys
from pathlib import Path

import numpy as np

ROOT = Path.cwd() if (Path.cwd() / "otbot_hw").is_dir() else Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from otbot_hw.model.effect_catalog import EFFECT_INDEX  # noqa: E402
from otbot_hw.model.effects import ExtendedModel, effect_vector  # noqa: E402
from otbot_hw.motors import MotorLimits  # noqa: E402
from otbot_hw.params import nominal  # noqa: E402
from otbot_hw.robot import RobotError  # noqa: E402
from otbot_hw.sensors import NoiseModel  # noqa: E402
from otbot_hw.simulation.simulator import ForceSchedule, PivotForce  # noqa: E402
from sim.direct import DirectSimRobot  # noqa: E402

OUT = Path(__file__).with_name("direct_reference.npz")
N = 1500
SETTINGS = {
    "paper": None,
    "drive_sensor": {"k_r": 0.05, "k_l": -0.04, "u_max_p": 4.0, "d_imu": 0.015, "psi": 0.02, "b_ax": 0.1,
                     "b_gz": 0.01, "e_r": 0.01, "d_x": 0.05},
    "forces": {"c_r": 0.3, "c_l": 0.25, "c_p": 0.2, "s_w": 0.1, "c_rr": 0.01, "f_cst": 10.0, "g_x": 0.2},
    "slip_lag": {"k_slip": 0.02, "T_i": 0.01, "d_imu": 0.01, "c_p": 0.1},
}
CHANNELS = ("pos", "vel", "torque", "accel", "gyro", "imu_time", "t", "truth", "truth_force", "commanded",
            "saturated")


def torques(k: int) -> np.ndarray:
    """A deterministic command (3,) N m at sample k that crosses the limits (clamped, saturated)."""
    s = k * 1e-3
    return np.array([8.0 * np.sin(2.1 * s) + 4.0 * np.sin(13.0 * s), -9.0 * np.sin(1.7 * s + 0.3),
                     6.0 * np.sin(3.3 * s) + 5.0 * np.sign(np.sin(7.0 * s))])


def run(setting: str) -> dict[str, np.ndarray]:
    """Every channel (N rows) of the run of ``setting`` on the current checkout's ``DirectSimRobot``."""
    params = nominal()
    loaded = dataclasses.replace(params, m_p=params.m_p + 40.0, I_p=params.I_p + 2.0)
    values = SETTINGS[setting]
    plant = params if values is None else ExtendedModel(params, effect_vector(values))
    robot = DirectSimRobot(plant, period=1e-3, noise=NoiseModel.paper(), seed=3, imu_rate=100.0,
                           encoder_counts=[4096 * 26, 4096 * 26, 2 ** 17], rate_step=[0.01, 0.01, 0.005],
                           limits=MotorLimits(max_torque=(10.0, 10.0, 8.0)), torque_step=0.01,
                           forces=ForceSchedule([PivotForce(0.3, 0.3, 15.0, -10.0)]))
    out = {c: [] for c in CHANNELS}
    robot.enable()
    for k in range(N):
        if k == 700:
            robot.quick_stop()
        if k == 800:
            robot.enable()
        if k == 1000 and setting == "paper":
            robot.stepper.set_params(loaded)
        if k == 1000 and setting == "drive_sensor":
            robot.stepper.params = loaded
            robot.stepper._prm = loaded.as_array()
        if k == 500 and setting == "slip_lag":
            robot.stepper.eff[EFFECT_INDEX["k_slip"]] = 0.05  # in place, as sim.effect_schedule does
        try:
            cmd = robot.write(torques(k))
            commanded, saturated = cmd.commanded, cmd.saturated.astype(float)
        except RobotError:
            commanded, saturated = np.full(3, np.nan), np.full(3, np.nan)
        s = robot.read()
        out["pos"].append(s.joint_pos)
        out["vel"].append(s.joint_vel)
        out["torque"].append(s.joint_torque)
        out["accel"].append(s.imu_accel if s.imu_accel is not None else np.full(3, np.nan))
        out["gyro"].append(s.imu_gyro if s.imu_gyro is not None else np.full(3, np.nan))
        out["imu_time"].append([np.nan if s.imu_time is None else s.imu_time])
        out["t"].append([s.t, s.cycle])
        out["truth"].append(robot.truth())
        out["truth_force"].append(robot.truth_force())
        out["commanded"].append(commanded)
        out["saturated"].append(saturated)
    return {c: np.array(v, dtype=float) for c, v in out.items()}


def digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a, dtype=float).tobytes()).hexdigest()


def main() -> None:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else OUT
    data = {}
    for setting in SETTINGS:
        r = run(setting)
        for c, a in r.items():
            data[f"{setting}/{c}/digest"] = np.array(digest(a))
            data[f"{setting}/{c}/rows"] = a[::50]
    np.savez_compressed(out, **data)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
