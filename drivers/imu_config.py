"""The serial IMU's configuration and its checks: the ``imu`` section of ``config/robot.yaml``
(``ImuConfig``, ``load_imu_config``), the mounting rotation (sensor -> platform B'', ``check_rotation``),
the output type and rate the device supports and the line's bandwidth (``check_output``,
``check_bandwidth``). The driver is ``drivers.imu``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers import vectornav as vn
from otbot_hw.params import DEFAULT_CONFIG_DIR, ParameterError, read_yaml

DEFAULT_ROBOT_FILE = DEFAULT_CONFIG_DIR / "robot.yaml"
PROTOCOLS = ("vectornav-ascii",)
IMU_OUTPUTS = ("VNIMU", "VNYMR")
#: Bits on the wire per byte: 8N1 framing (start + 8 data + stop).
BITS_PER_BYTE = 10
#: Tolerance on |R R^T - I| and |det R - 1| for a mounting matrix from the config.
ROTATION_TOL = 1e-4



def check_rotation(m, name: str = "mounting", tol: float = ROTATION_TOL) -> np.ndarray:
    """``m`` as a proper rotation matrix (3x3, R R^T = I, det R = +1 within ``tol``),
    re-orthonormalized to the nearest rotation; ValueError naming ``name`` otherwise."""
    try:
        r = np.asarray(m, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 3x3 matrix of numbers") from None
    if r.shape != (3, 3):
        raise ValueError(f"{name} must be a 3x3 matrix, got shape {r.shape}")
    if not np.all(np.isfinite(r)):
        raise ValueError(f"{name} has non-finite entries")
    if np.abs(r).max() > 2.0:  # (a rotation's entries are within [-1, 1]; also keeps r @ r.T finite)
        raise ValueError(f"{name} is not a rotation: entry {float(np.abs(r).max()):.3g} outside [-1, 1]")
    ortho = float(np.abs(r @ r.T - np.eye(3)).max())
    if ortho > tol:
        raise ValueError(f"{name} is not a rotation: |R R^T - I| = {ortho:.3g} > {tol:g}")
    det = float(np.linalg.det(r))
    if abs(det - 1.0) > tol:
        raise ValueError(f"{name} is not a proper rotation: det R = {det:.6g} (a reflection has det -1)")
    u, _, vt = np.linalg.svd(r)
    return u @ vt


def sentence_bytes(output: str) -> int:
    """Length in bytes of one full-scale sentence of ``output`` as the device formats it."""
    big = (-99.999, -99.999, -99.999)
    body = vn.format_imu(output, big, (-9.999999,) * 3, (-9.9999,) * 3, -99.9, 9999.999, (-179.999,) * 3)
    return len(vn.frame(body))


def check_bandwidth(output: str, rate_hz: float, baudrate: int) -> None:
    """ValueError when ``rate_hz`` sentences of ``output`` do not fit in ``baudrate`` (8N1)."""
    need = sentence_bytes(output) * BITS_PER_BYTE * rate_hz
    if need > baudrate:
        raise ValueError(f"{output} at {rate_hz:g} Hz needs {need:.0f} bit/s, more than the "
                         f"{baudrate} baud line carries (the device answers VNERR 12, insufficient baud rate)")


def check_output(output: str, rate_hz: float) -> int:
    """Validate an output type and rate; return the rate as the integer ADOF value (Hz)."""
    if output not in IMU_OUTPUTS:
        raise ValueError(f"output must be one of {', '.join(IMU_OUTPUTS)}, got {output!r}")
    try:
        rate = float(rate_hz)
    except (TypeError, ValueError):
        raise ValueError(f"rate_hz must be a number, got {rate_hz!r}") from None
    if rate not in vn.ASYNC_RATES_HZ:
        raise ValueError(f"rate_hz must be one of {', '.join(map(str, vn.ASYNC_RATES_HZ))} Hz "
                         f"(the device's output frequencies), got {rate_hz!r}")
    return int(rate)


@dataclass(frozen=True)
class ImuConfig:
    """``imu`` section of ``config/robot.yaml``.

    port: serial device path; baudrate (bit/s); protocol ``vectornav-ascii``; output
    VNIMU/VNYMR; rate_hz output frequency (Hz); mounting 3x3 rotation sensor -> B'';
    timeout: watchdog (s).
    """

    port: str
    baudrate: int
    protocol: str
    output: str
    rate_hz: int
    mounting: np.ndarray
    timeout: float


#: keys of the ``imu`` section
IMU_KEYS = ("port", "baudrate", "protocol", "output", "rate_hz", "timeout", "mounting")
#: longest IMU watchdog accepted (s)
MAX_TIMEOUT = 10.0


def load_imu_config(path: str | Path | None = None) -> ImuConfig:
    """Read and validate the ``imu`` section; :class:`ParameterError` names the bad key."""
    p = Path(path) if path is not None else DEFAULT_ROBOT_FILE
    data = read_yaml(p)
    sec = (data or {}).get("imu") if isinstance(data, dict) else None
    if not isinstance(sec, dict):
        raise ParameterError(f"{p}: missing section 'imu'")

    unknown = [k for k in sec if k not in IMU_KEYS]
    if unknown:
        raise ParameterError(f"{p}: 'imu' has unknown key(s) {unknown} (known: {', '.join(IMU_KEYS)})")

    def need(key):
        if key not in sec:
            raise ParameterError(f"{p}: missing key 'imu.{key}'")
        return sec[key]

    port = need("port")
    if not isinstance(port, str) or not port:
        raise ParameterError(f"{p}: 'imu.port' must be a device path, got {port!r}")
    baud = need("baudrate")
    if isinstance(baud, bool) or baud not in vn.BAUD_RATES:
        raise ParameterError(f"{p}: 'imu.baudrate' must be one of {', '.join(map(str, vn.BAUD_RATES))}, got {baud!r}")
    protocol = need("protocol")
    if protocol not in PROTOCOLS:
        raise ParameterError(f"{p}: 'imu.protocol' must be one of {', '.join(PROTOCOLS)}, got {protocol!r}")
    output = need("output")
    rate = need("rate_hz")
    try:
        rate = check_output(output, rate if not isinstance(rate, bool) else None)
    except ValueError as exc:
        key = "output" if output not in IMU_OUTPUTS else "rate_hz"
        raise ParameterError(f"{p}: 'imu.{key}': {exc}") from None
    try:
        check_bandwidth(output, rate, baud)
    except ValueError as exc:
        raise ParameterError(f"{p}: 'imu.rate_hz' with 'imu.baudrate': {exc}") from None
    timeout = sec.get("timeout", 0.5)
    if (isinstance(timeout, bool) or not isinstance(timeout, (int, float))
            or not (np.isfinite(timeout) and 0 < timeout <= MAX_TIMEOUT)):
        raise ParameterError(f"{p}: 'imu.timeout' must be a number of seconds in (0, {MAX_TIMEOUT:g}] (a longer "
                             f"silence is no watchdog), got {timeout!r}")
    mounting = need("mounting")
    if not isinstance(mounting, dict) or "matrix" not in mounting:
        raise ParameterError(f"{p}: missing key 'imu.mounting.matrix' (3x3 rotation, sensor -> platform B'')")
    if set(mounting) != {"matrix"}:
        raise ParameterError(f"{p}: 'imu.mounting' has unknown key(s) {sorted(set(mounting) - {'matrix'})} "
                             f"(known: matrix)")
    rows = mounting["matrix"]
    if (not isinstance(rows, list) or len(rows) != 3
            or not all(isinstance(r, list) and len(r) == 3 for r in rows)
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for r in rows for v in r)):
        raise ParameterError(f"{p}: 'imu.mounting.matrix' must be 3 rows of 3 numbers, got {rows!r}")
    try:
        rot = check_rotation(rows, name="'imu.mounting.matrix'")
    except ValueError as exc:
        raise ParameterError(f"{p}: {exc}") from None
    return ImuConfig(port=port, baudrate=int(baud), protocol=protocol, output=output, rate_hz=rate,
                     mounting=rot, timeout=float(timeout))
