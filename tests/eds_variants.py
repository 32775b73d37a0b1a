"""Object dictionaries derived from the third-party EDS files in ``../shared/eds/`` (test data):
small, named edits of a file written by others, so that the drivers are tried on dictionaries
they were not written against, including ones that can run."""
from __future__ import annotations

import configparser
from pathlib import Path

SHARED_EDS = Path(__file__).resolve().parents[2] / "shared" / "eds"
if not SHARED_EDS.is_dir():  # a worktree under /work/wt/NAME: ../shared is /work/shared
    SHARED_EDS = Path("/work/shared/eds")
CIA402_SLAVE = SHARED_EDS / "ros2_canopen_cia402_slave.eds"
ROBOT_CONTROL_SLAVE = SHARED_EDS / "ros2_canopen_robot_control_cia402_slave.eds"
CST_BIT = 0x200  # 0x6502 bit 9: cyclic synchronous torque


class Eds:
    """An EDS file as an INI document (canopen reads it the same way), edited section by section."""

    def __init__(self, path: Path):
        self.cp = configparser.RawConfigParser()
        self.cp.optionxform = str
        self.cp.read(path)

    def section(self, index: int, sub: int | None = None) -> str:
        name = f"{index:04X}" + (f"sub{sub:X}" if sub is not None else "")
        for s in self.cp.sections():
            if s.upper() == name.upper():
                return s
        raise KeyError(name)

    def get(self, index: int, sub: int | None = None, key: str = "DefaultValue") -> str:
        return self.cp.get(self.section(index, sub), key)

    def set(self, index: int, sub: int | None, key: str, value) -> "Eds":
        self.cp.set(self.section(index, sub), key, str(value))
        return self

    def add_modes(self, bits: int) -> "Eds":
        old = int(self.get(0x6502), 0)
        return self.set(0x6502, None, "DefaultValue", f"0x{old | bits:08X}")

    def add_variable(self, index: int, name: str, data_type: int, access: str = "rw", default: str = "0",
                     pdo: bool = True) -> "Eds":
        sec = f"{index:04X}"
        self.cp.add_section(sec)
        for k, v in (("ParameterName", name), ("ObjectType", "0x7"), ("DataType", f"0x{data_type:04X}"),
                     ("AccessType", access), ("DefaultValue", default), ("PDOMapping", "1" if pdo else "0")):
            self.cp.set(sec, k, v)
        listing = "OptionalObjects"
        n = int(self.cp.get(listing, "SupportedObjects"), 0) + 1
        self.cp.set(listing, "SupportedObjects", str(n))
        self.cp.set(listing, str(n), f"0x{index:04X}")
        return self

    def fix_mapping(self, map_index: int, entries: list[tuple[int, int, int]]) -> "Eds":
        """Make PDO mapping ``map_index`` (0x16xx / 0x1Axx) read-only with ``entries`` (index, sub, bits)."""
        subs = [s for s in self.cp.sections() if s.upper().startswith(f"{map_index:04X}SUB")]
        for s in subs:
            k = int(s[s.upper().index("SUB") + 3:], 16)
            value = len(entries) if k == 0 else (
                (entries[k - 1][0] << 16) | (entries[k - 1][1] << 8) | entries[k - 1][2] if k <= len(entries) else 0)
            self.cp.set(s, "DefaultValue", f"0x{value:08X}" if k else str(value))
            self.cp.set(s, "AccessType", "const" if k == 0 else "ro")
        return self

    def write(self, path: Path) -> Path:
        with open(path, "w") as fh:
            self.cp.write(fh, space_around_delimiters=False)
        return path


def robot_config_with(tmp: Path, eds: Path, extra: dict[str, str] | None = None) -> Path:
    """config/robot.yaml with the drives' EDS replaced by ``eds`` (copied next to it), other text
    replacements from ``extra``; the configuration's own EDS files copied along (the tests' one
    set-up, ``otbot_hw.runtime.daemon_process.config_copy``)."""
    from otbot_hw.runtime.daemon_process import config_copy

    out = config_copy(tmp, {"eds: cia402_torque_drive.eds": f"eds: {eds.name}", **(extra or {})})
    if eds.parent != tmp:
        (tmp / eds.name).write_text(eds.read_text())
    return out


def robot_control_cst(tmp: Path) -> Path:
    """ros2_canopen's robot_control slave with cyclic synchronous torque added to 0x6502 (it has
    0x6071 and 0x6077; no 0x6072, 0x6076, 0x603F, 0x1016)."""
    return Eds(ROBOT_CONTROL_SLAVE).add_modes(CST_BIT).write(tmp / "rc_cst.eds")


def cia402_slave_torque(tmp: Path) -> Path:
    """ros2_canopen's cia402 slave with a target torque 0x6071 and CST added (still no 0x6077
    torque actual, 0x6072, 0x6076, 0x603F, 0x6007)."""
    return (Eds(CIA402_SLAVE).add_modes(CST_BIT).add_variable(0x6071, "Target torque", 0x0003, "rw")
            .write(tmp / "slave_torque.eds"))


def robot_control_fixed(tmp: Path) -> Path:
    """robot_control + CST with fixed (read-only) mappings: RPDO1 = controlword, modes of operation,
    target torque; TPDO1 = statusword, mode display; the other PDOs configurable."""
    return (Eds(ROBOT_CONTROL_SLAVE).add_modes(CST_BIT)
            .fix_mapping(0x1600, [(0x6040, 0, 16), (0x6060, 0, 8), (0x6071, 0, 16)])
            .fix_mapping(0x1A00, [(0x6041, 0, 16), (0x6061, 0, 8)])
            .write(tmp / "rc_fixed.eds"))


def robot_control_fixed_without_torque(tmp: Path) -> Path:
    """robot_control + CST whose RPDO mappings are all fixed as the file gives them (controlword
    with modes of operation, target position or target velocity): no RPDO can carry 0x6071."""
    e = Eds(ROBOT_CONTROL_SLAVE).add_modes(CST_BIT)
    for k in range(4):
        entries = [(int(e.get(0x1600 + k, s), 0) >> 16, 0, int(e.get(0x1600 + k, s), 0) & 0xFF)
                   for s in range(1, int(e.get(0x1600 + k, 0), 0) + 1)]
        e.fix_mapping(0x1600 + k, entries)
    return e.write(tmp / "rc_fixed_no_torque.eds")
