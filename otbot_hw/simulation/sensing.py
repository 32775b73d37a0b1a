"""Sensor outputs of a simulated robot, one sample at a time (for loops stepping a ``Stepper``).

``StepperSensors`` reads the noise-free joint encoders and IMU at the stepper's current state x_k,
with the command u_k already acting (the convention of ``otbot_hw.recording``: the IMU at t_k sees
the acceleration under u_k), through the one sensor model ``otbot_hw.model.sensor_model`` that the
batch outputs of a trajectory use too (``stepper_readings_into`` at this one sample, with the previous
step's command as the left limit; the IMU latency by ``delay_held`` on the history of the loop's
samples, held before the first one). The paper's model is the extended one with every effect at zero.
So the sampler and the batch outputs (``otbot_hw.simulation.runs.extended_recording``) give the same
numbers for the same run (``tests/test_sensor_agreement.py``). Noise is the caller's
(``otbot_hw.sensors.NoiseModel``).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from numba import njit

from otbot_hw.model.effect_catalog import D_IMU
from otbot_hw.model.sensor_model import WORK, delay_held, stepper_readings_into
from otbot_hw.simulation.integrators import ext_rk4_into


@njit(cache=True, nogil=True)
def sample_and_step_into(x, s, tau, U, F, u_last, f_last, has_last, eff, prm, fixture, out, work, imu, dt, substeps,
                         X, TAU, S, none6, none2):
    """``stepper_readings_into`` at the current sample under U[0], F[0] into out, then one interval of
    ``ext_rk4_into`` under U (1, 3), F (1, 2) into X, TAU, S: a loop sample's sensors and model step in
    one compiled call (each call from Python costs about 70 ns per argument)."""
    stepper_readings_into(x, s, tau, U[0], F[0], u_last, f_last, has_last, eff, prm, fixture, out, work, imu)
    ext_rk4_into(x, tau, U, F, dt, substeps, prm, eff, fixture, X, TAU, S, none6, none2)


class StepperSensors:
    """Noise-free sensors of ``stepper`` (a ``Stepper``) sampled every ``period`` s."""

    def __init__(self, stepper, period: float):
        self.stepper = stepper
        self.period = float(period)
        self.latency = float(stepper.eff[D_IMU])
        n = int(math.ceil(self.latency / self.period)) + 2 if self.latency > 0 else 0
        self._history: deque = deque(maxlen=max(n, 2))
        self._last = None  # (sample key, readings) of the last read
        self._out, self._work, self._zero2 = np.empty((5, 3)), np.empty(WORK), np.zeros(2)

    @property
    def eff(self) -> np.ndarray:
        return self.stepper.eff

    def delivered_torque(self, u: np.ndarray) -> np.ndarray:
        """Torque (3,) N m the drives deliver at the current sample with command u acting."""
        return self.stepper.delivered_torque(u)

    def _read(self, u: np.ndarray, f: np.ndarray | None) -> np.ndarray:
        """Rows (pos, vel, acc just after, acc just before, gyro) (5, 3) at the current sample
        (``sensor_model.stepper_readings_into``), a fresh array. The encoders do not depend on the pivot
        force (``f`` None): a read at the same sample under the same command serves them."""
        st = self.stepper
        u = np.ascontiguousarray(u, dtype=float)
        key = (st.x, u.tobytes())  # the stepper replaces x at every step
        if f is None and self._last is not None and self._last[0][0] is key[0] and self._last[0][1] == key[1]:
            return self._last[1]
        f = self._zero2 if f is None else np.ascontiguousarray(f, dtype=float)
        has_last = st.u_last is not None
        stepper_readings_into(st.x, st.slip, st.tau, u, f, st.u_last if has_last else u,
                              st.f_last if has_last else f, has_last, st.eff, st._prm, st._code, self._out,
                              self._work)
        o = self._out.copy()
        self._last = (key, o)
        return o

    def joints(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Encoder angles (3,) rad and rates (3,) rad/s (phi_r, phi_l, phi_p) at the current state."""
        o = self._read(u, None)
        return o[0], o[1]

    def imu(self, t: float, u: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """IMU specific force (3,) m/s^2 and rate (3,) rad/s at sample time t (s), in the IMU frame
        (B'', rotated by the extended model's yaw misalignment psi). With an IMU latency call this at
        every loop sample, also where the IMU outputs nothing: the delayed value is interpolated."""
        return self._imu_out(t, self._read(u, f))

    def sample_and_step(self, t: float, u: np.ndarray, f: np.ndarray | None, imu: bool = True):
        """``joints(u)`` and, if ``imu`` or with an IMU latency, ``imu(t, u, f)`` at the current sample,
        then ``stepper.step(u, f)``, in one compiled call: encoder angles, rates (3,) each, IMU specific
        force and rate (3,) each or None (sample-time values, before the step)."""
        st = self.stepper
        U, F = st.interval_inputs(u, f)
        has_last = st.u_last is not None
        imu = imu or self.latency > 0
        sample_and_step_into(st.x, st.slip, st.tau, U, F, st.u_last if has_last else U[0],
                             st.f_last if has_last else F[0], has_last, st.eff, st._prm, st._code, self._out,
                             self._work, imu, st.dt, st._substeps, st._X, st._TAU, st._S, st._none6, st._none2)
        o = self._out.copy()
        st.advance(U, F)
        self._last = None
        acc, gyro = self._imu_out(t, o) if imu else (None, None)
        return o[0], o[1], acc, gyro

    def _imu_out(self, t: float, o: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """IMU specific force and rate at sample time t from the readings o (``_read``): with a latency,
        from the history of the samples (this one appended)."""
        if self.latency <= 0:
            return o[2], o[4]
        acc_r, acc_l, gyro = o[2], o[3], o[4]
        self._history.append((t, acc_r, acc_l, gyro))
        h = self._history
        ts = np.array([e[0] for e in h])
        gy = np.array([e[3] for e in h])
        acc = delay_held(ts, np.array([e[1] for e in h]), np.array([e[2] for e in h]), self.latency)[-1]
        return acc, delay_held(ts, gy, gy, self.latency)[-1]
