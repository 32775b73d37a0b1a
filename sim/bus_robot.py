"""The simulated robot over a CAN bus in this process: the master's ``CanopenRobot`` on python-can's
``virtual`` bus to a ``sim.plant.Plant`` (``VirtualPlant``), the simulated IMU on a pseudo-terminal,
``SimulatedBusRobot`` (the bus robot whose ``SimulatedRobot`` part looks behind the bus at the plant) and
``simulated_robot`` (all of it opened, or the same against a plant in its own process: ``sim.plant_process``).
``GatedBus``: a bus that can be cut (the ``bus-off`` injection).
"""
from __future__ import annotations

import gc
import queue
import time
import uuid
from contextlib import contextmanager

import can
import canopen
import numpy as np
from can.interfaces.virtual import VirtualBus

from drivers.config import LOCKSTEP_HEARTBEAT, LOCKSTEP_SDO_TIMEOUT, LOCKSTEP_TIMEOUT, RobotConfig
from drivers.robot import STANDARD_FRAMES_ONLY, CanopenRobot
from otbot_hw.robot import SimulatedRobot
from sim.injection import Injection, Injector
from sim.lockstep import ImuLockstep
from sim.plant import Plant
from sim.plant_process import PlantProcess


class SimVirtualBus(VirtualBus):
    """python-can's ``virtual`` bus (same channels: it shares them with plain ``VirtualBus`` es) whose
    ``send`` gives each receiver its own frame built field by field, not by ``copy.deepcopy`` (about
    30 us a frame on a loaded machine, most of a cycle's CAN sends in process: issue 22). Each
    receiver still gets its own ``Message`` with its own ``bytearray``, the send time stamped and
    ``channel`` / ``is_rx`` set as ``VirtualBus.send`` does; frames, their content and order are
    those of ``VirtualBus``."""

    def _copy(self, msg: can.Message, timestamp: float, bus_queue) -> can.Message:
        return can.Message(timestamp=timestamp, arbitration_id=msg.arbitration_id,
                           is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                           is_error_frame=msg.is_error_frame, channel=self.channel_id, dlc=msg.dlc,
                           data=bytearray(msg.data), is_fd=msg.is_fd, is_rx=bus_queue is not self.queue,
                           bitrate_switch=msg.bitrate_switch, error_state_indicator=msg.error_state_indicator,
                           check=False)

    def send(self, msg: can.Message, timeout=None) -> None:
        self._check_if_open()
        timestamp = msg.timestamp if self.preserve_timestamps else time.time()
        all_sent = True
        for bus_queue in self.channel:
            if bus_queue is self.queue and not self.receive_own_messages:
                continue
            try:
                bus_queue.put(self._copy(msg, timestamp, bus_queue), block=True, timeout=timeout)
            except queue.Full:
                all_sent = False
        if not all_sent:
            raise can.CanOperationError("Could not send message to one or more recipients")

    def send_many(self, msgs: list, timeout=None) -> None:
        """``send`` of several frames, in order, back to back: each receiver's queue takes them under
        one lock with one wake-up of its reader (not one per frame). Bounded receive queues: one
        ``send`` each."""
        if any(q.maxsize > 0 for q in self.channel):
            for msg in msgs:
                self.send(msg, timeout)
            return
        self._check_if_open()
        now = time.time()
        for bus_queue in self.channel:
            if bus_queue is self.queue and not self.receive_own_messages:
                continue
            copies = [self._copy(m, m.timestamp if self.preserve_timestamps else now, bus_queue) for m in msgs]
            with bus_queue.mutex:
                bus_queue.queue.extend(copies)
                bus_queue.unfinished_tasks += len(copies)
                bus_queue.not_empty.notify()


class GatedBus(can.BusABC):
    """A python-can bus that can be cut (``cut()``): from then on it carries no frame either way,
    as a CAN controller gone bus-off or a pulled connector."""

    def __init__(self, inner: can.BusABC):
        self.inner = inner
        self.is_cut = False
        super().__init__(channel=getattr(inner, "channel_info", "gated"))
        self.channel_info = f"gated {getattr(inner, 'channel_info', inner)}"

    def cut(self) -> None:
        self.is_cut = True

    def send(self, msg: can.Message, timeout=None) -> None:
        if not self.is_cut:
            self.inner.send(msg, timeout)

    def send_many(self, msgs: list, timeout=None) -> None:
        """Several frames in order (the inner bus's ``send_many`` where it has one)."""
        if self.is_cut:
            return
        many = getattr(self.inner, "send_many", None)
        if many is not None:
            many(msgs, timeout)
        else:
            for msg in msgs:
                self.inner.send(msg, timeout)

    def _recv_internal(self, timeout):
        # the inner bus's own receive, not its BusABC.recv loop: the filters are this bus's (set on it,
        # applied by its BusABC.recv), the inner one has none
        msg, _ = self.inner._recv_internal(timeout)
        return (None if self.is_cut else msg), False

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()


class VirtualPlant:
    """A ``Plant`` on python-can's ``virtual`` interface (channel ``config.bus.channel``), in-process,
    behind a ``GatedBus`` (the ``bus-off`` injection cuts it).

    Use as a context manager; the master opens its own virtual bus on the same channel.
    """

    def __init__(self, config: RobotConfig, **plant_kwargs):
        self.bus = GatedBus(SimVirtualBus(channel=config.bus.channel))
        self.network = canopen.Network(self.bus)
        self.network.NOTIFIER_CYCLE = 0.1
        self.network.connect()
        self.bus.set_filters(STANDARD_FRAMES_ONLY)
        try:
            self.plant = Plant(self.network, config, bus_gate=self.bus, **plant_kwargs)
        except Exception:
            self.network.disconnect()
            raise
        self.plant.power_on()

    def close(self) -> None:
        self.plant.stop()
        self.network.disconnect()

    def __enter__(self) -> Plant:
        return self.plant

    def __exit__(self, *exc) -> None:
        self.close()


def open_sim_imu(config: RobotConfig):
    """(publisher, driver): the simulated IMU on a pseudo-terminal and the VectorNav driver that
    opens it by path and configures it with register writes, as it would a real sensor."""
    from drivers.robot import open_imu
    from sim.imu import SimulatedIMU

    pub = SimulatedIMU(output=config.imu.output, rate_hz=int(config.imu.rate_hz), mounting=config.imu.mounting)
    try:
        drv = open_imu(config.imu, port=pub.port, configure=True)
    except Exception:
        pub.close()
        raise
    return pub, drv


class SimulatedBusRobot(ImuLockstep, CanopenRobot, SimulatedRobot):
    """``CanopenRobot`` talking to a ``Plant`` in this process, in lockstep with its IMU unless
    ``imu_lockstep=False`` (``sim.lockstep``): everything goes over the bus as with a real robot; only
    the ``SimulatedRobot`` part looks behind it: ``truth()`` (the plant's state at the last read's
    SYNC), the pivot force, the parameters simulated now and the plant's operator channel."""

    has_operator = True

    def __init__(self, plant: Plant, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.plant = plant

    @property
    def simulated_params(self):
        return self.plant.params

    def operator(self, command: str) -> dict:
        return self.plant.operator(command)

    def trace_points(self, wrap) -> None:
        """For ``otbot_hw.runtime.loop_trace`` (a measurement aid): stamp the plant's work —
        ``wrap(obj, attr, name)`` on its CAN dispatch, its SYNC handler and its IMU's writes."""
        plant = self.plant
        wrap(plant.network, "notify", "plant rx dispatch")
        subs = plant.network.subscribers.get(0x80, [])
        if plant._on_sync in subs:  # the subscriber list holds the bound method: swap in the stamped one
            holder = type("SyncHandler", (), {})()
            holder.f = plant._on_sync
            wrap(holder, "f", "plant SYNC handler")
            subs[:] = [holder.f if cb == plant._on_sync else cb for cb in subs]
        if plant.imu is not None:
            wrap(plant.imu, "_send", "sim IMU write")

    def truth(self) -> np.ndarray | None:
        x = self.plant.sync_x  # the latest SYNC's state, set before its TPDOs went out: no lock to wait
        if x is not None:      # for (the SYNC handler holds it while the model steps after the TPDOs)
            return x.copy()
        with self.plant.lock:
            if self.plant.truth.x:
                return np.array(self.plant.truth.x[-1])
            return self.plant.stepper.x.copy()

    def truth_force(self) -> np.ndarray:
        """External pivot force (2,) N, ground frame, held from the last read's SYNC on."""
        f = self.plant.sync_f  # (as ``truth``: the latest SYNC's, no lock to wait for)
        if f is not None:
            return np.array(f, dtype=float)
        with self.plant.lock:
            return np.array(self.plant.truth.f[-1], dtype=float) if self.plant.truth.f else np.zeros(2)




@contextmanager
def simulated_robot(config: RobotConfig, with_imu: bool = True, imu_pair=None, tpdo_timeout: float | None = None,
                    heartbeat_consumer: float | None = LOCKSTEP_HEARTBEAT, inject: Injection | str | None = None,
                    process: bool = False, realtime: bool = False, **plant_kwargs):
    """A ``CanopenRobot`` (opened: booted, configured, PDOs running) talking over python-can's
    ``virtual`` bus to a ``Plant`` in this process, with the simulated IMU on a pseudo-terminal;
    with ``process``, to a plant in its own process (``otbot plant``) over slcan on a pty.

    Yields (robot, plant) (``plant``: the ``Plant``, or the ``PlantProcess``). The virtual channel
    is made unique, so runs never hear each other. ``tpdo_timeout``: the lockstep wait for the
    TPDOs of a SYNC (s, default ``LOCKSTEP_TIMEOUT``); ``heartbeat_consumer`` (s): the heartbeat
    consumer times of both sides are at least this (None keeps the configuration's: fault tests);
    ``inject``: a fault for the plant to inject (``sim.injection``); ``realtime``: pace SYNCs at
    the control period with the configured watchdogs (no relaxing). On exit, after ``robot.close()``,
    with an injection the drives are given their longest watchdog time to stop by themselves, and
    ``plant.after`` holds the plant's ``report()``.
    """
    if isinstance(inject, str):
        inject = Injection.parse(inject)
    if heartbeat_consumer is not None and not realtime:
        config = config.relaxed(heartbeat_consumer)
    lockstep_timeout = tpdo_timeout if tpdo_timeout is not None else LOCKSTEP_TIMEOUT
    if process:
        with PlantProcess(config, inject=inject, with_imu=with_imu, **plant_kwargs) as pp:
            robot = pp.robot(config, with_imu=with_imu, realtime=realtime, lockstep_timeout=lockstep_timeout)
            try:
                robot.open()
                yield robot, pp
            finally:
                robot.close()
                pp.after = pp.report(wait_stopped=inject is not None)
        return
    config = config.replace_bus(interface="virtual", channel=f"otbot-sim-{uuid.uuid4().hex[:12]}")
    pub = drv = None
    if with_imu and config.imu is not None:
        pub, drv = imu_pair if imu_pair is not None else open_sim_imu(config)
    injector = Injector(inject) if inject is not None else None
    try:
        vp = VirtualPlant(config, imu=pub, injector=injector, **plant_kwargs)
    except Exception:
        if pub is not None and imu_pair is None:
            pub.close()
            drv.close()
        raise
    master_bus = SimVirtualBus(channel=config.bus.channel)
    try:
        robot = SimulatedBusRobot(vp.plant, config, bus=master_bus, imu=drv, imu_lockstep=not realtime,
                                  realtime=realtime, lockstep_timeout=lockstep_timeout,
                                  sdo_timeout=LOCKSTEP_SDO_TIMEOUT)
    except Exception:
        master_bus.shutdown()
        vp.close()
        if pub is not None:
            pub.close()
            drv.close()
        raise
    if realtime:  # wall-clock watchdogs on both sides of one process: no full collection of a large
        gc.collect()  # heap in the middle of the run (as otbot plant and the daemon do; 20-185 ms
        gc.freeze()   # pauses measured without, longer than a heartbeat consumer's slack)
    try:
        robot.open()
        yield robot, vp.plant
    finally:
        robot.close()
        if injector is not None and injector.fired_t is not None:
            vp.plant.wait_all_stopped(vp.plant.longest_watchdog() + 0.2)
        vp.plant.after = vp.plant.report()
        vp.close()
        if pub is not None and hasattr(pub, "close"):
            pub.close()
        if realtime:
            gc.unfreeze()
