"""``CanopenRobot``: the ``otbot_hw.robot.Robot`` interface over CANopen.

One control cycle::

    robot.write(u)        # torques (N m) -> RPDOs; the drives apply them at the next SYNC
    s = robot.read()      # SYNC -> every drive/encoder answers with TPDOs sampled at that SYNC

so the torque written before a ``read()`` is held from that SYNC to the next one, and the
snapshot returned by that ``read()`` holds the joints at the same SYNC (the convention of
``otbot_hw.robot``).

With ``realtime=True`` each ``read()`` waits for the next period boundary (real robot); without,
cycles run back to back (lockstep with a simulated plant, faster than real time).
"""
from __future__ import annotations

import math
import threading
import time

import can
import canopen
import numpy as np

from drivers.cia402 import CiA402Drive
from drivers.cia406 import CiA406Encoder
from drivers.config import RobotConfig
from drivers.device import CycleTracker, wait_until
from drivers.faults import DriverError
from drivers.heartbeat import HeartbeatConsumer
from otbot_hw.robot import Command, Fault, Robot, RobotError, RobotFault, Snapshot


def imu_due(sync_index: int, period: float, imu_rate: float) -> bool:
    """Whether the IMU (``imu_rate`` Hz) outputs a sample at SYNC number ``sync_index`` (0-based)
    of a bus with SYNC ``period`` s: when sync_index * period enters a new IMU period."""
    if sync_index == 0:
        return True
    tick = math.floor(sync_index * period * imu_rate + 1e-9)
    return tick > math.floor((sync_index - 1) * period * imu_rate + 1e-9)


#: python-can filter passing only 11-bit-ID frames: CANopen (CiA 301) never uses extended IDs,
#: and canopen's dispatcher would otherwise take an extended 0x181 for TPDO1 of node 1.
STANDARD_FRAMES_ONLY = [{"can_id": 0, "can_mask": 0, "extended": False}]


def open_imu(cfg, port: str | None = None, configure: bool = True):
    """Open the serial IMU of ``cfg`` (``drivers.imu.ImuConfig``; ``port`` overrides cfg.port)
    and, with ``configure``, set its output type and rate with register writes."""
    from drivers.imu import VectorNavIMU

    imu = VectorNavIMU(port or cfg.port, baudrate=cfg.baudrate, mounting=cfg.mounting, timeout=cfg.timeout)
    imu.open()
    if configure:
        imu.configure(output=cfg.output, rate_hz=cfg.rate_hz)
    return imu


class CanopenRobot(Robot):
    """The robot over CANopen: three ``CiA402Drive`` s, the ``CiA406Encoder`` (unless phi_p comes
    from the pivot drive), heartbeat consumer, and an optional IMU object (``read(timeout)`` ->
    sample with t, accel, gyro, as ``drivers.imu.VectorNavIMU``).

    ``bus``: a python-can bus to use instead of opening ``config.bus``; ``imu_lockstep``: wait,
    after each SYNC, for an IMU sample received after it (simulated IMU published on SYNC);
    ``close_imu``: whether ``close()`` closes the IMU too.
    """

    MAX_ENABLE_CYCLES = 12

    def __init__(self, config: RobotConfig, bus=None, imu=None, imu_lockstep: bool = False,
                 realtime: bool = False, close_imu: bool = True):
        self.config = config
        self.period = config.bus.period
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_CYCLE = 0.1  # s; bounds the wait in disconnect()
        self.tracker = CycleTracker()
        self._lock = threading.RLock()
        self._faults: list[Fault] = []
        self.drives = [CiA402Drive(self.network, dc, self.period, self.tracker, self._add_fault)
                       for dc in config.drives]
        enc = config.pivot_encoder
        self.encoder = (CiA406Encoder(self.network, enc, self.tracker, self._add_fault)
                        if enc.source == "encoder" else None)
        self.devices = [*self.drives, *([self.encoder] if self.encoder else [])]
        self.heartbeats = HeartbeatConsumer(self.network, on_fault=self._add_fault)
        for dc, d in zip(config.drives, self.drives):
            self.heartbeats.add(d.node_id, d.name, dc.heartbeat_consumer)
        if self.encoder:
            self.heartbeats.add(self.encoder.node_id, self.encoder.name, enc.heartbeat_consumer)
        self.imu = imu
        self.close_imu = close_imu
        self.imu_lockstep = imu_lockstep
        self.imu_timeout = config.imu.timeout if config.imu else 0.5
        self.imu_rate = float(config.imu.rate_hz) if config.imu else 1.0 / self.period
        self._syncs = 0  # SYNCs sent since open()
        self._imu_last = None
        self.realtime = realtime
        self.enabled = False  # drives in OPERATION ENABLED: write() allowed
        self._powered = False  # enabled since the last disable (includes quick stop)
        self._cycle = 0
        self._next = None
        self._open = False

    # -- lifecycle ---------------------------------------------------------------------------------
    def open(self) -> "CanopenRobot":
        """Connect, boot and configure every node, start PDOs (NMT OPERATIONAL), watch heartbeats."""
        try:
            if self.network.bus is None:
                self.network.connect(**self.config.bus.can_kwargs())
            else:
                self.network.connect()
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            b = self.config.bus
            raise DriverError(f"cannot open CAN bus {b.interface}:{b.channel} ({b.bitrate} bit/s): {exc}") from None
        self.network.bus.set_filters(STANDARD_FRAMES_ONLY)
        self._open = True
        try:
            for dev in self.devices:
                dev.reset_and_wait_bootup(self.config.bus.boot_timeout)
                dev.configure()
            for dev in self.devices:
                dev.start()
            ok = wait_until(lambda: all(self.heartbeats.state(d.node_id) == 5 for d in self.devices),
                            self.config.bus.boot_timeout)
            if not ok:
                bad = [d.name for d in self.devices if self.heartbeats.state(d.node_id) != 5]
                raise DriverError(f"no OPERATIONAL heartbeat from {', '.join(bad)} within "
                                  f"{self.config.bus.boot_timeout:g} s of NMT start")
            self.heartbeats.expect_state("OPERATIONAL")
            self.heartbeats.start()
        except Exception:
            self.close()
            raise
        return self

    def close(self) -> None:
        """Disable the drives (if powered and not faulted), NMT PRE-OPERATIONAL, release bus and IMU."""
        if not self._open:
            return
        self.heartbeats.stop()
        if self._powered and not self._faults:
            try:
                self.disable()
            except RobotError:
                pass
        self._open = False
        try:
            for dev in self.devices:
                dev.node.nmt.state = "PRE-OPERATIONAL"
        except Exception:  # bus already gone
            pass
        if self.imu is not None and self.close_imu and hasattr(self.imu, "close"):
            self.imu.close()
        self.network.disconnect()

    # -- faults ------------------------------------------------------------------------------------
    def _add_fault(self, f: Fault) -> None:
        with self._lock:
            if any(g.device == f.device and g.kind == f.kind and g.code == f.code for g in self._faults):
                return
            self._faults.append(f)
            # Fault reaction: every drive to quick stop with zero torque at the next SYNC.
            if self._open and self.enabled:
                for d in self.drives:
                    d.stage_quick_stop()
                    try:
                        d.transmit()
                    except Exception:
                        pass

    @property
    def faults(self) -> tuple[Fault, ...]:
        with self._lock:
            return tuple(self._faults)

    # -- cycle -------------------------------------------------------------------------------------
    def _transmit_all(self) -> None:
        with self._lock:
            for d in self.drives:
                d.transmit()

    def read(self) -> Snapshot:
        if not self._open:
            raise DriverError("robot is not open: call open() first")
        if self.realtime:
            now = time.monotonic()
            self._next = now if self._next is None else max(self._next + self.period, now)
            time.sleep(max(0.0, self._next - time.monotonic()))
        silent = {f.node for f in self.faults if f.kind in ("heartbeat", "nmt")}
        expected = [k for d in self.devices if d.node_id not in silent for k in d.expected_tpdos()]
        self.tracker.begin(expected)
        t_sync = time.monotonic()
        self.network.sync.transmit()
        missing = self.tracker.wait(self.config.bus.tpdo_timeout)
        byid = {d.node_id: d for d in self.devices}
        for node, no in sorted(missing):
            self._add_fault(byid[node].fault("stale", f"TPDO{no} not received within "
                                                      f"{self.config.bus.tpdo_timeout * 1000:g} ms of SYNC"))
        self.heartbeats.check()
        for d in self.drives:
            f = d.check_statusword()
            if f:
                self._add_fault(f)
        readings = [d.reading() for d in self.drives]
        pos = np.array([r.position for r in readings])
        if self.encoder is not None:
            pos[2] = self.encoder.position
        acc = gyro = imu_t = None
        sync_index = self._syncs
        self._syncs += 1
        if self.imu is not None:
            sample = self._read_imu(t_sync, sync_index)
            if sample is not None:
                acc, gyro, imu_t = np.asarray(sample.accel, float), np.asarray(sample.gyro, float), sample.t
        snap = Snapshot(t=self._cycle * self.period, cycle=self._cycle, host_time=t_sync, joint_pos=pos,
                        joint_vel=np.array([r.velocity for r in readings]),
                        joint_torque=np.array([r.torque for r in readings]), imu_accel=acc, imu_gyro=gyro,
                        imu_time=imu_t, drive_states=tuple(r.state for r in readings), faults=self.faults)
        self._cycle += 1
        return snap

    def _read_imu(self, t_sync: float, sync_index: int):
        """Latest IMU sample; in lockstep, on SYNCs where the simulated IMU publishes, the one
        published for this SYNC."""
        wait_new = self.imu_lockstep and imu_due(sync_index, self.period, self.imu_rate)
        try:
            sample = self.imu.read(timeout=self.imu_timeout if wait_new else 0)
            if sample is not None:
                self._imu_last = sample
            elif wait_new:
                self._add_fault(Fault("imu", None, "imu", f"no IMU sample within {self.imu_timeout:g} s of SYNC"))
        except Exception as exc:  # drivers.imu.ImuFault: timeout, disconnected port
            self._add_fault(Fault("imu", None, "imu", str(exc) or type(exc).__name__))
        return self._imu_last

    def write(self, torques) -> Command:
        u = np.asarray(torques, dtype=float).reshape(-1)
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            raise ValueError(f"torques must be 3 finite numbers (tau_r, tau_l, tau_p) N m, got {torques!r}")
        faults = self.faults
        if faults:
            raise RobotFault("robot is faulted: " + "; ".join(map(str, faults)), faults)
        if not self.enabled:
            raise DriverError("drives are not enabled: call enable() first")
        clamped, sat = self.config.limits.clamp(u)
        with self._lock:
            commanded = np.array([d.stage_torque(c) for d, c in zip(self.drives, clamped)])
            for d in self.drives:
                d.controlword = 0x000F
            self._transmit_all()
        quantum = np.array([d.cfg.joint_torque_per_permille for d in self.drives])
        sat = sat | (np.abs(commanded - clamped) > 0.5 * quantum + 1e-12)
        return Command(requested=u, commanded=commanded, saturated=sat)

    def enable(self) -> None:
        faults = self.faults
        if faults:
            raise RobotFault("cannot enable while faulted: " + "; ".join(map(str, faults)), faults)
        for _ in range(self.MAX_ENABLE_CYCLES):
            with self._lock:
                done = [d.step_towards_enabled() for d in self.drives]
                if all(done):
                    break
                self._transmit_all()
            self.read()
            if self.faults:
                raise RobotFault("fault while enabling: " + "; ".join(map(str, self.faults)), self.faults)
        else:
            states = ", ".join(f"{d.name}: {d.node.state}" for d in self.drives)
            raise DriverError(f"drives did not reach OPERATION ENABLED in {self.MAX_ENABLE_CYCLES} cycles ({states})")
        self.enabled = True
        self._powered = True
        self._cycle = 0

    def _one_cycle(self, stage) -> None:
        with self._lock:
            for d in self.drives:
                stage(d)
            self._transmit_all()
        self.read()

    def disable(self) -> None:
        self._one_cycle(lambda d: d.stage_disable())
        self.enabled = False
        self._powered = False

    def quick_stop(self) -> None:
        self._one_cycle(lambda d: d.stage_quick_stop())
        self.enabled = False

    def fault_reset(self) -> None:
        self._one_cycle(lambda d: d.stage_fault_reset(False))
        self._one_cycle(lambda d: d.stage_fault_reset(True))
        with self._lock:
            self._faults.clear()
            for d in self.drives:
                d.stage_disable()
        self.heartbeats.expect_state("OPERATIONAL")
        self.enabled = False
