"""``CanopenRobot``: the ``otbot_hw.robot.Robot`` interface over CANopen — the robot, its devices,
boot and configuration (``open``), ``close``. Its parts, each in a module of its own:

* ``drivers.cyclic``   — ``CyclicExchange``: one SYNC cycle, ``read()``, ``write()``'s back end
  (the control cycle's timing convention is there);
* ``drivers.reaction`` — ``FaultReaction``: latched faults, the fault reaction (quick stop confirmed
  by each drive's statusword, NMT STOP for the rest, then disable), the safety thread, and the
  multi-SYNC power sequences ``enable``/``disable``/``quick_stop``/``fault_reset``.

One clock: the runtime owns it (``otbot_hw.clock``) and hands it down (``use_clock``); ``read()``
never waits for a period boundary, and the driver's own multi-SYNC sequences send their SYNCs at the
clock's ticks (default, before a loop hands one: ``Pacer``, one per period on the wall clock). The
real driver awaits each SYNC's TPDOs only up to its deadline within the period; lockstep with a
simulated plant is the simulated back end's (``sim.lockstep``). While the drives are enabled the
master's heartbeat is withheld once the loop has run no cycle for ``bus.loop_liveness`` periods.

Drive-side protection, configured at boot as the configuration says (``drives.sync_watchdog``,
``drives.rpdo_timeout``, ``drives.master_heartbeat_consumer``): the master produces a heartbeat that
every drive consumes (0x1016), the drives watch the SYNC period (0x1006) and their RPDO deadline
(0x1400:05).

``close()`` never raises: it returns what it could not do.
"""
from __future__ import annotations

import math
import threading
import time

import can
import canopen

from drivers.cia402 import CiA402Drive
from drivers.cia406 import CiA406Encoder
from drivers.config import RobotConfig
from drivers.cyclic import CyclicExchange
from drivers.device import NMT_ENTER_PRE_OPERATIONAL, CycleTracker, wait_until
from drivers.faults import DriverError
from drivers.heartbeat import HeartbeatConsumer, HeartbeatProducer
from drivers.reaction import FaultReaction
from otbot_hw.clock import Pacer
from otbot_hw.robot import Fault, Robot, RobotError


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


class CanopenRobot(CyclicExchange, FaultReaction, Robot):
    """The robot over CANopen: three ``CiA402Drive`` s, the ``CiA406Encoder`` (unless phi_p comes
    from the pivot drive), heartbeat consumer and producer, and an optional IMU object
    (``read(timeout)`` -> sample with t, accel, gyro, as ``drivers.imu.VectorNavIMU``; the newest
    sample is taken, never awaited: lockstep with a simulated IMU is ``sim.lockstep.ImuLockstep``).

    ``bus``: a python-can bus to use instead of opening ``config.bus``; ``close_imu``: whether
    ``close()`` closes the IMU too; ``sdo_timeout``: s an SDO answer is awaited (canopen's 0.3 s by
    default); ``clock``: the clock of the driver's own multi-SYNC sequences until a loop hands its
    own (``use_clock``; default a ``Pacer`` at the control period).

    The constructor reads the object dictionaries and refuses (``DeviceConfigError``) what cannot
    run, before any bus is opened. ``warnings``: what the devices cannot do that the loop would
    use (said once, after ``open()``). ``reactions``: one record per fault reaction.
    """

    def __init__(self, config: RobotConfig, bus=None, imu=None, close_imu: bool = True,
                 sdo_timeout: float | None = None, clock=None):
        self.config = config
        self.period = config.bus.period
        self.clock = clock if clock is not None else Pacer(self.period)
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
