"""Lockstep with a simulated plant: a property of the simulated back end, not of the real driver.

The simulated plant (``sim.plant``) steps its model once per SYNC, answers with the TPDOs of that
SYNC when it has stepped, and publishes the IMU sample of that SYNC on its pseudo-terminal
(``sim.imu``); nothing need run in real time. A master in lockstep therefore

* waits for each SYNC's TPDOs until the plant answers (up to ``lockstep_timeout`` s, then
  ``LOCKSTEP_SETTLE`` s for the rest once the first is in) instead of up to the deadline within the
  period (``TpdoLockstep``);
* asks the drives for no period-based watchdog (``RobotConfig.unpaced``: 0x1006 and 0x1400:05 off),
  since no period is kept, and runs its own multi-SYNC sequences back to back (an ``Unpaced``
  clock) until a loop hands it its clock (``use_clock``);
* after each SYNC on which the IMU is due (``drivers.robot.imu_due``), waits for the sample
  published for it (up to at least ``LOCKSTEP_IMU_TIMEOUT``), and restarts the simulated IMU
  stream's watchdog from the SYNC (``ImuLockstep``, which includes ``TpdoLockstep``).

The real driver (``drivers.robot.CanopenRobot``) does none of this: it awaits TPDOs only within the
period, arms the watchdogs the configuration asks for, and takes the newest IMU sample (a real
VectorNav streams at its own rate). ``LockstepCanopenRobot`` is the driver so extended, for a plant
in this process (``sim.plant.SimulatedBusRobot``), in its own process (``otbot plant``) or any bus
whose other end is a simulated plant; ``realtime=True`` (a plant paced in real time) keeps the real
driver's TPDO wait, watchdogs and clock, ``imu_lockstep`` the IMU's wait.
"""
from __future__ import annotations

from drivers.config import LOCKSTEP_IMU_TIMEOUT
from drivers.robot import CanopenRobot, imu_due
from otbot_hw.clock import Unpaced
from otbot_hw.robot import Fault


class TpdoLockstep:
    """Mixin before ``CanopenRobot``: each SYNC's TPDOs awaited until the plant answers, no
    period-based drive watchdogs, an ``Unpaced`` clock by default (see the module docstring).
    ``realtime``: the plant is paced in real time (none of this); ``lockstep_timeout`` s."""

    #: Once one TPDO of a SYNC arrived, wait at most this long (s) for the others.
    LOCKSTEP_SETTLE = 0.05

    def __init__(self, config, *args, realtime: bool = False, lockstep_timeout: float = 1.0, clock=None, **kwargs):
        self.lockstep = not realtime
        if self.lockstep:
            config = config.unpaced()
            if clock is None:
                clock = Unpaced(config.bus.period)
        super().__init__(config, *args, clock=clock, **kwargs)
        self.lockstep_timeout = lockstep_timeout

    def _await_tpdos(self, t_sync: float) -> set:
        if not self.lockstep:
            return super()._await_tpdos(t_sync)
        return self.tracker.wait(self.lockstep_timeout, settle=self.LOCKSTEP_SETTLE)


class ImuLockstep(TpdoLockstep):
    """Mixin before ``CanopenRobot``: ``TpdoLockstep`` and the IMU sample of each SYNC awaited (see the
    module docstring). ``imu_lockstep``: whether to (default True); the IMU object then also has
    ``timeout`` and ``restart_watchdog(t)`` (``drivers.imu.VectorNavIMU``)."""

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
