"""Hardware configuration of the drivers (``config/robot.yaml``: bus, drives, pivot_encoder; the
``imu`` section is read by ``drivers.imu_config.load_imu_config``).

Every error is a ``ParameterError`` naming the file and the key (the CLI exits with code 2).
Quantities with units are written ``{value: V, unit: U}`` as in the ``motors`` section.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drivers.config_reader import ConfigReader
from otbot_hw.motors import DEFAULT_ROBOT_FILE, MOTORS, MotorLimits, load_motor_limits
from otbot_hw.params import ParameterError, read_yaml

JOINTS = MOTORS  # ("right_wheel", "left_wheel", "pivot"): order of u and of the joint angles
VELOCITY_UNITS = ("counts/s", "rpm", "0.1 rpm", "0.001 rpm")  # of 0x606C, motor side
#: 0x6007 abort connection option codes (CiA 402): what a drive does when it loses the master.
ABORT_OPTIONS = {"no_action": 0, "fault": 1, "disable_voltage": 2, "quick_stop": 3}


#: Longest wait for a node's boot-up message (s).
MAX_BOOT_TIMEOUT = 60.0
#: Heartbeat times (ms) go to 0x1016 / 0x1017, UNSIGNED16.
MAX_HEARTBEAT_MS = (65535.0, "0x1016/0x1017 hold at most 65535 ms")
#: Largest gear ratio (motor or encoder revolutions per joint revolution) accepted.
MAX_GEAR_RATIO = (1e5, "no gearbox reduces more")
UNSIGNED32 = 2 ** 32 - 1
#: Lockstep runs: how long the master waits for the plant's answer to a SYNC (s).
LOCKSTEP_TIMEOUT = 0.25
#: Lockstep runs: SDO answers are awaited this long (s) while booting (a loaded machine can hold a
#: simulated slave's answer longer than canopen's 0.3 s).
LOCKSTEP_SDO_TIMEOUT = 1.0
#: Lockstep runs: heartbeat consumer times (both ways) are at least this (s): no real-time deadline
#: is at stake, and a loaded machine must not trip them.
LOCKSTEP_HEARTBEAT = 0.5
#: Lockstep runs: the master waits at least this long (s) for the simulated IMU's sample of a SYNC
#: (the plant publishes it when it has stepped; a loaded machine can hold that past imu.timeout).
LOCKSTEP_IMU_TIMEOUT = 1.0


@dataclass(frozen=True)
class BusConfig:
    """python-can bus and the control cycle: interface, channel, bitrate (bit/s), control_rate (Hz),
    boot_timeout (s), options (extra ``can.Bus`` keyword arguments).

    tpdo_timeout: a device whose TPDO is missing at this many consecutive SYNCs is faulted (periods);
    reaction_timeout: on a fault, SYNC keeps running at most this many periods for every drive still
    on the bus to confirm its quick stop, then the ones that did not get NMT STOP (periods);
    master_node_id / master_heartbeat: the heartbeat the master produces (COB-ID 0x700 + ID, every s),
    which the drives consume (0x1016); loop_liveness: while the drives are enabled, the master's
    heartbeat is withheld once the control loop has not run a cycle (``read``/``write``) for this many
    periods, so every drive's heartbeat watchdog fires even if the process's other threads live on.
    """

    interface: str
    channel: str
    bitrate: int
    control_rate: float
    tpdo_timeout: int = 2
    boot_timeout: float = 2.0
    options: dict = field(default_factory=dict)
    reaction_timeout: int = 2
    master_node_id: int = 127
    master_heartbeat: float = 0.02
    loop_liveness: int = 3

    @property
    def period(self) -> float:
        """Control (SYNC) period, s."""
        return 1.0 / self.control_rate

    def can_kwargs(self) -> dict:
        """Keyword arguments for ``can.Bus``."""
        kw = {"interface": self.interface, "channel": self.channel, **self.options}
        if self.interface != "virtual":
            kw.setdefault("bitrate", self.bitrate)
        return kw


@dataclass(frozen=True)
class DriveConfig:
    """One CiA 402 drive: node_id, EDS path, counts_per_rev (motor), gear_ratio, polarity (+1/-1),
    rated_torque (N m, motor side, 0x6076; used as is where the drive has no 0x6076), heartbeat
    producer/consumer times (s), SDO writes, max_torque (N m, joint side, from ``motors``),
    velocity_unit of 0x606C (motor side, one of ``VELOCITY_UNITS``).

    Drive-side protection, written by SDO at boot: master_heartbeat_consumer (s, 0x1016),
    sync_watchdog (0x1006 = the control period: the drive watches SYNC; False: 0, off), rpdo_timeout
    (periods, RPDO deadline 0x1400:05; 0: off), abort_connection_option
    (0x6007: what the drive does when the master's heartbeat, SYNC or RPDOs stop), quick_stop_option
    (0x605A, CiA 402 code 0-8; 2: quick stop ramp, then SWITCH ON DISABLED)."""

    name: str
    node_id: int
    eds: Path
    counts_per_rev: int
    gear_ratio: float
    polarity: int
    rated_torque: float
    heartbeat_producer: float
    heartbeat_consumer: float
    sdo_config: tuple = ()
    max_torque: float = float("inf")
    velocity_unit: str = "counts/s"
    master_heartbeat_consumer: float = 0.1
    rpdo_timeout: int = 3
    abort_connection_option: int = 3
    quick_stop_option: int = 2
    sync_watchdog: bool = True

    @property
    def rad_s_per_velocity_unit(self) -> float:
        """Joint rate (rad/s) of one unit of 0x606C (sign excluded)."""
        motor = {"counts/s": 2 * np.pi / self.counts_per_rev, "rpm": 2 * np.pi / 60,
                 "0.1 rpm": 2 * np.pi / 600, "0.001 rpm": 2 * np.pi / 60000}[self.velocity_unit]
        return motor / self.gear_ratio

    @property
    def rad_per_count(self) -> float:
        """Joint angle per motor encoder count, rad (sign excluded)."""
        return 2 * np.pi / (self.counts_per_rev * self.gear_ratio)

    @property
    def joint_torque_per_permille(self) -> float:
        """Joint torque of one per-mille of rated motor torque, N m (sign excluded)."""
        return self.rated_torque * self.gear_ratio / 1000.0


@dataclass(frozen=True)
class EncoderConfig:
    """Where phi_p comes from: ``source`` "encoder" (CiA 406 device) or "drive" (pivot motor encoder).

    offset (counts at phi_p = 0), direction (+1/-1), gear_ratio (encoder rev per pivot rev),
    heartbeat producer/consumer (s); node_id and eds only for the encoder source.
    """

    source: str
    node_id: int | None = None
    eds: Path | None = None
    offset: int = 0
    direction: int = 1
    gear_ratio: float = 1.0
    heartbeat_producer: float = 0.05
    heartbeat_consumer: float = 0.2


@dataclass(frozen=True)
class RobotConfig:
    """The whole hardware configuration."""

    bus: BusConfig
    drives: tuple[DriveConfig, DriveConfig, DriveConfig]
    pivot_encoder: EncoderConfig
    imu: object | None  # drivers.imu_config.ImuConfig (the imu section), None without one
    limits: MotorLimits
    path: Path

    def replace_bus(self, **kw) -> "RobotConfig":
        """A copy with some bus fields changed (e.g. control_rate from the command line)."""
        from dataclasses import replace

        return replace(self, bus=replace(self.bus, **kw))

    def unpaced(self) -> "RobotConfig":
        """A copy whose drives watch neither the SYNC period (0x1006) nor their RPDO deadline
        (0x1400:05): for a bus whose SYNCs keep no period (lockstep with a simulated plant)."""
        from dataclasses import replace

        return replace(self, drives=tuple(replace(d, sync_watchdog=False, rpdo_timeout=0) for d in self.drives))

    def relaxed(self, seconds: float) -> "RobotConfig":
        """A copy whose heartbeat consumer times (the master's of each node, each drive's of the
        master) and the loop's liveness (``bus.loop_liveness``) are at least ``seconds``: for lockstep
        runs against a simulated plant, where no real-time deadline is at stake and a loaded machine
        must not trip them."""
        from dataclasses import replace

        drives = tuple(replace(d, heartbeat_consumer=max(seconds, d.heartbeat_consumer),
                               master_heartbeat_consumer=max(seconds, d.master_heartbeat_consumer))
                       for d in self.drives)
        enc = replace(self.pivot_encoder, heartbeat_consumer=max(seconds, self.pivot_encoder.heartbeat_consumer))
        # and the loop's liveness: a lockstep cycle held up that long by a loaded machine is no stall
        liveness = max(self.bus.loop_liveness, int(np.ceil(seconds / self.bus.period - 1e-9)))
        return replace(self, drives=drives, pivot_encoder=enc, bus=replace(self.bus, loop_liveness=liveness))

    def node_ids(self) -> list[int]:
        ids = [d.node_id for d in self.drives]
        if self.pivot_encoder.source == "encoder":
            ids.append(self.pivot_encoder.node_id)
        return ids


def load_robot_config(path: str | Path | None = None) -> RobotConfig:
    """Read and validate bus, drives, pivot_encoder, imu and motors from ``path`` (default config/robot.yaml)."""
    p = Path(path) if path is not None else DEFAULT_ROBOT_FILE
    data = read_yaml(p)
    if not isinstance(data, dict):
        raise ParameterError(f"{p}: expected a mapping of sections, got {type(data).__name__}")
    r = ConfigReader(p)
    limits = load_motor_limits(p)

    b = r.section(data, "bus")
    r.only(b, "bus", ("interface", "channel", "bitrate", "control_rate", "tpdo_timeout", "reaction_timeout",
                      "boot_timeout", "master_node_id", "master_heartbeat", "loop_liveness", "options"))
    iface = r.raw(b, "interface", "bus.interface")
    chan = r.raw(b, "channel", "bus.channel")
    import can

    if not isinstance(iface, str) or iface not in can.VALID_INTERFACES:
        raise r.err("bus.interface", f"must be a python-can interface ({', '.join(sorted(can.VALID_INTERFACES))}), "
                                     f"got {iface!r}")
    if not isinstance(chan, (str, int)) or chan == "":
        raise r.err("bus.channel", f"must be a channel name, got {chan!r}")
    options = r.raw(b, "options", "bus.options", {}) or {}
    if not isinstance(options, dict):
        raise r.err("bus.options", f"must be a mapping, got {options!r}")
    rate = r.number(b, "control_rate", "bus.control_rate", "Hz")
    master_id = r.number(b, "master_node_id", "bus.master_node_id", None, default=127, integer=True)
    if not 1 <= master_id <= 127:
        raise r.err("bus.master_node_id", f"must be a CANopen node ID 1..127, got {master_id}")
    bus = BusConfig(interface=iface, channel=str(chan),
                    bitrate=r.number(b, "bitrate", "bus.bitrate", "bit/s", integer=True),
                    control_rate=rate,
                    tpdo_timeout=r.periods(b, "tpdo_timeout", "bus.tpdo_timeout", rate, default=2),
                    boot_timeout=r.number(b, "boot_timeout", "bus.boot_timeout", "s", default=2.0,
                                          maximum=(MAX_BOOT_TIMEOUT, "a node boots in seconds")),
                    options=dict(options),
                    reaction_timeout=r.periods(b, "reaction_timeout", "bus.reaction_timeout", rate, default=2),
                    master_node_id=master_id,
                    master_heartbeat=r.number(b, "master_heartbeat", "bus.master_heartbeat", "ms", default=20.0,
                                              maximum=MAX_HEARTBEAT_MS) / 1000,
                    loop_liveness=r.periods(b, "loop_liveness", "bus.loop_liveness", rate, default=3))

    d = r.section(data, "drives")
    r.only(d, "drives", ("eds", "counts_per_rev", "velocity_unit", "rated_torque", "heartbeat_producer",
                         "heartbeat_consumer", "master_heartbeat_consumer", "sync_watchdog", "rpdo_timeout",
                         "abort_connection_option", "quick_stop_option", "sdo_config") + tuple(JOINTS))
    eds = r.eds(d, "drives.eds")
    cpr = r.number(d, "counts_per_rev", "drives.counts_per_rev", None, integer=True,
                   maximum=(UNSIGNED32, "0x608F:01 is UNSIGNED32"))
    rated = r.number(d, "rated_torque", "drives.rated_torque", "N m",
                     maximum=(UNSIGNED32 / 1000, "0x6076 is UNSIGNED32 mN m"))
    hb_p = r.number(d, "heartbeat_producer", "drives.heartbeat_producer", "ms", maximum=MAX_HEARTBEAT_MS) / 1000
    hb_c = r.number(d, "heartbeat_consumer", "drives.heartbeat_consumer", "ms", maximum=MAX_HEARTBEAT_MS) / 1000
    if hb_c <= hb_p:
        raise r.err("drives.heartbeat_consumer", f"({hb_c * 1000:g} ms) must exceed heartbeat_producer "
                                                 f"({hb_p * 1000:g} ms)")
    sdo = _sdo_list(r, d.get("sdo_config", []), "drives.sdo_config", eds)
    vunit = r.raw(d, "velocity_unit", "drives.velocity_unit", "counts/s")
    if vunit not in VELOCITY_UNITS:
        raise r.err("drives.velocity_unit", f"must be one of {', '.join(VELOCITY_UNITS)}, got {vunit!r}")
    mhb_c = r.number(d, "master_heartbeat_consumer", "drives.master_heartbeat_consumer", "ms", default=100.0) / 1000
    if mhb_c <= bus.master_heartbeat:
        raise r.err("drives.master_heartbeat_consumer", f"({mhb_c * 1000:g} ms) must exceed bus.master_heartbeat "
                                                        f"({bus.master_heartbeat * 1000:g} ms)")
    if mhb_c > 65.535:
        raise r.err("drives.master_heartbeat_consumer", f"({mhb_c * 1000:g} ms) must fit 0x1016 (at most 65535 ms)")
    rpdo_timeout = r.periods(d, "rpdo_timeout", "drives.rpdo_timeout", rate, default=3)
    sync_watchdog = r.raw(d, "sync_watchdog", "drives.sync_watchdog", True)
    if not isinstance(sync_watchdog, bool):
        raise r.err("drives.sync_watchdog", f"must be true or false (0x1006 = the control period, or 0: off), "
                                            f"got {sync_watchdog!r}")
    abort = r.raw(d, "abort_connection_option", "drives.abort_connection_option", "quick_stop")
    if not isinstance(abort, str) or abort not in ABORT_OPTIONS:
        raise r.err("drives.abort_connection_option", f"must be one of {', '.join(ABORT_OPTIONS)}, got {abort!r}")
    qso = r.raw(d, "quick_stop_option", "drives.quick_stop_option", 2)
    if isinstance(qso, bool) or not isinstance(qso, int) or not 0 <= qso <= 8:
        raise r.err("drives.quick_stop_option", f"must be a CiA 402 quick stop option code 0..8 (0x605A; 2: quick "
                                                f"stop ramp, then SWITCH ON DISABLED), got {qso!r}")
    drives = []
    for k, name in enumerate(JOINTS):
        j = r.section(d, f"drives.{name}")
        r.only(j, f"drives.{name}", ("node_id", "gear_ratio", "polarity"))
        drives.append(DriveConfig(
            name=name, node_id=r.node_id(j, f"drives.{name}"), eds=eds, counts_per_rev=cpr,
            gear_ratio=r.number(j, "gear_ratio", f"drives.{name}.gear_ratio", None, maximum=MAX_GEAR_RATIO),
            polarity=r.sign(j, "polarity", f"drives.{name}.polarity"), rated_torque=rated,
            heartbeat_producer=hb_p, heartbeat_consumer=hb_c, sdo_config=sdo,
            max_torque=float(limits.max_torque[k]), velocity_unit=vunit, master_heartbeat_consumer=mhb_c,
            rpdo_timeout=rpdo_timeout, abort_connection_option=ABORT_OPTIONS[abort], quick_stop_option=qso,
            sync_watchdog=sync_watchdog))

    e = r.section(data, "pivot_encoder")
    r.only(e, "pivot_encoder", ("source", "node_id", "eds", "offset", "direction", "gear_ratio", "heartbeat_producer",
                                "heartbeat_consumer"))
    source = r.raw(e, "source", "pivot_encoder.source")
    if source not in ("encoder", "drive"):
        raise r.err("pivot_encoder.source", f"must be 'encoder' or 'drive', got {source!r}")
    if source == "encoder":
        e_hb_p = r.number(e, "heartbeat_producer", "pivot_encoder.heartbeat_producer", "ms",
                          maximum=MAX_HEARTBEAT_MS) / 1000
        e_hb_c = r.number(e, "heartbeat_consumer", "pivot_encoder.heartbeat_consumer", "ms",
                          maximum=MAX_HEARTBEAT_MS) / 1000
        if e_hb_c <= e_hb_p:
            raise r.err("pivot_encoder.heartbeat_consumer", "must exceed heartbeat_producer")
        enc = EncoderConfig(source=source, node_id=r.node_id(e, "pivot_encoder"),
                            eds=r.eds(e, "pivot_encoder.eds"),
                            offset=_offset(r, e),
                            direction=r.sign(e, "direction", "pivot_encoder.direction"),
                            gear_ratio=r.number(e, "gear_ratio", "pivot_encoder.gear_ratio", None, default=1.0,
                                                maximum=MAX_GEAR_RATIO),
                            heartbeat_producer=e_hb_p, heartbeat_consumer=e_hb_c)
    else:
        enc = EncoderConfig(source="drive")

    imu = None
    if data.get("imu") is not None:
        from drivers.imu_config import load_imu_config

        imu = load_imu_config(p)
    ids = [dc.node_id for dc in drives] + ([enc.node_id] if enc.source == "encoder" else []) + [bus.master_node_id]
    if len(set(ids)) != len(ids):
        raise ParameterError(f"{p}: node IDs must be distinct, got {ids} (drives.*.node_id, pivot_encoder.node_id, "
                             f"bus.master_node_id)")
    return RobotConfig(bus=bus, drives=tuple(drives), pivot_encoder=enc, imu=imu, limits=limits, path=p)


def _offset(r: ConfigReader, e: dict) -> int:
    """pivot_encoder.offset: counts >= 0 within UNSIGNED32 (the device's own range, 0x6002, is checked at
    boot)."""
    v = r.number(e, "offset", "pivot_encoder.offset", "counts", positive=False, integer=True,
                 maximum=(UNSIGNED32, "an absolute position is UNSIGNED32"))
    if v < 0:
        raise r.err("pivot_encoder.offset", f"must be a position >= 0 counts (0x6004), got {v}")
    return v


def _sdo_list(r: ConfigReader, items, name: str, eds: Path) -> tuple:
    """[index, subindex, value] writes (no PDO object), each value within its object's data type where the
    drive's EDS has the object."""
    if not isinstance(items, list):
        raise r.err(name, f"must be a list of [index, subindex, value], got {items!r}")
    out = []
    od = _import_od(r, eds, name) if items else None
    for k, it in enumerate(items):
        if (not isinstance(it, list) or len(it) != 3
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in it)):
            raise r.err(f"{name}[{k}]", f"must be [index, subindex, value] integers, got {it!r}")
        idx, sub, val = it
        if not (0x1000 <= idx <= 0xFFFF and 0 <= sub <= 0xFF):
            raise r.err(f"{name}[{k}]", f"index 0x{idx:X} / subindex {sub} out of range")
        if 0x1400 <= idx <= 0x1BFF:
            raise r.err(f"{name}[{k}]", f"0x{idx:04X} is a PDO object: the driver maps PDOs itself")
        var = od.get_variable(idx, sub)
        try:  # (an object the EDS lacks is the drive's to refuse at boot, after its more basic checks)
            if var is not None:
                var.encode_raw(val)
        except (ValueError, TypeError, OverflowError):
            raise r.err(f"{name}[{k}]", f"{val} does not fit 0x{idx:04X}:{sub:02X} {var.name!r} (data type "
                                        f"0x{var.data_type:04X} in {eds.name})") from None
        out.append((idx, sub, val))
    return tuple(out)


def _import_od(r: ConfigReader, eds: Path, name: str):
    import canopen

    try:
        return canopen.import_od(str(eds))
    except Exception as exc:  # noqa: BLE001 -- canopen raises many kinds on a malformed file
        raise r.err(name, f"cannot check the writes against {eds}: {exc}") from None
