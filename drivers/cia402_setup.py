"""Set-up of a CiA 402 drive at boot (``drivers.cia402.CiA402Drive``'s ``DriveSetup`` part): what
the object dictionary must offer, the PDO plan, and the SDO configuration, every step skipped or
refused by name where the dictionary lacks the object.

Heartbeat producer time (0x1017); drive-side protection (the master's heartbeat consumed through
0x1016, abort connection option 0x6007, communication cycle period 0x1006 for SYNC monitoring where
``drives.sync_watchdog``, the RPDO deadline 0x1400:05 of ``drives.rpdo_timeout`` periods); the
configured SDO writes; interpolation period (0x60C2) = control period; 0x6076 rated torque checked
against the configuration (the configuration's value used where the drive has no 0x6076), 0x608F
encoder resolution; mode of operation: cyclic synchronous torque (10) or, where the drive lacks it,
profile torque (4); quick stop option 0x605A (written and read back); PDO mapping
(``drivers.mapping``: planned from the dictionary, fixed mappings used as they are, written, read
back and verified), all synchronous (type 1). The preferred layout:

* RPDO1: controlword 0x6040, target torque 0x6071 (per-mille of rated torque);
* TPDO1: statusword 0x6041, position actual 0x6064 (counts), torque actual 0x6077 (per-mille);
* TPDO2: velocity actual 0x606C, error code 0x603F, mode display 0x6061.

No CiA 402 command words here: they are written only in ``drivers.cia402``.
"""
from __future__ import annotations

import math

from canopen.profiles.p402 import OperationMode
from canopen.sdo import SdoAbortedError

from drivers.mapping import Need, object_name

RPDO_LAYOUT = {1: [0x6040, 0x6071]}
TPDO_LAYOUT = {1: [0x6041, 0x6064, 0x6077], 2: [0x606C, 0x603F, 0x6061]}
RX_NEEDS = [Need(0x6040), Need(0x6071)]
TX_NEEDS = [Need(0x6041), Need(0x6064), Need(0x606C), Need(0x6077, False), Need(0x603F, False),
            Need(0x6061, False)]
TORQUE_MODES = {"CYCLIC SYNCHRONOUS TORQUE": OperationMode.CYCLIC_SYNCHRONOUS_TORQUE,
                "PROFILED TORQUE": OperationMode.PROFILED_TORQUE}


def plan_drive_pdos(od, node_id: int, device: str):
    """Check that dictionary ``od`` describes a drive the loop can command in torque and plan its
    PDOs (``drivers.mapping.plan_pdos``); ``PlanError`` naming the missing object or capability."""
    from drivers.mapping import PlanError, plan_pdos

    modes = supported_torque_modes(od)
    if modes == []:
        raise PlanError(f"{device}: {no_torque_mode(od[0x6502].default)}")
    if 0x6060 not in od:
        raise PlanError(f"{device}: the object dictionary has no {object_name(0x6060)}: the torque mode cannot be "
                        "selected")
    return plan_pdos(od, node_id, device, RX_NEEDS, TX_NEEDS, RPDO_LAYOUT, TPDO_LAYOUT)


def supported_torque_modes(od) -> list[str] | None:
    """Torque modes the dictionary's 0x6502 default declares (None where it gives no value)."""
    if 0x6502 not in od or od[0x6502].default is None:
        return None
    bits = od[0x6502].default
    return [m for m in TORQUE_MODES if bits & OperationMode.SUPPORTED[m]]


def mode_names(bits: int) -> str:
    """'pp, pv, hm, csp' for a 0x6502 value."""
    short = {"PROFILED POSITION": "pp", "VELOCITY": "vl", "PROFILED VELOCITY": "pv", "PROFILED TORQUE": "tq",
             "HOMING": "hm", "INTERPOLATED POSITION": "ip", "CYCLIC SYNCHRONOUS POSITION": "csp",
             "CYCLIC SYNCHRONOUS VELOCITY": "csv", "CYCLIC SYNCHRONOUS TORQUE": "cst"}
    return ", ".join(short[m] for m, b in OperationMode.SUPPORTED.items() if b and bits & b) or "none"


def no_torque_mode(bits: int) -> str:
    return (f"0x6502 supported drive modes = 0x{bits:08X} ({mode_names(bits)}): neither cyclic synchronous torque "
            "(bit 9) nor profile torque (bit 3), so the drive cannot be commanded in torque")


def interpolation_period(period: float) -> tuple[int, int]:
    """0x60C2 (value, index) with value * 10^index = ``period`` s, value <= 255 (ValueError otherwise,
    also for a period that is not a finite number > 0, e.g. 1/rate of a denormal rate)."""
    if not (math.isfinite(period) and 0 < period <= 1.0):
        raise ValueError(f"control period {period:g} s cannot be written as 0x60C2 (value 1..255 x 10^-3..-6 s)")
    for index in range(-3, -7, -1):
        value = period / 10.0 ** index
        if abs(value - round(value)) < 1e-6 and 1 <= round(value) <= 255:
            return int(round(value)), index
    raise ValueError(f"control period {period} s cannot be written as 0x60C2 (value 1..255 x 10^-3..-6 s)")


class DriveSetup:
    """The boot-time configuration of ``CiA402Drive`` (state, SDO access and notes are the drive's)."""

    def configure(self) -> None:
        """SDO configuration, checks, mode of operation and PDO mapping (node PRE-OPERATIONAL)."""
        c = self.cfg
        self.notes = []
        self.sdo_write(0x1017, 0, int(round(c.heartbeat_producer * 1000)))
        self.configure_protection()
        self.configure_quick_stop_option()
        self.max_permille = 32767
        for index, sub, value in c.sdo_config:
            if self.has(index, sub):
                self.sdo_write(index, sub, value)
                continue
            what = "configured write skipped"
            if (index, sub) == (0x6072, 0):
                self.max_permille = min(self.max_permille, int(value))
                what += f"; the driver limits target torque to {int(value)} per-mille itself"
            self.notes.append(f"no {object_name(index, sub)} in the object dictionary: {what}")
        if self.has(0x60C2, 1) and self.has(0x60C2, 2):
            value, index = interpolation_period(self.period)
            self.sdo_write(0x60C2, 1, value)
            self.sdo_write(0x60C2, 2, index)
        if self.has(0x6076):
            rated = self.sdo_read(0x6076) / 1000.0
            if abs(rated - c.rated_torque) > 5e-4:
                raise self.config_error(f"drive reports rated torque 0x6076 = {rated:g} N m, config "
                                        f"'drives.rated_torque' says {c.rated_torque:g} N m")
        else:
            self.notes.append(f"no {object_name(0x6076)} in the object dictionary: per-mille taken of "
                              f"'drives.rated_torque' = {c.rated_torque:g} N m")
        self.rated_torque = c.rated_torque
        if self.has(0x608F, 1) and self.has(0x608F, 2):
            inc, revs = self.sdo_read(0x608F, 1), self.sdo_read(0x608F, 2)
            if revs and inc / revs != c.counts_per_rev:
                raise self.config_error(f"drive reports {inc}/{revs} increments per motor revolution (0x608F), "
                                        f"config 'drives.counts_per_rev' says {c.counts_per_rev}")
        if self.has(0x6072):
            self.max_permille = min(self.max_permille, int(self.sdo_read(0x6072)))
        self.mode = self.select_torque_mode()
        plan = self.static_plan
        self.map_pdos(plan)
        rx = plan.rx.carrying(0x6040)
        self.configure_rpdo_deadline(rx)
        self._fill = {}
        for no, objs in plan.rx.pdos.items():
            for index, sub, _ in objs:
                if index == 0x6060:
                    self._fill[index] = self.mode
                elif index not in (0x6040, 0x6071):
                    self._fill[index] = self.sdo_read(index, sub) if self.has(index, sub) else 0
        self._pos_tpdo = plan.tx.carrying(0x6064)
        self.node.tpdo_values.clear()
        self.node.tpdo_pointers.clear()
        self.node.rpdo_pointers.clear()
        self.node.setup_pdos(upload=False)  # BaseNode402 caches TPDO values / RPDO pointers
        self.hook_tpdos()  # after BaseNode402's cache update, so tpdo_values are fresh here
        self._rpdo_frames = None  # compiled at the first transmit
        self._last_raw_pos = None
        self.stage_disable()

    def configure_protection(self) -> None:
        """Drive-side watchdogs: the drive consumes the master's heartbeat (0x1016), and on its loss,
        on SYNC loss (0x1006 cycle period, where ``drives.sync_watchdog``) or an RPDO deadline miss, applies the abort
        connection option 0x6007."""
        c = self.cfg
        master = getattr(self, "master", None)
        if master is not None:
            node_id, _ = master
            entry = (node_id << 16) | int(math.ceil(c.master_heartbeat_consumer * 1000 - 1e-9))
            self.sdo_write_if_present(0x1016, 1, entry, "the drive does not watch the master's heartbeat and will "
                                                        "not stop by itself if the master dies")
        self.sdo_write_if_present(0x6007, 0, c.abort_connection_option,
                                  "the drive's reaction to a lost master is its own default")
        cycle_us = int(round(self.period * 1e6)) if c.sync_watchdog else 0
        self.sdo_write_if_present(0x1006, 0, cycle_us, "the drive does not watch the SYNC period")

    def configure_quick_stop_option(self) -> None:
        """0x605A quick stop option code = ``drives.quick_stop_option``, read back: with 1-4 a drive
        that quick-stops (on the master's command or by itself) ends in SWITCH ON DISABLED, where no
        controlword but the master's full enable sequence powers it again."""
        want = self.cfg.quick_stop_option
        if not self.sdo_write_if_present(0x605A, 0, want, "the drive's quick stop option is its own default"):
            return
        got = self.sdo_read(0x605A)
        if got != want:
            raise self.config_error(f"quick stop option 0x605A = {want} written, drive reads back {got}")

    def configure_rpdo_deadline(self, rpdo: int | None) -> None:
        """RPDO deadline monitoring (0x1400:05 event timer of the RPDO with the controlword), ms
        (``drives.rpdo_timeout`` periods; 0: off)."""
        if rpdo is None:
            return
        ms = int(math.ceil(self.cfg.rpdo_timeout * self.period * 1000 - 1e-9))
        self.sdo_write_if_present(0x1400 + rpdo - 1, 5, ms, "the drive does not watch its RPDO deadline (event "
                                                            "timer)")

    def select_torque_mode(self) -> int:
        """Write 0x6060 = cyclic synchronous torque where the drive supports it, else profile torque;
        confirmed by 0x6061 where the drive has it."""
        if self.has(0x6502):
            bits = int(self.sdo_read(0x6502))
            candidates = [code for name, code in TORQUE_MODES.items() if bits & OperationMode.SUPPORTED[name]]
            if not candidates:
                raise self.config_error(no_torque_mode(bits))
        else:
            candidates = list(TORQUE_MODES.values())
            self.notes.append(f"no {object_name(0x6502)}: torque modes tried in turn")
        self.sdo_write(0x6071, 0, 0)
        for k, mode in enumerate(candidates):
            try:
                self.node.sdo[0x6060].raw = mode
            except SdoAbortedError as exc:
                if k + 1 < len(candidates):
                    continue
                raise self.config_error(f"the drive refused every torque mode (0x6060 = {mode}: {exc})") from None
            break
        if self.has(0x6061):
            shown = self.sdo_read(0x6061)
            if shown != mode:
                raise self.config_error(f"mode of operation {mode} written, drive shows {shown} (0x6061)")
        else:
            self.notes.append(f"no {object_name(0x6061)}: the mode of operation is not confirmed")
        return mode
