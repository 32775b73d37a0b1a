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
from otbot_hw.model.sensor_model import delay_held, stepper_readings_into
from otbot_hw.simulation.integrators import ext_rk4_into
from otbot_hw.simulation.simulator import BUF_F, BUF_OUT, BUF_PRM, BUF_S, BUF_TAU, BUF_U, BUF_WORK, BUF_X


@njit(cache=True, nogil=True)
def sample_and_step_into(x, s, tau, u, f, u_last, f_last, has_last, eff, buf, fixture, imu, dt, substeps):
    """``stepper_readings_into`` at the current sample under u (3,), f (2,) into the readings of ``buf``
    (``Stepper._buf``), then one interval of ``ext_rk4_into`` under them into its X, TAU, S: a loop
    sample's sensors and model step in one compiled call (each call from Python costs about 70 ns per
    argument: the constant arrays are one). Returns 0 (nothing done) when u is not 3 finite numbers or f
    not 2, else 1, or 2 when a wheel slipped in the interval."""
    if u.shape[0] != 3 or f.shape[0] != 2:
        return 0
    for i in range(3):
        if not math.isfinite(u[i]):
            return 0
    U = buf[BUF_U:BUF_F].reshape((1, 3))
    F = buf[BUF_F:BUF_PRM].reshape((1, 2))
    for i in range(3):
        U[0, i] = u[i]
    F[0, 0], F[0, 1] = f[0], f[1]
    prm = buf[BUF_PRM:]
    stepper_readings_into(x, s, tau, u, f, u_last, f_last, has_last, eff, prm, fixture,
                          buf[BUF_OUT:BUF_WORK].reshape((5, 3)), buf[BUF_WORK:BUF_U], imu)
    S = buf[BUF_S:BUF_OUT].reshape((2, 2))
    ext_rk4_into(x, tau, U, F, dt, substeps, prm, eff, fixture, buf[BUF_X:BUF_TAU].reshape((2, 12)),
                 buf[BUF_TAU:BUF_S].reshape((2, 3)), S, buf[:0].reshape((0, 6)), buf[:0].reshape((0, 2)))
    return 2 if (S[1, 0] != 0.0 or S[1, 1] != 0.0) else 1


_F64 = np.dtype(np.float64)


class StepperSensors:
    """Noise-free sensors of ``stepper`` (a ``Stepper``) sampled every ``period`` s."""

    def __init__(self, stepper, period: float):
        self.stepper = stepper
        self.period = float(period)
        self.latency = float(stepper.eff[D_IMU])
        n = int(math.ceil(self.latency / self.period)) + 2 if self.latency > 0 else 0
        self._history: deque = deque(maxlen=max(n, 2))
        self._last = None  # (sample key, readings) of the last read
        b = stepper._buf  # the readings and the scratch of the fused call live in the stepper's buffer
        self._out, self._work, self._zero2 = b[BUF_OUT:BUF_WORK].reshape(5, 3), b[BUF_WORK:BUF_U], np.zeros(2)

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
        if type(u) is not np.ndarray or u.dtype is not _F64 or u.ndim != 1:  # once per cycle: cheap checks
            u = np.asarray(u, dtype=float).reshape(-1)                      # (the lengths: compiled)
        if f is None:
            f = self._zero2
        elif type(f) is not np.ndarray or f.dtype is not _F64 or f.ndim != 1:
            f = np.asarray(f, dtype=float).reshape(-1)
        imu = imu or self.latency > 0
        u_last = st.u_last
        if u_last is None:
            done = sample_and_step_into(st.x, st.slip, st.tau, u, f, u, f, False, st.eff, st._buf, st._code, imu,
                                        st.dt, st._substeps)
        else:
            done = sample_and_step_into(st.x, st.slip, st.tau, u, f, u_last, st.f_last, True, st.eff, st._buf,
                                        st._code, imu, st.dt, st._substeps)
        if done <= 0:
            raise ValueError(f"torques must be 3 finite numbers and the force 2, got {u}, {f}")
        o = self._out.copy()
        st.advance(u, f, done == 2)
        self._last = None
        if not imu:
            return o[0], o[1], None, None
        acc, gyro = self._imu_out(t, o)
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
