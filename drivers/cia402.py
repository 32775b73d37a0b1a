"""CiA 402 drive in a torque mode, driven through canopen's ``BaseNode402``.

Setup (``configure``): heartbeat producer time (0x1017), the configured SDO writes,
interpolation period (0x60C2) = control period, checks of 0x6076 (rated torque) and 0x608F
(encoder resolution) against the configuration, mode of operation: cyclic synchronous torque
(10) or, where 0x6502 lacks it, profile torque (4); PDO mapping, all synchronous (type 1):

* RPDO1: controlword 0x6040, target torque 0x6071 (per-mille of rated torque);
* TPDO1: statusword 0x6041, position actual 0x6064 (counts), torque actual 0x6077 (per-mille);
* TPDO2: velocity actual 0x606C (counts/s), error code 0x603F, mode display 0x6061.

SI units at the API: joint angle phi = polarity * (counts - counts at zero) / (counts_per_rev *
gear_ratio) * 2 pi rad, zeroed at the first TPDO after ``configure`` (the 32-bit counter is
unwrapped, so wrap-around is invisible); joint rate in rad/s from 0x606C in the configured
``drives.velocity_unit`` (counts/s or rpm variants, motor side); joint torque tau = polarity *
gear_ratio * per-mille / 1000 * rated torque (N m).
"""
from __future__ import annotations

from dataclasses import dataclass

import canopen
from canopen.profiles.p402 import BaseNode402, OperationMode, State402

from drivers.config import DriveConfig
from drivers.device import CanopenDevice, pdo_bytes, pdo_get, pdo_put
from drivers.faults import DriverError, error_meaning
from otbot_hw.robot import Fault

CW_FAULT_RESET = 0x0080
RPDO_LAYOUT = {1: [0x6040, 0x6071]}
TPDO_LAYOUT = {1: [0x6041, 0x6064, 0x6077], 2: [0x606C, 0x603F, 0x6061]}
FAULT_STATES = ("FAULT", "FAULT REACTION ACTIVE")


class Node402(BaseNode402):
    """``BaseNode402`` that ignores TPDOs of the wrong length instead of decoding garbage."""

    def on_TPDOs_update_callback(self, mapobject):
        if len(mapobject.data) != pdo_bytes(mapobject):
            return
        for obj in mapobject:
            self.tpdo_values[obj.index] = pdo_get(obj)


def interpolation_period(period: float) -> tuple[int, int]:
    """0x60C2 (value, index) with value * 10^index = ``period`` s, value <= 255."""
    for index in range(-3, -7, -1):
        value = period / 10.0 ** index
        if abs(value - round(value)) < 1e-6 and 1 <= round(value) <= 255:
            return int(round(value)), index
    raise ValueError(f"control period {period} s cannot be written as 0x60C2 (value 1..255 x 10^-3..-6 s)")


@dataclass(frozen=True)
class DriveReading:
    """What a drive reported at one SYNC: joint angle (rad), rate (rad/s), torque (N m), raw words."""

    position: float
    velocity: float
    torque: float
    statusword: int
    state: str
    error_code: int
    mode: int


class CiA402Drive(CanopenDevice):
    """One joint drive (configuration ``cfg``) on ``network``."""

    node_class = Node402

    def __init__(self, network: canopen.Network, cfg: DriveConfig, period: float, tracker, on_fault):
        super().__init__(network, cfg.name, cfg.node_id, cfg.eds, tracker, on_fault)
        self.cfg = cfg
        self.period = period
        self.mode: int | None = None
        self.max_permille = 32767
        self.controlword = State402.CW_DISABLE_VOLTAGE
        self.target_permille = 0
        self._last_raw_pos: int | None = None
        self._pos_counts = 0  # unwrapped counts since the first reading
        self._fault_reported = False

    # -- setup -----------------------------------------------------------------------------------
    def configure(self) -> None:
        """SDO configuration, checks, mode of operation and PDO mapping (node PRE-OPERATIONAL)."""
        c = self.cfg
        self.sdo_write(0x1017, 0, int(round(c.heartbeat_producer * 1000)))
        for index, sub, value in c.sdo_config:
            self.sdo_write(index, sub, value)
        if 0x60C2 in self.node.object_dictionary:
            value, index = interpolation_period(self.period)
            self.sdo_write(0x60C2, 1, value)
            self.sdo_write(0x60C2, 2, index)
        rated = self.sdo_read(0x6076) / 1000.0
        if abs(rated - c.rated_torque) > 5e-4:
            f = self.fault("config", f"drive reports rated torque 0x6076 = {rated:g} N m, config "
                                     f"'drives.rated_torque' says {c.rated_torque:g} N m")
            raise DriverError(str(f), (f,))
        if 0x608F in self.node.object_dictionary:
            inc, revs = self.sdo_read(0x608F, 1), self.sdo_read(0x608F, 2)
            if revs and inc / revs != c.counts_per_rev:
                f = self.fault("config", f"drive reports {inc}/{revs} increments per motor revolution (0x608F), "
                                         f"config 'drives.counts_per_rev' says {c.counts_per_rev}")
                raise DriverError(str(f), (f,))
        self.max_permille = min(32767, int(self.sdo_read(0x6072))) if 0x6072 in self.node.object_dictionary else 32767
        if self.node.is_op_mode_supported("CYCLIC SYNCHRONOUS TORQUE"):
            self.mode = OperationMode.CYCLIC_SYNCHRONOUS_TORQUE
        elif self.node.is_op_mode_supported("PROFILED TORQUE"):
            self.mode = OperationMode.PROFILED_TORQUE
        else:
            f = self.fault("config", f"0x6502 = 0x{self.node._op_mode_support:08X}: neither cyclic synchronous "
                                     "torque nor profile torque mode supported")
            raise DriverError(str(f), (f,))
        self.sdo_write(0x6071, 0, 0)
        self.sdo_write(0x6060, 0, self.mode)
        shown = self.sdo_read(0x6061)
        if shown != self.mode:
            f = self.fault("config", f"mode of operation {self.mode} written, drive shows {shown} (0x6061)")
            raise DriverError(str(f), (f,))
        self.map_pdos(RPDO_LAYOUT, TPDO_LAYOUT)
        self.node.setup_pdos(upload=False)  # BaseNode402 caches TPDO values / RPDO pointers
        self.hook_tpdos()  # after BaseNode402's cache update, so tpdo_values are fresh here
        self._last_raw_pos = None
        self.controlword = State402.CW_DISABLE_VOLTAGE
        self.target_permille = 0

    # -- units -----------------------------------------------------------------------------------
    def torque_to_permille(self, tau: float) -> int:
        """Joint torque (N m) -> target torque per-mille, rounded and limited to 0x6072."""
        c = self.cfg
        pm = int(round(tau / (c.polarity * c.joint_torque_per_permille)))
        return max(-self.max_permille, min(self.max_permille, pm))

    def permille_to_torque(self, pm: int) -> float:
        return self.cfg.polarity * pm * self.cfg.joint_torque_per_permille

    # -- reception -------------------------------------------------------------------------------
    def on_valid_tpdo(self, number: int, pdo_map) -> None:
        if number == 1:
            raw = self.node.tpdo_values[0x6064]
            if self._last_raw_pos is None:
                self._pos_counts = 0
            else:
                d = (raw - self._last_raw_pos) % 2 ** 32  # 32-bit wrap-around
                self._pos_counts += d - 2 ** 32 if d >= 2 ** 31 else d
            self._last_raw_pos = raw

    def reading(self) -> DriveReading:
        """SI values of the last TPDOs."""
        v = self.node.tpdo_values
        c = self.cfg
        sw = v.get(0x6041, 0)
        return DriveReading(position=c.polarity * self._pos_counts * c.rad_per_count,
                            velocity=c.polarity * v.get(0x606C, 0) * c.rad_s_per_velocity_unit,
                            torque=self.permille_to_torque(v.get(0x6077, 0)), statusword=sw,
                            state=self.node.state, error_code=v.get(0x603F, 0), mode=v.get(0x6061, 0))

    def check_statusword(self) -> Fault | None:
        """A fault if the statusword shows FAULT (reported once until reset)."""
        state = self.node.state
        if state in FAULT_STATES:
            if not self._fault_reported:
                self._fault_reported = True
                code = self.node.tpdo_values.get(0x603F, 0)
                return self.fault("statusword", f"drive in {state}: {error_meaning(code)}", code)
        else:
            self._fault_reported = False
        return None

    # -- commands (sent in RPDO1 before the next SYNC) ---------------------------------------------
    def step_towards_enabled(self) -> bool:
        """Stage the controlword of the next transition towards OPERATION ENABLED; True once there."""
        state = self.node.state
        if state == "OPERATION ENABLED":
            self.controlword = State402.CW_OPERATION_ENABLED
            return True
        if state in FAULT_STATES:
            f = self.fault("statusword", f"cannot enable: drive in {state} "
                                         f"({error_meaning(self.node.tpdo_values.get(0x603F, 0))}); reset the fault")
            raise DriverError(str(f), (f,))
        nxt = ("OPERATION ENABLED" if (state, "OPERATION ENABLED") in State402.TRANSITIONTABLE
               else State402.next_state_indirect(state))
        self.controlword = State402.TRANSITIONTABLE.get((state, nxt), State402.CW_DISABLE_VOLTAGE)
        self.target_permille = 0
        return False

    def stage_fault_reset(self, edge: bool) -> None:
        """Fault reset is the rising edge of controlword bit 7: stage 0 (edge=False) then 0x80."""
        self.controlword = CW_FAULT_RESET if edge else State402.CW_DISABLE_VOLTAGE
        self.target_permille = 0

    def stage_quick_stop(self) -> None:
        self.controlword = State402.CW_QUICK_STOP
        self.target_permille = 0

    def stage_disable(self) -> None:
        self.controlword = State402.CW_DISABLE_VOLTAGE
        self.target_permille = 0

    def stage_torque(self, tau: float) -> float:
        """Stage joint torque ``tau`` (N m); returns the torque actually commanded (quantized)."""
        self.target_permille = self.torque_to_permille(tau)
        return self.permille_to_torque(self.target_permille)

    def transmit(self) -> None:
        """Send RPDO1 (controlword, target torque); the drive applies it at the next SYNC."""
        p = self.node.rpdo_pointers
        pdo_put(p[0x6040], self.controlword)
        pdo_put(p[0x6071], self.target_permille)
        p[0x6040].pdo_parent.transmit()
