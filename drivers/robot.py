"""``CanopenRobot``: the ``otbot_hw.robot.Robot`` interface over CANopen.

One control cycle::

    robot.write(u)        # torques (N m) -> RPDOs; the drives apply them at the next SYNC
    s = robot.read()      # SYNC -> every drive/encoder answers with TPDOs sampled at that SYNC

so the torque written before a ``read()`` is held from that SYNC to the next one, and the
snapshot returned by that ``read()`` holds the joints at the same SYNC (the convention of
``otbot_hw.robot``).

``read()`` never waits for a period boundary: the loop that calls it owns the clock. With
``realtime=True`` (a paced bus: the real robot) the drives' SYNC and RPDO watchdogs are armed, each
SYNC's TPDOs are awaited within the period, and the driver's own multi-SYNC sequences (enable, fault
reaction, fault reset) keep one SYNC per period; without, against a simulated plant, cycles run
back to back (lockstep). Each cycle's controlword comes from what the master commands and what the
drive reports (``drivers.cia402.cyclic_controlword``): a drive found stopped is never re-enabled.
While the drives are enabled the master's heartbeat is withheld once the loop has run no cycle for
``bus.loop_liveness`` periods.

Fault reaction (here, so it holds under any loop): a fault stages a quick stop with zero torque
for every drive and sends it at once; the SYNC cycle is then kept alive, for at most
``bus.reaction_timeout`` periods, until every drive still on the bus confirms QUICK STOP ACTIVE
(or a state without torque) in its own statusword; then the drives are disabled; a drive that
does not confirm gets NMT STOP, which a CiA 402 drive answers with its abort connection option
(0x6007). A fault found by ``read()`` is reacted to before ``read()`` returns; one found by a
background thread (EMCY, heartbeat) by a safety thread unless a ``read()`` is under way, which
then does it. Drive-side protection, configured at boot: the master produces a heartbeat that
every drive consumes (0x1016), and on a paced bus the drives watch the SYNC period (0x1006) and
their RPDO deadline (0x1400:05).

``close()`` never raises: it returns what it could not do.
"""
from __future__ import annotations

import math
import threading
import time

import can
import canopen
import numpy as np

from drivers.cia402 import STOPPED_STATES, CiA402Drive
from drivers.cia406 import CiA406Encoder
from drivers.config import RobotConfig
from drivers.device import NMT_ENTER_PRE_OPERATIONAL, NMT_STOP, CycleTracker, wait_until
from drivers.faults import DriverError
from drivers.heartbeat import HeartbeatConsumer, HeartbeatProducer
from otbot_hw.robot import Fault, Robot, RobotError, RobotFault, Snapshot


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

#: Errors a python-can bus raises when it cannot carry a frame (bus off, adapter gone).
BUS_ERRORS = (can.CanError, OSError, ValueError, AttributeError)
#: Fault kinds after which a node cannot confirm anything over PDOs.
OFF_BUS_KINDS = ("heartbeat", "stale", "nmt", "bus")


def grouped_notes(devices) -> list[str]:
    """Each device note once, with the devices it concerns: 'right_wheel, left_wheel: no 0x6076 ...'."""
    who: dict[str, list[str]] = {}
    for dev in devices:
        for note in dev.notes:
            names = who.setdefault(note, [])
            if dev.name not in names:
                names.append(dev.name)
    return [f"{', '.join(names)}: {note}" for note, names in who.items()]


def open_imu(cfg, port: str | None = None, configure: bool = True):
    """Open the serial IMU of ``cfg`` (``drivers.imu.ImuConfig``; ``port`` overrides cfg.port)
    and, with ``configure``, set its output type and rate with register writes."""
    from drivers.imu import VectorNavIMU

    imu = VectorNavIMU(port or cfg.port, baudrate=cfg.baudrate, mounting=cfg.mounting, timeout=cfg.timeout)
    imu.open()
    if configure:
        try:
            imu.configure(output=cfg.output, rate_hz=cfg.rate_hz)
        except Exception:
            imu.close()
            raise
    return imu


class ReceiveErrors(can.Listener):
    """Turns an error of the bus's receive thread (adapter unplugged, pty closed) into a ``bus``
    fault, instead of a dead thread and a traceback; throttles the retries."""

    def __init__(self, robot: "CanopenRobot"):
        self.robot = robot

    def on_message_received(self, msg) -> None:
        pass

    def on_error(self, exc: Exception) -> None:
        if self.robot._open:
            self.robot._add_fault(Fault("bus", None, "bus", f"cannot receive: {exc}"))
        time.sleep(0.05)


class CanopenRobot(Robot):
    """The robot over CANopen: three ``CiA402Drive`` s, the ``CiA406Encoder`` (unless phi_p comes
    from the pivot drive), heartbeat consumer and producer, and an optional IMU object
    (``read(timeout)`` -> sample with t, accel, gyro, as ``drivers.imu.VectorNavIMU``; the newest
    sample is taken, never awaited: lockstep with a simulated IMU is ``sim.lockstep.ImuLockstep``).

    ``bus``: a python-can bus to use instead of opening ``config.bus``; ``close_imu``: whether
    ``close()`` closes the IMU too; ``realtime``: a bus paced by its loop at the control period
    (drives' SYNC/RPDO watchdogs armed, TPDOs awaited within the period; else lockstep: each SYNC's
    TPDOs awaited up to ``lockstep_timeout`` s, and the drives get no period-based watchdogs since no
    period is kept); ``sdo_timeout``: s an SDO answer is awaited (canopen's 0.3 s by default).

    The constructor reads the object dictionaries and refuses (``DeviceConfigError``) what cannot
    run, before any bus is opened. ``warnings``: what the devices cannot do that the loop would
    use (said once, after ``open()``). ``reactions``: one record per fault reaction.
    """

    MAX_ENABLE_CYCLES = 12
    #: Realtime: part of the period ``read()`` waits for the TPDOs of its SYNC.
    TPDO_WINDOW = 0.8
    #: Lockstep: once one TPDO of a SYNC arrived, wait at most this long (s) for the others.
    LOCKSTEP_SETTLE = 0.05

    def __init__(self, config: RobotConfig, bus=None, imu=None,
                 realtime: bool = False, close_imu: bool = True, lockstep_timeout: float = 1.0,
                 sdo_timeout: float | None = None):
        self.config = config
        self.period = config.bus.period
        self.realtime = realtime
        self.lockstep_timeout = lockstep_timeout
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_CYCLE = 0.1  # s; bounds the wait in disconnect()
        self.tracker = CycleTracker()
        self._lock = threading.RLock()  # faults, staging and sending RPDOs (short)
        self._cycle_lock = threading.RLock()  # one SYNC cycle at a time
        self._faults: list[Fault] = []
        self._fault_t: dict[Fault, float] = {}
        self._fault_sync: dict[Fault, float] = {}
        self.drives = [CiA402Drive(self.network, dc, self.period, self.tracker, self._add_fault)
                       for dc in config.drives]
        for d in self.drives:
            d.master = (config.bus.master_node_id, config.bus.master_heartbeat)
            d.paced = realtime
        enc = config.pivot_encoder
        self.encoder = (CiA406Encoder(self.network, enc, self.tracker, self._add_fault)
                        if enc.source == "encoder" else None)
        self.devices = [*self.drives, *([self.encoder] if self.encoder else [])]
        self._by_id = {d.node_id: d for d in self.devices}
        self.max_torque = tuple(float(v) for v in config.limits.max_torque)
        self.torque_quantum = tuple(d.cfg.joint_torque_per_permille for d in self.drives)
        if sdo_timeout is not None:
            for dev in self.devices:
                dev.node.sdo.RESPONSE_TIMEOUT = sdo_timeout
        self.heartbeats = HeartbeatConsumer(self.network, on_fault=self._add_fault)
        for dc, d in zip(config.drives, self.drives):
            self.heartbeats.add(d.node_id, d.name, dc.heartbeat_consumer)
        if self.encoder:
            self.heartbeats.add(self.encoder.node_id, self.encoder.name, enc.heartbeat_consumer)
        self.master_heartbeat = HeartbeatProducer(self.network, config.bus.master_node_id, config.bus.master_heartbeat,
                                                  alive=self._loop_alive)
        self._loop_t: float | None = None  # wall time of the loop's last read() / write()
        self._stalled = False  # the heartbeat is being withheld
        self._nmt_stopped: set[int] = set()  # nodes this master sent NMT STOP (a reaction's escalation)
        self.imu = imu
        self.close_imu = close_imu
        self.imu_timeout = config.imu.timeout if config.imu else 0.5
        self.imu_rate = float(config.imu.rate_hz) if config.imu else 1.0 / self.period
        self._syncs = 0  # SYNCs sent since open()
        self._misses: dict[tuple[int, int], int] = {}  # consecutive SYNCs without this TPDO
        self._imu_last = None
        self.enabled = False  # drives in OPERATION ENABLED: write() allowed
        self._armed = False  # drives may hold power: a fault must stop them
        self._cycle = 0  # SYNCs since enable(): bus time = cycle * period
        self._sync_t = 0.0
        self._sync_index = -1  # SYNCs sent since open(), minus one: the index of the last one
        self._sync_wall = time.monotonic()
        self._open = False
        self._reaction_pending = False
        self._wake = threading.Event()
        self._safety: threading.Thread | None = None
        self.warnings: list[str] = []
        self.reactions: list[dict] = []
        self.problems: list[str] = []  # what a reaction could not do (reported by close())
        self.close_report: list[str] = []
        self._configured: set[int] = set()  # nodes configured by open() (their 0x1016 is ours to clear)

    # -- lifecycle ---------------------------------------------------------------------------------
    def open(self) -> "CanopenRobot":
        """Connect, boot and configure every node, start PDOs (NMT OPERATIONAL), watch heartbeats,
        produce the master heartbeat."""
        try:
            if self.network.bus is None and self.config.bus.interface == "slcan":
                from drivers.slcan import ChunkedSlcanBus  # python-can's slcan, reading in chunks

                kw = self.config.bus.can_kwargs()
                del kw["interface"]
                self.network.bus = ChunkedSlcanBus(**kw)
                self.network.connect()
            elif self.network.bus is None:
                self.network.connect(**self.config.bus.can_kwargs())
            else:
                self.network.connect()
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            b = self.config.bus
            raise DriverError(f"cannot open CAN bus {b.interface}:{b.channel} ({b.bitrate} bit/s): {exc}") from None
        self.network.bus.set_filters(STANDARD_FRAMES_ONLY)
        if self.network.notifier is not None:
            self.network.notifier.add_listener(ReceiveErrors(self))
        self._open = True
        try:
            self.master_heartbeat.start()
            for dev in self.devices:
                dev.reset_and_wait_bootup(self.config.bus.boot_timeout)
                dev.configure()
                self._configured.add(dev.node_id)
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
        self.warnings = grouped_notes(self.devices)
        self._safety = threading.Thread(target=self._safety_loop, name="fault-reaction", daemon=True)
        self._safety.start()
        return self

    def close(self) -> list[str]:
        """Stop the drives (quick stop confirmed, then disabled; NMT STOP for those that do not
        confirm), NMT PRE-OPERATIONAL, stop the heartbeat watcher and producer, release bus and IMU.
        Never raises: returns what it could not do (empty when all went well)."""
        if not self._open:
            return list(self.close_report)
        problems: list[str] = []
        self.heartbeats.stop()
        try:
            with self._cycle_lock:
                if self._armed:
                    self._stop_drives("close")
        except Exception as exc:  # noqa: BLE001 - close() reports, never raises
            problems.append(f"stopping the drives failed: {type(exc).__name__}: {exc}")
        problems += self.problems
        self._open = False
        self._wake.set()
        def attempt(what: str, fn) -> None:
            try:
                fn()
            except Exception as exc:  # noqa: BLE001 - close() reports, never raises
                problems.append(f"{what}: {exc}")

        # PRE-OPERATIONAL first: it brings back a node the reaction stopped with NMT STOP (SDO works
        # again there), and PDOs stop; then 0x1016 off while the master's heartbeat still runs
        for dev in self.devices:
            attempt(f"{dev.name} (node {dev.node_id}): NMT PRE-OPERATIONAL not sent",
                    lambda dev=dev: dev.nmt_command(NMT_ENTER_PRE_OPERATIONAL))
        off = self._off_bus() - self._nmt_stopped  # (a node we stopped is back in PRE-OPERATIONAL)
        if not any(f.kind == "bus" for f in self.faults):
            for d in self.drives:  # a master that leaves in order is not a lost master
                if d.has(0x1016, 1) and d.node_id in self._configured and d.node_id not in off:
                    try:
                        d.sdo_write(0x1016, 1, 0)
                    except RobotError as exc:
                        problems.append(f"{d.name} (node {d.node_id}): heartbeat consumer not switched off: {exc}")
        attempt("master heartbeat not stopped", self.master_heartbeat.stop)
        if self._safety is not None:
            self._safety.join(timeout=2.0)
            self._safety = None
        if self.imu is not None and self.close_imu and hasattr(self.imu, "close"):
            attempt("IMU not closed", self.imu.close)
        attempt("CAN bus not released", self.network.disconnect)
        self.close_report = problems
        return list(problems)

    def _loop_alive(self) -> bool:
        """False while the drives are enabled and the control loop has run no cycle (``read`` or
        ``write``) for ``bus.loop_liveness`` periods: the master's heartbeat is then withheld."""
        t = self._loop_t
        n = self.config.bus.loop_liveness
        alive = not self.enabled or t is None or time.monotonic() - t <= n * self.period
        if not alive and not self._stalled:
            self.problems.append(f"the control loop ran no cycle for {n} periods (bus.loop_liveness) while the drives "
                                 "were enabled: master heartbeat withheld, the drives' watchdogs stop them")
        self._stalled = not alive
        return alive

    # -- faults ------------------------------------------------------------------------------------
    def _bus_time(self, wall: float | None = None) -> float:
        """Bus time (s): cycle * period at the last SYNC, plus the wall time elapsed since it."""
        if wall is None:
            return self._sync_t
        return self._sync_t + max(0.0, wall - self._sync_wall)

    def _add_fault(self, f: Fault, at_sync: bool = False) -> None:
        """Latch ``f``; start the fault reaction: quick stop with zero torque staged and sent to every
        drive at once (applied at the next SYNC), the rest of the reaction at the next cycle."""
        with self._lock:
            if any(g.device == f.device and g.kind == f.kind and g.code == f.code for g in self._faults):
                return
            self._faults.append(f)
            self._fault_t[f] = self._sync_t if at_sync else self._bus_time(f.time)
            gap = 0.0 if at_sync else max(0.0, f.time - self._sync_wall) / self.period
            self._fault_sync[f] = self._sync_index + gap
            if self._open and self._armed:
                self._reaction_pending = True
                for d in self.drives:
                    d.stage_quick_stop()
                    try:
                        d.transmit()
                    except Exception:  # noqa: BLE001 - the reaction retries and reports
                        pass
        if self._reaction_pending:
            self._wake.set()

    @property
    def faults(self) -> tuple[Fault, ...]:
        with self._lock:
            return tuple(self._faults)

    def fault_times(self) -> dict[Fault, float]:
        """Bus time (s since enabling, see ``_bus_time``) at which each active fault was detected."""
        with self._lock:
            return {f: self._fault_t[f] for f in self._faults}

    def fault_syncs(self) -> dict[Fault, float]:
        """When each active fault was detected, as the index of the SYNC since ``open()`` (a fault
        found between SYNCs: the last index plus the elapsed wall time in periods). A simulated
        plant counts the same SYNCs from the master's boot, so this is the clock both sides share."""
        with self._lock:
            return {f: self._fault_sync[f] for f in self._faults}

    def _safety_loop(self) -> None:
        while True:
            self._wake.wait()
            self._wake.clear()
            if not self._open:
                return
            with self._cycle_lock:
                if self._reaction_pending and self._armed and self._open:
                    try:
                        self._stop_drives("fault")
                    except Exception as exc:  # noqa: BLE001 - never let the thread die silently
                        self.problems.append(f"fault reaction failed: {type(exc).__name__}: {exc}")

    def _off_bus(self) -> set[int]:
        """Nodes that cannot confirm anything over PDOs (all of them once the bus itself failed)."""
        faults = self.faults
        if any(f.kind == "bus" for f in faults):
            return {d.node_id for d in self.devices}
        return {f.node for f in faults if f.kind in OFF_BUS_KINDS}

    # -- cycle -------------------------------------------------------------------------------------
    def _send_rpdos(self, drives) -> list[str]:
        """Send each drive's staged RPDOs; returns the drives whose transmission failed."""
        failed = []
        for d in drives:
            try:
                d.transmit()
            except Exception as exc:  # noqa: BLE001
                failed.append(f"{d.name} (node {d.node_id}): RPDO not sent: {exc}")
        return failed

    def _space(self) -> None:
        """Paced bus, in the driver's own multi-SYNC sequences (enable, fault reaction, fault reset),
        which run while the loop waits: the next SYNC no sooner than one period after the last one.
        ``read()`` itself never waits: the loop runner owns the clock."""
        if self.realtime:
            time.sleep(max(0.0, self._sync_wall + self.period - time.monotonic()))

    def _sync_cycle(self, spaced: bool = False) -> set[tuple[int, int]]:
        """One SYNC (``spaced``: see ``_space``): send it, wait for the TPDOs, count misses (stale
        faults after ``bus.tpdo_timeout`` consecutive ones), check each statusword against what the
        master commands. Returns the (node, TPDO) pairs that arrived."""
        if spaced:
            self._space()
        off = {f.node for f in self.faults if f.kind in ("heartbeat", "nmt")} | self._nmt_stopped
        expected = [k for d in self.devices if d.node_id not in off for k in d.expected_tpdos()]
        self.tracker.begin(expected)
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
        if self.realtime:
            missing = self.tracker.wait(max(0.0, t_sync + self.TPDO_WINDOW * self.period - time.monotonic()))
        else:
            missing = self.tracker.wait(self.lockstep_timeout, settle=self.LOCKSTEP_SETTLE)
        byid = self._by_id
        n_max = self.config.bus.tpdo_timeout
        for key in expected:
            if key in missing:
                self._misses[key] = self._misses.get(key, 0) + 1
                if self._misses[key] == n_max:
                    node, no = key
                    self._add_fault(byid[node].fault("stale", f"TPDO{no} missing at {n_max} consecutive SYNCs "
                                                              f"(bus.tpdo_timeout = {n_max} periods)"), at_sync=True)
            else:
                self._misses[key] = 0
        arrived = set(expected) - missing
        for d in self.drives:
            f = d.check_statusword()
            if f:
                self._add_fault(f, at_sync=True)
            elif (d.node_id, d.status_tpdo) in arrived and d.node_id not in off:
                with self._lock:  # the command and the check as one: a fault staging a quick stop waits
                    why = d.unexpected_state()
                    if why:
                        self._add_fault(d.fault("statusword", why), at_sync=True)
        return arrived

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

    def node_identities(self) -> dict[str, dict]:
        """Each node's CiA 301 identity object 0x1018 (vendor, product, revision, serial) over SDO."""
        nodes = {}
        for dev in self.devices:
            entry: dict = {"node_id": dev.node_id}
            for sub, key in ((1, "vendor"), (2, "product"), (3, "revision"), (4, "serial")):
                try:
                    entry[key] = int(dev.sdo_read(0x1018, sub))
                except Exception:  # noqa: BLE001 - a node without (that part of) the identity object
                    entry[key] = None
            nodes[dev.name] = entry
        return nodes

    def enable(self) -> None:
        faults = self.faults
        if faults:
            raise RobotFault("cannot enable while faulted: " + "; ".join(map(str, faults)), faults)
        with self._cycle_lock:
            self._armed = True
            try:
                for _ in range(self.MAX_ENABLE_CYCLES):
                    with self._lock:
                        done = [d.step_towards_enabled() for d in self.drives]
                        if all(done):
                            break
                        failed = self._send_rpdos(self.drives)
                    if failed:
                        self._add_fault(Fault("bus", None, "bus", "; ".join(failed)))
                    self._space()
                    self.read()
                    if self.faults:
                        raise RobotFault("fault while enabling: " + "; ".join(map(str, self.faults)), self.faults)
                else:
                    states = ", ".join(f"{d.name}: {d.state}" for d in self.drives)
                    raise DriverError(f"drives did not reach OPERATION ENABLED in {self.MAX_ENABLE_CYCLES} cycles "
                                      f"({states})")
            except RobotError:
                if self._armed:
                    self._stop_drives("enable failed")  # the drives that did enable lose power again
                raise
            self.enabled = True
            self._cycle = 0

    def _stop_drives(self, reason: str, quick_stop: bool = True, disable: bool = True) -> dict:
        """Quick stop (SYNC kept alive until every drive still on the bus confirms a state without
        torque in its statusword, at most ``bus.reaction_timeout`` periods), NMT STOP for those that
        do not confirm, then disable. Call with the cycle lock held. Returns the reaction record."""
        with self._lock:
            self._reaction_pending = False
            self.enabled = False
        n_max = self.config.bus.reaction_timeout
        rec = {"reason": reason, "t": self._sync_t, "cycles": 0, "confirmed": [], "escalated": [],
               "not_sent": []}
        confirmed: set[int] = set()
        if quick_stop:
            for _ in range(n_max):
                with self._lock:
                    for d in self.drives:
                        d.stage_quick_stop()
                    rec["not_sent"] += self._send_rpdos(self.drives)
                arrived = self._sync_cycle(spaced=True)
                rec["cycles"] += 1
                off = self._off_bus()
                for d in self.drives:
                    if (d.node_id, d.status_tpdo) in arrived and d.state in STOPPED_STATES:
                        confirmed.add(d.node_id)
                if all(d.node_id in confirmed for d in self.drives if d.node_id not in off):
                    break
        for d in self.drives:
            if quick_stop and d.node_id not in confirmed:
                why = ("off the bus" if d.node_id in self._off_bus()
                       else f"no quick stop confirmed within {n_max} periods")
                try:
                    if d.node_id not in self._off_bus():  # our own NMT STOP: expected, no second reaction
                        self.heartbeats.expect_node(d.node_id, "STOPPED")
                        self._nmt_stopped.add(d.node_id)
                    d.nmt_command(NMT_STOP)
                    rec["escalated"].append(d.name)
                    msg = f"{d.name} (node {d.node_id}): {why}: NMT STOP sent (the drive applies 0x6007)"
                except Exception as exc:  # noqa: BLE001
                    msg = f"{d.name} (node {d.node_id}): {why}: NMT STOP not sent: {exc}"
                self.problems.append(msg)
                if d.node_id not in self._off_bus():
                    self._add_fault(d.fault("statusword", f"{why} ({reason})"))
        if disable:
            reachable = [d for d in self.drives if d.node_id not in self._off_bus() | self._nmt_stopped]
            if reachable:
                with self._lock:
                    for d in self.drives:
                        d.stage_disable()
                    rec["not_sent"] += self._send_rpdos(reachable)
                for _ in range(n_max):
                    arrived = self._sync_cycle(spaced=True)
                    rec["cycles"] += 1
                    if all((d.node_id, d.status_tpdo) in arrived and d.state not in ("OPERATION ENABLED",
                                                                                  "QUICK STOP ACTIVE")
                           for d in reachable):
                        break
            self._armed = False
        with self._lock:
            self._reaction_pending = False
        rec["confirmed"] = [d.name for d in self.drives if d.node_id in confirmed]
        self.problems += [p for p in rec["not_sent"] if p not in self.problems]
        self.reactions.append(rec)
        return rec

    def disable(self) -> None:
        with self._cycle_lock:
            if self._open:
                self._stop_drives("disable", quick_stop=False)

    def quick_stop(self) -> None:
        """Quick stop every drive, confirmed by their statuswords (SYNC kept alive for at most
        ``bus.reaction_timeout`` periods; NMT STOP for a drive that does not confirm). After a fault
        the drives are disabled as well."""
        with self._cycle_lock:
            if self._open and self._armed:
                self._stop_drives("quick stop", disable=bool(self.faults))

    def fault_reset(self) -> None:
        with self._cycle_lock:
            for node in sorted(self._nmt_stopped):  # escalated nodes kept their setup: start their PDOs again
                dev = next(d for d in self.devices if d.node_id == node)
                try:
                    dev.start()
                except Exception as exc:  # noqa: BLE001 - reported; the heartbeat check says the rest
                    self.problems.append(f"{dev.name} (node {node}): NMT START not sent: {exc}")
            self._nmt_stopped.clear()
            for edge in (False, True):
                with self._lock:
                    for d in self.drives:
                        d.stage_fault_reset(edge)
                    self._send_rpdos(self.drives)
                self._sync_cycle(spaced=True)
            with self._lock:
                self._faults.clear()
                self._fault_t.clear()
                self._fault_sync.clear()
                self._misses.clear()
                self.problems.clear()
                for d in self.drives:
                    d.stage_disable()
            self.heartbeats.expect_state("OPERATIONAL")
            self.enabled = False
