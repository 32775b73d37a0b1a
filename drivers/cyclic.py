"""The cyclic exchange of ``CanopenRobot`` (``drivers.robot``): one SYNC cycle, ``read()`` and
``write()``'s back end.

One control cycle::

    robot.write(u)        # torques (N m) -> RPDOs; the drives apply them at the next SYNC
    s = robot.read()      # SYNC -> every drive/encoder answers with TPDOs sampled at that SYNC

so the torque written before a ``read()`` is held from that SYNC to the next one, and the snapshot
returned by that ``read()`` holds the joints at the same SYNC (the convention of ``otbot_hw.robot``).

``read()`` never waits for a period boundary: the loop that calls it owns the clock
(``otbot_hw.clock``). Each SYNC's TPDOs are awaited up to the deadline within the period
(``TPDO_WINDOW``; ``_await_tpdos``, which a simulated back end in lockstep replaces: ``sim.lockstep``);
a TPDO missing at ``bus.tpdo_timeout`` consecutive SYNCs is a ``stale`` fault. Each cycle's
controlword comes from what the master commands and what the drive reports
(``drivers.cia402.cyclic_controlword``): a drive found stopped is never re-enabled. The IMU's newest
sample is taken, never awaited.
"""
from __future__ import annotations

import time

import can
import numpy as np

from drivers.faults import DriverError
from otbot_hw.robot import Fault, RobotFault, Snapshot

#: Errors a python-can bus raises when it cannot carry a frame (bus off, adapter gone).
BUS_ERRORS = (can.CanError, OSError, ValueError, AttributeError)


class CyclicExchange:
    """SYNC, TPDOs, RPDOs: the cycle part of ``CanopenRobot`` (state and locks are the robot's)."""

    #: Part of the period ``read()`` waits for the TPDOs of its SYNC.
    TPDO_WINDOW = 0.8

    def _send_rpdos(self, drives) -> list[str]:
        """Send each drive's staged RPDOs; returns the drives whose transmission failed."""
        failed = []
        for d in drives:
            try:
                d.transmit()
            except Exception as exc:  # noqa: BLE001
                failed.append(f"{d.name} (node {d.node_id}): RPDO not sent: {exc}")
        return failed

    def _sync_cycle(self, spaced: bool = False) -> set[tuple[int, int]]:
        """One SYNC: send it, wait for the TPDOs, count misses (stale faults after ``bus.tpdo_timeout``
        consecutive ones), check each statusword against what the master commands. Returns the
        (node, TPDO) pairs that arrived. ``spaced``: a SYNC of the driver's own multi-SYNC sequences
        (enable, fault reaction, fault reset), sent at the next tick of the runtime's clock
        (``self.clock``) — the driver never sleeps to pace."""
        if spaced:
            self._await_tick()
        off = {f.node for f in self.faults if f.kind in ("heartbeat", "nmt")} | self._nmt_stopped
        expected, expected_set = self._expected(off)
        self.tracker.begin(expected_set)
        t_sync = time.monotonic()
        self._sync_t = self._cycle * self.period
        self._sync_wall = t_sync
        self._sync_index = self._syncs
        self._syncs += 1
        self._cycle += 1
        try:
            self.network.sync.transmit()
        except BUS_ERRORS as exc:
            self.tracker.wait(0)
            self._add_fault(Fault("bus", None, "bus", f"cannot transmit SYNC: {exc}"), at_sync=True)
            return set()
        missing = self._await_tpdos(t_sync)
        if missing or self._missed_last:  # (every TPDO in, none missed before: no count to touch)
            byid = self._by_id
            n_max = self.config.bus.tpdo_timeout
            for key in expected:
                if key in missing:
                    self._misses[key] = self._misses.get(key, 0) + 1
                    if self._misses[key] == n_max:
                        node, no = key
                        self._add_fault(byid[node].fault("stale", f"TPDO{no} missing at {n_max} consecutive SYNCs "
                                                                  f"(bus.tpdo_timeout = {n_max} periods)"),
                                        at_sync=True)
                else:
                    self._misses[key] = 0
            self._missed_last = bool(missing)
        arrived = expected_set - missing if missing else expected_set
        with self._lock:  # each command and its check as one: a fault staging a quick stop waits
            for d in self.drives:
                f = d.check_statusword()
                if f:
                    self._add_fault(f, at_sync=True)
                elif (d.node_id, d.status_tpdo) in arrived and d.node_id not in off:
                    why = d.unexpected_state()
                    if why:
                        self._add_fault(d.fault("statusword", why), at_sync=True)
        return set(arrived)

    _missed_last = True  # a TPDO was missing at the last SYNC (so some miss counts may be non-zero)
    _expected_cache: tuple = ((), None, None, None)

    def _expected(self, off: set) -> tuple[list, frozenset]:
        """The (node, TPDO) pairs this SYNC should bring from the nodes not ``off``, as a list (device
        order) and a frozenset; rebuilt only when ``off`` or a device's TPDO plan changed."""
        plans, off_key, expected, expected_set = self._expected_cache
        key = frozenset(off)
        devices = self.devices
        if off_key != key or len(plans) != len(devices) or any(p is not d.tpdos for p, d in zip(plans, devices)):
            expected = [k for d in devices if d.node_id not in off for k in d.expected_tpdos()]
            expected_set = frozenset(expected)
            self._expected_cache = (tuple(d.tpdos for d in devices), key, expected, expected_set)
        return expected, expected_set

    def _await_tick(self) -> None:
        """The next SYNC of the driver's own multi-SYNC sequences: at the runtime's clock's tick one
        period after the last SYNC (at once on an unpaced clock). The driver itself never sleeps."""
        self.clock.wait_until(self._sync_wall + self.period)

    def _await_tpdos(self, t_sync: float) -> set:
        """Wait for the TPDOs of the SYNC sent at ``t_sync`` (s, ``time.monotonic``) up to the deadline
        within the period; returns the missing ones."""
        return self.tracker.wait(max(0.0, t_sync + self.TPDO_WINDOW * self.period - time.monotonic()))

    def read(self) -> Snapshot:
        if not self._open:
            raise DriverError("robot is not open: call open() first")
        with self._cycle_lock:
            self._loop_t = time.monotonic()
            cycle = self._cycle
            sync_index = self._syncs
            self._sync_cycle()
            t_sync = self._sync_wall
            self.heartbeats.check()  # new faults go to _add_fault
            readings = [d.reading() for d in self.drives]
            pos = np.array([r.position for r in readings])
            if self.encoder is not None:
                pos[2] = self.encoder.position
            acc = gyro = imu_t = None
            if self.imu is not None:
                sample = self._read_imu(t_sync, sync_index)
                if sample is not None:
                    acc, gyro, imu_t = np.asarray(sample.accel, float), np.asarray(sample.gyro, float), sample.t
            if self._reaction_pending and self._armed:
                self._stop_drives("fault")
            snap = Snapshot(t=cycle * self.period, cycle=cycle, host_time=t_sync, joint_pos=pos,
                            joint_vel=np.array([r.velocity for r in readings]),
                            joint_torque=np.array([r.torque for r in readings]), imu_accel=acc, imu_gyro=gyro,
                            imu_time=imu_t, drive_states=tuple(r.state for r in readings), faults=self.faults)
        return snap

    def _read_imu(self, t_sync: float, sync_index: int):
        """The newest IMU sample (never waited for: the IMU streams at its own rate; lockstep with a
        simulated IMU is ``sim.lockstep``'s)."""
        try:
            sample = self.imu.read(timeout=0)
            if sample is not None:
                self._imu_last = sample
        except Exception as exc:  # drivers.imu.ImuFault: device error, timeout, disconnected port
            self._add_fault(Fault("imu", None, "imu", str(exc) or type(exc).__name__), at_sync=True)
        return self._imu_last

    def _apply(self, torques: list[float]) -> np.ndarray:
        """``Robot.write``'s back end: stage each drive's torque (quantized to its per-mille unit) and
        its controlword, send the RPDOs; the drives apply them at the next SYNC."""
        with self._lock:  # the check and the staging as one: a fault staging a quick stop waits
            self._refuse_unless_writable(self._faults, self.enabled, DriverError)
            self._loop_t = time.monotonic()
            # each drive's controlword from the master's command and the drive's reported state:
            # a drive found stopped (by itself) is not re-enabled, and gets no torque
            commanded = np.array([d.stage_cyclic(c) for d, c in zip(self.drives, torques)])
            failed = self._send_rpdos(self.drives)
        if failed:
            self._add_fault(Fault("bus", None, "bus", "; ".join(failed)))
            raise RobotFault("cannot command the drives: " + "; ".join(failed), self.faults)
        return commanded
