"""Lockstep with a simulated plant: a property of the simulated back end, not of the real driver.

The simulated plant (``sim.plant``) steps its model once per SYNC and publishes the IMU sample of
that SYNC on its pseudo-terminal (``sim.imu``); nothing runs in real time. A master in lockstep
therefore waits, after each SYNC on which the IMU is due (``drivers.robot.imu_due``), for the sample
published for it (up to at least ``LOCKSTEP_IMU_TIMEOUT``), and restarts the simulated IMU stream's
watchdog from the SYNC. The real driver (``drivers.robot.CanopenRobot``) never waits for its IMU: a
real VectorNav streams at its own rate, and the newest sample is taken.

``ImuLockstep`` adds that to a ``CanopenRobot`` (``imu_lockstep``: off for a plant run paced in real
time); ``LockstepCanopenRobot`` is the driver so extended, for a plant in its own process (``otbot
plant``) or any bus whose other end is a simulated plant.
"""
from __future__ import annotations

from drivers.config import LOCKSTEP_IMU_TIMEOUT
from drivers.robot import CanopenRobot, imu_due
from otbot_hw.robot import Fault


class ImuLockstep:
    """Mixin before ``CanopenRobot``: the IMU sample of each SYNC awaited (see the module docstring).
    ``imu_lockstep``: whether to (default True); the IMU object then also has ``timeout`` and
    ``restart_watchdog(t)`` (``drivers.imu.VectorNavIMU``)."""

    def __init__(self, *args, imu_lockstep: bool = True, **kwargs):
        super().__init__(*args, **kwargs)
        self.imu_lockstep = imu_lockstep
        if imu_lockstep:  # no real-time deadline: the plant's sample of a SYNC may come late
            self.imu_timeout = max(self.imu_timeout, LOCKSTEP_IMU_TIMEOUT)
            if self.imu is not None:
                self.imu.timeout = max(self.imu.timeout, LOCKSTEP_IMU_TIMEOUT)

    def _read_imu(self, t_sync: float, sync_index: int):
        """On SYNCs where the simulated IMU publishes, the sample published for this SYNC."""
        if not self.imu_lockstep:
            return super()._read_imu(t_sync, sync_index)
        wait_new = imu_due(sync_index, self.period, self.imu_rate)
        try:
            self.imu.restart_watchdog(t_sync)  # the plant publishes per SYNC: the stream is due from this one
            sample = self.imu.read(timeout=self.imu_timeout if wait_new else 0)
            if sample is not None:
                self._imu_last = sample
            elif wait_new:
                self._add_fault(Fault("imu", None, "imu", f"no IMU sample within {self.imu_timeout:g} s of SYNC"),
                                at_sync=True)
        except Exception as exc:  # drivers.imu.ImuFault: device error, timeout, disconnected port
            self._add_fault(Fault("imu", None, "imu", str(exc) or type(exc).__name__), at_sync=True)
        return self._imu_last


class LockstepCanopenRobot(ImuLockstep, CanopenRobot):
    """``CanopenRobot`` in lockstep with a simulated plant (see the module docstring)."""
