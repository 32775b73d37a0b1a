"""CiA 402 drive in a torque mode, driven through canopen's ``BaseNode402``: the profile's words
(controlwords, states, the master's command per drive), the drive's readings in SI units and its
commands. Its set-up at boot (SDO configuration, PDO plan, mode of operation) is
``drivers.cia402_setup`` (``DriveSetup``).

State handling: the master's command per drive (``commanded``) and the drive's reported state give
each cycle's controlword (``cyclic_controlword``); the controlword values are written here only.

SI units at the API: joint angle phi = polarity * (counts - counts at zero) / (counts_per_rev *
gear_ratio) * 2 pi rad, zeroed at the first TPDO after ``configure`` (the 32-bit counter is
unwrapped, so wrap-around is invisible); joint rate in rad/s from 0x606C in the configured
``drives.velocity_unit`` (counts/s or rpm variants, motor side); joint torque tau = polarity *
gear_ratio * per-mille / 1000 * rated torque (N m); NaN where the drive does not report 0x6077.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import canopen
from canopen.profiles.p402 import BaseNode402, State402

from drivers import pdo_codec
from drivers.cia402_setup import DriveSetup, plan_drive_pdos
from drivers.config import DriveConfig
from drivers.device import CanopenDevice, pdo_bytes, pdo_get, pdo_put
from drivers.faults import DriverError, error_meaning
from otbot_hw.robot import Fault

# Controlwords (CiA 402 §6.3.1, bits 0-3 and 7): written nowhere else in the project.
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_FAULT_RESET = 0x0080
#: What the master commands a drive to be in (``CiA402Drive.commanded``).
DISABLED, ENABLING, ENABLED, QUICK_STOP = "disabled", "enabling", "enabled", "quick stop"
#: The master's way to OPERATION ENABLED, one controlword per SYNC: "enable operation" only from
#: SWITCHED ON (transition 4), never from QUICK STOP ACTIVE (transition 16) or READY TO SWITCH ON.
ENABLE_PATH = {"NOT READY TO SWITCH ON": CW_DISABLE_VOLTAGE, "SWITCH ON DISABLED": CW_SHUTDOWN,
               "READY TO SWITCH ON": CW_SWITCH_ON, "SWITCHED ON": CW_ENABLE_OPERATION,
               "OPERATION ENABLED": CW_ENABLE_OPERATION, "QUICK STOP ACTIVE": CW_DISABLE_VOLTAGE}
#: 0x605A quick stop option codes (CiA 402): 1-4 end in SWITCH ON DISABLED after the stop, 5-8 stay
#: in QUICK STOP ACTIVE (where "enable operation" would re-enable: transition 16), 0 disables at once.
QUICK_STOP_OPTIONS = range(0, 9)


def cyclic_controlword(commanded: str, state: str) -> int:
    """The controlword of one control cycle for a drive the master commands ``commanded`` and that
    last reported CiA 402 ``state``: "enable operation" only to keep a commanded drive in OPERATION
    ENABLED; a drive found elsewhere (stopped by itself: its watchdog, a local fault) gets quick stop
    (in QUICK STOP ACTIVE) or disable voltage, never "enable operation"."""
    if commanded == ENABLED and state == "OPERATION ENABLED":
        return CW_ENABLE_OPERATION
    if commanded == QUICK_STOP or state == "QUICK STOP ACTIVE":
        return CW_QUICK_STOP
    return CW_DISABLE_VOLTAGE


def expected_states(commanded: str) -> tuple[str, ...] | None:
    """States a drive may report while the master commands ``commanded`` (None: any, e.g. on the
    way to OPERATION ENABLED or while disabling, where the statusword lags one SYNC)."""
    if commanded == ENABLED:
        return ("OPERATION ENABLED",)
    if commanded == QUICK_STOP:  # the SYNC before the quick stop applies still shows OPERATION ENABLED
        return ("OPERATION ENABLED", *STOPPED_STATES)
    return None
FAULT_STATES = ("FAULT", "FAULT REACTION ACTIVE")
#: States in which a drive produces no torque: a quick stop or disable is confirmed by these.
STOPPED_STATES = ("QUICK STOP ACTIVE", "SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON",
                  "NOT READY TO SWITCH ON", "FAULT")


class Node402(BaseNode402):
    """``BaseNode402`` that ignores TPDOs of the wrong length instead of decoding garbage, and whose
    ``state`` is worked out once per statusword value (it is asked several times a cycle)."""

    _sw_seen: int | None = None
    _state_seen = "UNKNOWN"

    def on_TPDOs_update_callback(self, mapobject):
        if len(mapobject.data) != pdo_bytes(mapobject):
            return
        for obj in mapobject:
            self.tpdo_values[obj.index] = pdo_get(obj)

    @property
    def state(self) -> str:
        sw = self.tpdo_values.get(0x6041)
        if sw is None:  # not in a TPDO: canopen's SDO fallback
            return BaseNode402.state.fget(self)
        if sw != self._sw_seen:
            self._state_seen = _state_of(sw)
            self._sw_seen = sw
        return self._state_seen

    @state.setter
    def state(self, target: str) -> None:
        BaseNode402.state.fset(self, target)


def _state_of(statusword: int) -> str:
    """CiA 402 state of a statusword (canopen's ``State402.SW_MASK`` table)."""
    for state, (mask, bits) in State402.SW_MASK.items():
        if statusword & mask == bits:
            return state
    return "UNKNOWN"


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


class CiA402Drive(DriveSetup, CanopenDevice):
    """One joint drive (configuration ``cfg``) on ``network``."""

    node_class = Node402

    def __init__(self, network: canopen.Network, cfg: DriveConfig, period: float, tracker, on_fault):
        super().__init__(network, cfg.name, cfg.node_id, cfg.eds, tracker, on_fault)
        self.cfg = cfg
        self.period = period
        self.mode: int | None = None
        self.max_permille = 32767
        self.rated_torque = cfg.rated_torque  # N m, motor side
        self.controlword = CW_DISABLE_VOLTAGE
        self.commanded = DISABLED
        self.target_permille = 0
        self._last_raw_pos: int | None = None
        self._pos_counts = 0  # unwrapped counts since the first reading
        self._fault_reported = False
        self._pos_tpdo: int | None = None
        self._fill: dict[int, int] = {}  # values of RPDO objects the loop does not command
        # Refuse, before any bus traffic, what the dictionary cannot do.
        from drivers.mapping import PlanError

        try:
            self.static_plan = plan_drive_pdos(self.node.object_dictionary, self.node_id,
                                               f"{self.name} (node {self.node_id})")
        except PlanError as exc:
            raise self.config_error(str(exc).split(": ", 1)[1]) from None

    # -- units -----------------------------------------------------------------------------------
    def torque_to_permille(self, tau: float) -> int:
        """Joint torque (N m) -> target torque per-mille, rounded and limited to 0x6072."""
        c = self.cfg
        pm = int(round(tau / (c.polarity * c.joint_torque_per_permille)))
        return max(-self.max_permille, min(self.max_permille, pm))

    def permille_to_torque(self, pm: int) -> float:
        return self.cfg.polarity * pm * self.cfg.joint_torque_per_permille

    def _carried(self) -> tuple:
        """(TPDO with the statusword, with torque actual, with error code) of the current plan;
        worked out once per plan (asked every cycle)."""
        plan = self.plan
        if self._carried_plan is not plan:
            self._carried_for = ((None, None, None) if plan is None else
                                 (plan.tx.carrying(0x6041), plan.tx.carrying(0x6077), plan.tx.carrying(0x603F)))
            self._carried_plan = plan
        return self._carried_for

    _carried_plan = None
    _carried_for = (None, None, None)

    @property
    def status_tpdo(self) -> int | None:
        """Number of the TPDO that carries the statusword."""
        return self._carried()[0]

    @property
    def reports_torque(self) -> bool:
        return self._carried()[1] is not None

    # -- reception -------------------------------------------------------------------------------
    def on_valid_tpdo(self, number: int, pdo_map) -> None:
        if number == self._pos_tpdo:
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
        _, torque_tpdo, error_tpdo = self._carried()
        torque = self.permille_to_torque(v.get(0x6077, 0)) if torque_tpdo is not None else math.nan
        return DriveReading(position=c.polarity * self._pos_counts * c.rad_per_count,
                            velocity=c.polarity * v.get(0x606C, 0) * c.rad_s_per_velocity_unit,
                            torque=torque, statusword=sw, state=self.node.state,
                            error_code=v.get(0x603F, 0) if error_tpdo is not None else self.last_emcy_code,
                            mode=v.get(0x6061, 0))

    @property
    def state(self) -> str:
        """CiA 402 state of the last statusword received (in a TPDO)."""
        return self.node.state

    def error_code(self) -> int | None:
        """0x603F from the last TPDO; where the drive does not send it, the last EMCY code (or None)."""
        if self._carried()[2] is not None:
            return self.node.tpdo_values.get(0x603F, 0)
        return self.last_emcy_code

    def error_text(self) -> str:
        code = self.error_code()
        return error_meaning(code) if code is not None else "error code unknown (the drive sends no 0x603F)"

    def check_statusword(self) -> Fault | None:
        """A fault if the statusword shows FAULT (reported once until reset)."""
        state = self.node.state
        if state in FAULT_STATES:
            if not self._fault_reported:
                self._fault_reported = True
                return self.fault("statusword", f"drive in {state}: {self.error_text()}", self.error_code())
        else:
            self._fault_reported = False
        return None

    # -- commands (sent in RPDO1 before the next SYNC) ---------------------------------------------
    def step_towards_enabled(self) -> bool:
        """Stage the controlword of the next transition towards OPERATION ENABLED (``ENABLE_PATH``);
        True once there (the drive is then commanded ``ENABLED``)."""
        state = self.node.state
        self.target_permille = 0
        if state == "OPERATION ENABLED":
            self.commanded = ENABLED
            self.controlword = CW_ENABLE_OPERATION
            return True
        if state in FAULT_STATES:
            f = self.fault("statusword", f"cannot enable: drive in {state} ({self.error_text()}); reset the fault")
            raise DriverError(str(f), (f,))
        self.commanded = ENABLING
        self.controlword = ENABLE_PATH.get(state, CW_DISABLE_VOLTAGE)
        return False

    def unexpected_state(self) -> str | None:
        """Why the last reported state does not fit the master's command (None: it fits)."""
        allowed = expected_states(self.commanded)
        state = self.node.state
        if allowed is None or state in allowed:
            return None
        return f"drive left OPERATION ENABLED without a command: now {state}"

    def stage_cyclic(self, tau: float) -> float:
        """Stage this cycle's controlword (``cyclic_controlword`` of the command and the reported
        state) and joint torque ``tau`` (N m; zero unless the word keeps the drive enabled); returns
        the torque actually commanded."""
        self.controlword = cyclic_controlword(self.commanded, self.node.state)
        self.target_permille = self.torque_to_permille(tau) if self.controlword == CW_ENABLE_OPERATION else 0
        return self.permille_to_torque(self.target_permille)

    def stage_fault_reset(self, edge: bool) -> None:
        """Fault reset is the rising edge of controlword bit 7: stage 0 (edge=False) then 0x80."""
        self.commanded = DISABLED
        self.controlword = CW_FAULT_RESET if edge else CW_DISABLE_VOLTAGE
        self.target_permille = 0

    def stage_quick_stop(self) -> None:
        self.commanded = QUICK_STOP
        self.controlword = CW_QUICK_STOP
        self.target_permille = 0

    def stage_disable(self) -> None:
        self.commanded = DISABLED
        self.controlword = CW_DISABLE_VOLTAGE
        self.target_permille = 0

    def stage_torque(self, tau: float) -> float:
        """Stage joint torque ``tau`` (N m); returns the torque actually commanded (quantized)."""
        self.target_permille = self.torque_to_permille(tau)
        return self.permille_to_torque(self.target_permille)

    def transmit(self) -> None:
        """Send the RPDO(s) with controlword and target torque; the drive applies them at the next SYNC.
        Each RPDO is packed by its precompiled layout (``drivers.pdo_codec``) where one struct
        expresses it, else by canopen's variables."""
        frames = self._rpdo_frames
        if frames is None:
            frames = self._rpdo_frames = self._compile_rpdos()
        if frames:
            send = self.network.send_message
            for m, layout in frames:
                values = [self.controlword if i == 0x6040 else self.target_permille if i == 0x6071 else self._fill[i]
                          for i in layout.indices]
                data = layout.encode(values)
                m.data[:] = data  # canopen's view of the map stays current
                send(m.cob_id, data)
            return
        p = self.node.rpdo_pointers
        pdo_put(p[0x6040], self.controlword)
        pdo_put(p[0x6071], self.target_permille)
        for index, value in self._fill.items():
            pdo_put(p[index], value)
        parents = {id(p[0x6040].pdo_parent): p[0x6040].pdo_parent, id(p[0x6071].pdo_parent): p[0x6071].pdo_parent}
        for m in parents.values():
            m.transmit()

    _rpdo_frames: list | None = None

    def _compile_rpdos(self) -> list:
        """[(PdoMap, PdoLayout)] of the RPDOs carrying controlword and target torque, [] when one of
        them cannot be packed by one struct or carries an object the driver does not fill."""
        p = self.node.rpdo_pointers
        maps = {id(p[i].pdo_parent): p[i].pdo_parent for i in (0x6040, 0x6071)}
        frames = []
        for m in maps.values():
            layout = pdo_codec.compile_map(m)
            if layout is None or any(i not in (0x6040, 0x6071) and i not in self._fill for i in layout.indices):
                return []
            frames.append((m, layout))
        return frames

