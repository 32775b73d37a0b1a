"""CANopen error codes and their meanings, and ``DriverError`` (the fault record itself,
``otbot_hw.robot.Fault``, belongs to the ``Robot`` interface).

Error codes are the CiA 301 / CiA 402 EMCY error codes (also found in a drive's 0x603F and
0x1003); ``error_meaning`` names the specific code where the profile defines it and falls
back to the error class (``canopen.emcy.EmcyError``) otherwise.
"""
from __future__ import annotations

from canopen.emcy import EmcyError

from otbot_hw.params import ParameterError
from otbot_hw.robot import RobotError

#: Specific error codes of CiA 301 / CiA 402 (the classes are in canopen's EmcyError).
ERROR_CODES: dict[int, str] = {
    0x0000: "no error",
    0x1000: "generic error",
    0x2310: "continuous over-current",
    0x2320: "short circuit or earth leakage",
    0x2330: "earth leakage",
    0x2340: "short circuit",
    0x3110: "mains over-voltage",
    0x3120: "mains under-voltage",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4110: "excess ambient temperature",
    0x4210: "excess device temperature",
    0x4310: "excess drive temperature",
    0x4410: "excess supply temperature",
    0x5112: "supply low voltage",
    0x5530: "non-volatile memory error",
    0x6010: "software reset (watchdog)",
    0x6320: "parameter error",
    0x7121: "motor blocked",
    0x7305: "incremental sensor 1 fault",
    0x7310: "speed sensor fault",
    0x7320: "position sensor fault",
    0x8100: "communication error (SYNC timeout)",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8150: "CAN-ID collision",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8230: "DAM MPDO not processed, destination object not available",
    0x8240: "unexpected SYNC data length",
    0x8250: "RPDO timeout",
    0x8611: "following error",
    0x8612: "reference limit",
    0xFF00: "device specific",
}


def error_meaning(code: int) -> str:
    """Meaning of a CANopen error code: the specific entry, else the error class, else 'unknown'."""
    if code in ERROR_CODES:
        return ERROR_CODES[code]
    cls = EmcyError(code, 0, b"", 0.0).get_desc()
    return f"{cls.lower()} error (0x{code:04X})" if cls else f"unknown error 0x{code:04X}"


class DriverError(RobotError):
    """A driver operation failed (boot, configuration, enabling); ``faults`` says why."""


class DeviceConfigError(DriverError, ParameterError):
    """A device cannot be run as the configuration asks: its object dictionary lacks an object or
    a capability the loop needs, it refused a configuration write, or its PDO mapping read back
    does not carry what the loop needs. Bad input (exit code 2), raised before any motion."""
