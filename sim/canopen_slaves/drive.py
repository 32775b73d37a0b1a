"""A simulated CiA 402 servo drive in a torque mode (CST / PT): the CiA 402 state machine, its own unit
conversions (written from CiA 402, not the driver's), and the drive-side protection a real drive has,
configured by the master over SDO: it consumes the master's heartbeat (0x1016), watches the SYNC
(1.5 x the communication cycle period 0x1006, as CANopenNode does) and its RPDO deadline (event timer
0x1400:05), and treats leaving NMT OPERATIONAL while enabled the same way: it applies its abort
connection option 0x6007 (0 nothing, 1 fault, 2 disable voltage, 3 quick stop; 1 where the dictionary
has no 0x6007, the CiA 402 default) and sends an EMCY. The watchdogs run on wall time
(``check_watchdogs``, called by the plant's watchdog thread).

Fault injection for tests: ``inject_fault(code, emcy=True)``, ``send_emcy(code)``, ``drop_tpdos``,
``go_silent()``.
"""
from __future__ import annotations

import logging
import math
import time

import canopen
from canopen.profiles.p402 import OperationMode
from canopen.sdo import SdoAbortedError

from drivers.config import DriveConfig
from sim.canopen_slaves.node import SYNC_LOSS_CYCLES, SimulatedNode, wrap_int32

log = logging.getLogger(__name__)


# CiA 402 statusword bits of each state (State402.SW_MASK values) plus "voltage enabled" (bit 4).
_SW = {"NOT READY TO SWITCH ON": 0x00, "SWITCH ON DISABLED": 0x40, "READY TO SWITCH ON": 0x31,
       "SWITCHED ON": 0x33, "OPERATION ENABLED": 0x37, "QUICK STOP ACTIVE": 0x17,
       "FAULT REACTION ACTIVE": 0x1F, "FAULT": 0x08}
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
TORQUE_MODES = (OperationMode.PROFILED_TORQUE, OperationMode.CYCLIC_SYNCHRONOUS_TORQUE)
_ERROR_REGISTER_BITS = {0x2: 0x02, 0x3: 0x04, 0x4: 0x08, 0x8: 0x10}  # current, voltage, temperature, comm
#: 0x606C velocity units, per revolution per second of the motor (CiA 402: position units = encoder
#: increments, so "counts/s" is increments per second; rpm and its fractions per minute).
REVS_PER_S_TO_VELOCITY_UNIT = {"rpm": 60.0, "0.1 rpm": 600.0, "0.001 rpm": 60000.0}
ABORT_NOTHING, ABORT_FAULT, ABORT_DISABLE_VOLTAGE, ABORT_QUICK_STOP = 0, 1, 2, 3


class SimulatedDrive(SimulatedNode):
    """A CiA 402 servo drive in a torque mode (CST 10 / PT 4) on the joint described by ``cfg``.

    The plant reads ``joint_torque()`` (N m at the joint, after gear and polarity) and writes the
    joint angle and rate with ``sample(phi, phi_dot)``; 0x6064 is floor-quantized to motor counts
    and wraps as an INTEGER32 (``position_offset`` counts at phi = 0), 0x606C is rounded to the
    configured velocity unit (counts/s by default). ``clock()`` gives the plant's bus time (s),
    used to stamp when the drive stops producing torque (``stopped_since``).
    """

    def __init__(self, network: canopen.Network, cfg: DriveConfig, position_offset: int = 0,
                 supported_modes: int | None = None):
        super().__init__(network, cfg.node_id, cfg.eds, cfg.name)
        self.cfg = cfg
        self.position_offset = int(position_offset)
        self.set_od(0x6076, 0, int(round(cfg.rated_torque * 1000)))
        self.set_od(0x608F, 1, cfg.counts_per_rev)
        self.set_od(0x608F, 2, 1)
        if supported_modes is not None:
            self.set_od(0x6502, 0, supported_modes)
        self.state = "SWITCH ON DISABLED"
        self._last_cw = 0
        self._actual_pm = 0
        self.values.update({(0x6040, 0): 0, (0x6041, 0): 0, (0x6060, 0): 0, (0x6061, 0): 0,
                            (0x6064, 0): 0, (0x606C, 0): 0, (0x6071, 0): 0, (0x6077, 0): 0,
                            (0x603F, 0): 0, (0x1001, 0): 0})
        self.clock = lambda: 0.0
        self.stopped_since: tuple[float, float] | None = (0.0, time.monotonic())  # (bus time, wall)
        self.aborts: list[tuple[int, str, float]] = []  # (error code, reason, bus time) of each abort
        self._master: tuple[int, float] | None = None  # (node ID, consumer time s) from 0x1016:01
        self._master_seen: float | None = None  # wall time of the master's last heartbeat
        self._last_sync: float | None = None
        self._last_rpdo: float | None = None
        self._tripped: set[str] = set()
        self._qs_syncs = 0  # SYNCs spent in QUICK STOP ACTIVE
        self._update_statusword()

    def keep_on_reset(self) -> set[int]:
        return {0x6076, 0x608F, 0x6502}

    def on_reset(self, application: bool) -> None:
        if application:
            self.state = "SWITCH ON DISABLED"
            for key in ((0x6040, 0), (0x6060, 0), (0x6061, 0), (0x6071, 0), (0x6077, 0), (0x603F, 0), (0x1001, 0)):
                self.values[key] = 0
            self._last_cw = 0
            self._actual_pm = 0
        self._configure_master_watch()
        self._last_sync = self._last_rpdo = None
        self._tripped.clear()
        self._update_statusword()
        self._track()

    # -- units (CiA 402) -------------------------------------------------------------------------
    @property
    def rated_torque(self) -> float:
        """Motor rated torque, N m: 0x6076 (mN m) where the drive has it, else the configuration's."""
        v = self.od_value(0x6076)
        return v / 1000.0 if v else self.cfg.rated_torque

    def motor_angle(self, phi: float) -> float:
        """Motor shaft angle (rad) of joint angle ``phi`` (rad), before the polarity sign."""
        return phi * self.cfg.gear_ratio

    def velocity_units(self, phi_dot: float) -> int:
        """0x606C for joint rate ``phi_dot`` (rad/s): motor revolutions per second in the configured
        unit (increments per second of 0x608F, or rpm, 0.1 rpm, 0.001 rpm), rounded."""
        revs_per_s = self.cfg.polarity * phi_dot * self.cfg.gear_ratio / (2 * math.pi)
        unit = self.cfg.velocity_unit
        if unit == "counts/s":
            inc = self.od_value(0x608F, 1, self.cfg.counts_per_rev) / self.od_value(0x608F, 2, 1)
            return int(round(revs_per_s * inc))
        return int(round(revs_per_s * REVS_PER_S_TO_VELOCITY_UNIT[unit]))

    # -- state machine ---------------------------------------------------------------------------
    def on_sdo_write(self, index: int, subindex: int, value) -> None:
        if index == 0x6060:
            supported = self.od_value(0x6502, 0, 0)
            bit = {v: OperationMode.SUPPORTED[k] for k, v in OperationMode.NAME2CODE.items()}.get(value)
            if value != 0 and (bit is None or not supported & bit):
                raise SdoAbortedError(0x06090030)  # value range of parameter exceeded
            self.values[(0x6061, 0)] = value
        elif index == 0x6040:
            self._controlword(value)

    def on_config_write(self, index: int, subindex: int, value) -> None:
        if (index, subindex) == (0x1016, 1):
            self._configure_master_watch(value)

    def _configure_master_watch(self, entry: int | None = None) -> None:
        """0x1016:01 = node ID << 16 | consumer time in ms (CiA 301): watch that node's heartbeat."""
        if self._master is not None:
            try:
                self.network.unsubscribe(0x700 + self._master[0], self._on_master_heartbeat)
            except (KeyError, ValueError):
                pass
        self._master = None
        self._master_seen = None
        if entry is None:
            entry = self.od_value(0x1016, 1, 0) or 0
        node, ms = (entry >> 16) & 0x7F, entry & 0xFFFF
        if node and ms:
            self._master = (node, ms / 1000.0)
            self.network.subscribe(0x700 + node, self._on_master_heartbeat)

    def _on_master_heartbeat(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self.silent or len(data) != 1:
            return
        self._master_seen = time.monotonic()
        self._tripped.discard("heartbeat")

    def on_sync_received(self) -> None:
        self._last_sync = time.monotonic()
        self._tripped.discard("sync")

    def on_rpdo_received(self, pdo_map) -> None:
        self._last_rpdo = time.monotonic()
        self._tripped.discard("rpdo")

    def _controlword(self, cw: int) -> None:
        rising_reset = bool(cw & 0x80) and not (self._last_cw & 0x80)
        self._last_cw = cw
        s = self.state
        if s == "FAULT":
            if rising_reset:
                self.values[(0x603F, 0)] = 0
                self.values[(0x1001, 0)] = 0
                self.state = "SWITCH ON DISABLED"
                if not self.silent:
                    self.node.emcy.reset()
        elif s == "FAULT REACTION ACTIVE" or cw & 0x80:
            pass
        elif cw & 0x02 == 0:  # disable voltage
            self.state = "SWITCH ON DISABLED"
        elif cw & 0x04 == 0:  # quick stop (transition 11); 0x605A 0: disable at once, 1-4: stop, then
            # SWITCH ON DISABLED at the next SYNC (transition 12, ``on_sync``), 5-8: stay
            self.state = "QUICK STOP ACTIVE" if s in ("OPERATION ENABLED", "QUICK STOP ACTIVE") else "SWITCH ON DISABLED"
            if self.state == "QUICK STOP ACTIVE" and self.quick_stop_option() == 0:
                self.state = "SWITCH ON DISABLED"
        elif cw & 0x01 == 0:  # shutdown
            if s in ("SWITCH ON DISABLED", "SWITCHED ON", "OPERATION ENABLED"):
                self.state = "READY TO SWITCH ON"
        elif cw & 0x08 == 0:  # switch on / disable operation
            if s in ("READY TO SWITCH ON", "OPERATION ENABLED"):
                self.state = "SWITCHED ON"
        else:  # switch on + enable operation; from QUICK STOP ACTIVE (transition 16) only with 0x605A 5-8
            if s in ("READY TO SWITCH ON", "SWITCHED ON") or (s == "QUICK STOP ACTIVE"
                                                               and self.quick_stop_option() in (5, 6, 7, 8)):
                self.state = "OPERATION ENABLED"
        self._update_statusword()

    def quick_stop_option(self) -> int:
        """0x605A quick stop option code (2 where the dictionary has none)."""
        return self.od_value(0x605A, 0, 2)

    def _update_statusword(self) -> None:
        sw = _SW[self.state] | SW_REMOTE
        if self.state == "OPERATION ENABLED":
            sw |= SW_TARGET_REACHED
        self.values[(0x6041, 0)] = sw

    def on_rpdo_applied(self) -> None:
        self._update_statusword()

    def _track(self) -> None:
        """Stamp the moment the drive stops producing torque (zero torque, not OPERATION ENABLED)."""
        stopped = self._actual_pm == 0 and self.state != "OPERATION ENABLED"
        if stopped and self.stopped_since is None:
            self.stopped_since = (self.clock(), time.monotonic())
        elif not stopped:
            self.stopped_since = None

    # -- faults ----------------------------------------------------------------------------------
    def inject_fault(self, code: int, emcy: bool = True) -> None:
        """A drive error: FAULT state (torque off), 0x603F = ``code``, error register, 0x1003
        history and, with ``emcy``, an EMCY message (without: the fault shows in the statusword only)."""
        with self.lock:
            reg = 0x01 | _ERROR_REGISTER_BITS.get(code >> 12, 0)
            self.state = "FAULT"
            self._actual_pm = 0
            self.values[(0x603F, 0)] = code
            self.values[(0x1001, 0)] = reg
            if self.has(0x1003, 0):
                n = min(self.od_value(0x1003, 0, 0) + 1, 4)
                for i in range(n, 1, -1):
                    self.set_od(0x1003, i, self.od_value(0x1003, i - 1, 0))
                self.set_od(0x1003, 1, code)
                self.set_od(0x1003, 0, n)
            self._update_statusword()
            self._track()
            if emcy and not self.silent:
                self.node.emcy.send(code, reg)

    def send_emcy(self, code: int) -> None:
        """An EMCY message (e.g. a warning) without any change of state: the drive keeps running."""
        if not self.silent:
            self.node.emcy.send(code, 0x01 | _ERROR_REGISTER_BITS.get(code >> 12, 0))

    def abort_connection(self, code: int, reason: str, emcy: bool = True) -> None:
        """The master is lost (``reason``): apply 0x6007 (1, fault, where the dictionary has none)."""
        with self.lock:
            option = self.od_value(0x6007, 0, ABORT_FAULT)
            self.aborts.append((code, reason, self.clock()))
            log.info("%s: %s: abort connection option %s", self.name, reason, option)
            if option == ABORT_NOTHING:
                return
            if option == ABORT_DISABLE_VOLTAGE:
                self._controlword(0x0000)
            elif option == ABORT_QUICK_STOP:
                self._controlword(0x0002)
            else:  # fault signal, or manufacturer-specific (< 0)
                self.inject_fault(code, emcy=emcy)
                return
            if self.state != "OPERATION ENABLED":
                self._actual_pm = 0
            self._track()
            if emcy and not self.silent:
                self.node.emcy.send(code, 0x11)

    def on_leave_operational(self, command: int) -> None:
        if self.state == "OPERATION ENABLED":
            self.abort_connection(0x8100, f"NMT command 0x{command:02X} while OPERATION ENABLED", emcy=False)

    def check_watchdogs(self, now: float) -> None:
        """Drive-side watchdogs on wall time ``now`` (time.monotonic()): the master's heartbeat
        (0x1016), SYNC loss (0x1006) and the RPDO deadline (0x1400:05); each trips once until the
        watched thing comes back."""
        with self.lock:
            if self._master is not None and self._master_seen is not None and "heartbeat" not in self._tripped:
                if now - self._master_seen > self._master[1]:
                    self._tripped.add("heartbeat")
                    self.abort_connection(0x8130, f"heartbeat of the master (node {self._master[0]}) lost for "
                                                  f"{now - self._master_seen:.3f} s")
            if self.state != "OPERATION ENABLED":
                return
            if not self.operational:  # left OPERATIONAL by itself (no NMT command seen)
                self.abort_connection(0x8100, f"NMT state {self.node.nmt.state} while OPERATION ENABLED")
                return
            cycle = (self.od_value(0x1006, 0, 0) or 0) * 1e-6
            if cycle and self._last_sync is not None and "sync" not in self._tripped:
                if now - self._last_sync > SYNC_LOSS_CYCLES * cycle:
                    self._tripped.add("sync")
                    self.abort_connection(0x8100, f"SYNC lost for {now - self._last_sync:.4f} s")
            deadline = self._rpdo_deadline()
            if deadline and self._last_rpdo is not None and "rpdo" not in self._tripped:
                if now - self._last_rpdo > deadline:
                    self._tripped.add("rpdo")
                    self.abort_connection(0x8250, f"no RPDO for {now - self._last_rpdo:.4f} s")

    def _rpdo_deadline(self) -> float:
        """Shortest event timer (s) of the enabled RPDOs (0x14xx:05, CiA 301 deadline monitoring)."""
        best = 0.0
        for k in range(4):
            if not self.has(0x1400 + k, 5):
                continue
            cob = self.od_value(0x1400 + k, 1, 0x80000000)
            ms = self.od_value(0x1400 + k, 5, 0) or 0
            if not cob & 0x80000000 and ms:
                best = ms / 1000.0 if not best else min(best, ms / 1000.0)
        return best

    def watchdog_times(self) -> list[float]:
        """The configured watchdog times (s), for the plant's check period."""
        out = [self._master[1]] if self._master else []
        cycle = (self.od_value(0x1006, 0, 0) or 0) * 1e-6
        return out + [t for t in (SYNC_LOSS_CYCLES * cycle, self._rpdo_deadline()) if t]

    # -- process values --------------------------------------------------------------------------
    def on_sync(self) -> None:
        """Torque the power stage produces until the next SYNC: the target torque limited by 0x6072
        (CST), ramped at the torque slope 0x6087 per-mille/s in profile torque mode (slope 0: step);
        zero unless OPERATION ENABLED."""
        mode = self.values[(0x6061, 0)]
        if self.state == "QUICK STOP ACTIVE" and self._qs_syncs >= 1 and self.quick_stop_option() in (1, 2, 3, 4):
            self.state = "SWITCH ON DISABLED"  # stopped (the torque ramp is one SYNC): transition 12
            self._update_statusword()
        self._qs_syncs = self._qs_syncs + 1 if self.state == "QUICK STOP ACTIVE" else 0
        if self.state != "OPERATION ENABLED" or mode not in TORQUE_MODES:
            self._actual_pm = 0
            self._track()
            return
        limit = self.od_value(0x6072, 0, 32767)
        target = int(max(-limit, min(limit, self.values[(0x6071, 0)])))
        slope = self.od_value(0x6087, 0, 0) or 0
        if mode == OperationMode.PROFILED_TORQUE and slope > 0:
            period = self.od_value(0x60C2, 1, 1) * 10.0 ** self.od_value(0x60C2, 2, -3)
            step = max(1, int(slope * period))
            target = self._actual_pm + max(-step, min(step, target - self._actual_pm))
        self._actual_pm = target
        self._track()

    def applied_permille(self) -> int:
        """Torque the power stage produces, per-mille of rated torque (set at each SYNC)."""
        return self._actual_pm

    def joint_torque(self) -> float:
        """Torque at the joint, N m: polarity * gear ratio * motor torque (per-mille of rated)."""
        motor = self.applied_permille() / 1000.0 * self.rated_torque
        return self.cfg.polarity * self.cfg.gear_ratio * motor

    def sample(self, phi: float, phi_dot: float) -> None:
        """Joint angle (rad) and rate (rad/s) into 0x6064 (increments of 0x608F per motor revolution)
        and 0x606C (the configured velocity unit)."""
        inc = self.od_value(0x608F, 1, self.cfg.counts_per_rev) / self.od_value(0x608F, 2, 1)
        counts = math.floor(self.motor_angle(phi) * inc / (2 * math.pi) + 1e-9)
        self.values[(0x6064, 0)] = wrap_int32(self.position_offset + self.cfg.polarity * counts)
        self.values[(0x606C, 0)] = self.velocity_units(phi_dot)
        self.values[(0x6077, 0)] = self.applied_permille()
        self._update_statusword()
