"""Sensor outputs of a simulated robot, one sample at a time (for loops stepping a ``Stepper``).

``StepperSensors`` reads the noise-free joint encoders and IMU at the stepper's current state x_k,
with the command u_k already acting (the convention of ``otbot_hw.recording``: the IMU at t_k sees
the acceleration under u_k). For the paper's model that is ``otbot_hw.sensors`` (encoders read q,
the IMU the pivot's specific force and the platform rate in B''). For the extended model
(``ExtendedStepper``) the sensor effects of ``otbot_hw.model.effects.sensor_outputs`` apply, sample
by sample: wheel encoders read the wheel angles (rolling angle / radius ratio) plus the slip, times
their scale error; the IMU has its lever arm, slope, yaw misalignment, biases and latency (linear
interpolation in the history of the loop's samples, held before the first one).

The batch functions (``otbot_hw.simulation.runs.extended_recording``) and this sampler give the same
numbers for the same run (tested). Noise is the caller's (``otbot_hw.sensors.NoiseModel``).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from otbot_hw.model import compiled
from otbot_hw.model import effects as fx
from otbot_hw.sensors import GRAVITY


class StepperSensors:
    """Noise-free sensors of ``stepper`` (``Stepper`` or ``ExtendedStepper``) sampled every ``period`` s."""

    def __init__(self, stepper, period: float):
        self.stepper = stepper
        self.period = float(period)
        self.eff = getattr(stepper, "eff", None)
        self._code = stepper._code
        self._floor = stepper.fixture == "floor"
        self._gen = np.zeros(6)
        self.latency = float(self.eff[fx.D_IMU]) if self.eff is not None else 0.0
        n = int(math.ceil(self.latency / self.period)) + 2 if self.latency > 0 else 0
        self._history: deque = deque(maxlen=max(n, 2))

    def delivered_torque(self, u: np.ndarray) -> np.ndarray:
        """Torque (3,) N m the drives deliver at the current sample with command u acting."""
        if self.eff is None:
            return u
        if self.eff[fx.T_I] > 0:
            return self.stepper.tau  # lagged: the torque reached at the end of the last interval
        return fx.actuated_torque(np.asarray(u, dtype=float), self.eff)

    def joints(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Encoder angles (3,) rad and rates (3,) rad/s (phi_r, phi_l, phi_p) at the current state."""
        x = self.stepper.x
        pos, vel = x[3:6].copy(), x[9:12].copy()
        eff = self.eff
        if eff is None:
            return pos, vel
        rho = fx.radius_ratios(eff)
        slip = self.stepper.slip
        slip_d = (fx.slip_rates(x, self.delivered_torque(u), eff, self.stepper._prm, self._code)
                  if eff[fx.K_SLIP] != 0.0 or eff[fx.T_TRAC] != 0.0 else (0.0, 0.0))
        for i in range(2):
            scale = 1.0 + eff[fx.E_R + i]
            pos[i] = scale * (rho[i] * x[3 + i] + slip[i])
            vel[i] = scale * (rho[i] * x[9 + i] + slip_d[i])
        return pos, vel

    def accelerations(self, u: np.ndarray, f: np.ndarray) -> np.ndarray:
        """q_ddot (6,) at the current state under command u and pivot force f (2,) N."""
        x = self.stepper.x
        if self.eff is None:
            return compiled.derivative(x, np.asarray(u, dtype=float), np.asarray(f, dtype=float), self._gen,
                                       self.stepper._prm, self._code)[6:]
        return fx.ext_accelerations(x, self.delivered_torque(u), np.asarray(f, dtype=float), self.eff,
                                    self.stepper._prm, self._code)

    def imu(self, t: float, u: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """IMU specific force (3,) m/s^2 and rate (3,) rad/s at sample time t (s), in the IMU frame
        (B'', rotated by the extended model's yaw misalignment psi). With an IMU latency call this at
        every loop sample, also where the IMU outputs nothing: the delayed value is interpolated."""
        x = self.stepper.x
        qdd = self.accelerations(u, f)
        if self.eff is None:
            c, s = math.cos(x[2]), math.sin(x[2])
            acc = np.array([c * qdd[0] + s * qdd[1], -s * qdd[0] + c * qdd[1], GRAVITY])
            gyro = np.array([0.0, 0.0, x[8]])
            return acc, gyro
        acc, gyro = fx.imu_from_motion(x[2:3], x[8:9], qdd[0:1], qdd[1:2], qdd[2:3], self.eff, floor=self._floor)
        acc, gyro = acc[0], gyro[0]
        if self.latency <= 0:
            return acc, gyro
        self._history.append((t, acc, gyro))
        return self._delayed(t - self.latency)

    def _delayed(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        h = self._history
        if t <= h[0][0]:
            return h[0][1], h[0][2]
        for (t0, a0, g0), (t1, a1, g1) in zip(list(h)[:-1], list(h)[1:]):
            if t0 <= t <= t1:
                w = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
                return a0 + w * (a1 - a0), g0 + w * (g1 - g0)
        return h[-1][1], h[-1][2]
