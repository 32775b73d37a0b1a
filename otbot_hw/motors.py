"""Motor torque limits from the hardware configuration (``config/robot.yaml``, section ``motors``)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from otbot_hw.params import DEFAULT_CONFIG_DIR, ParameterError, read_yaml

DEFAULT_ROBOT_FILE = DEFAULT_CONFIG_DIR / "robot.yaml"
MOTORS = ("right_wheel", "left_wheel", "pivot")  # order of u = (tau_r, tau_l, tau_p)


@dataclass(frozen=True)
class MotorLimits:
    """Peak joint torques (N m) for (tau_r, tau_l, tau_p)."""

    max_torque: np.ndarray

    def clamp(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(clamped torques, boolean mask of the motors that were saturated)."""
        u = np.asarray(u, dtype=float)
        clamped = np.clip(u, -self.max_torque, self.max_torque)
        return clamped, clamped != u


def load_motor_limits(path: str | Path | None = None) -> MotorLimits:
    """Read ``motors.<name>.max_torque`` for the three motors; errors name the key."""
    p = Path(path) if path is not None else DEFAULT_ROBOT_FILE
    data = read_yaml(p)
    motors = data.get("motors") if isinstance(data, dict) else None
    if not isinstance(motors, dict):
        raise ParameterError(f"{p}: missing section 'motors'")
    out = []
    unknown = [k for k in motors if k not in MOTORS]
    if unknown:
        raise ParameterError(f"{p}: 'motors' has unknown key(s) {unknown} (known: {', '.join(MOTORS)})")
    for name in MOTORS:
        block = motors.get(name)
        if isinstance(block, dict) and set(block) - {"max_torque"}:
            raise ParameterError(f"{p}: 'motors.{name}' has unknown key(s) {sorted(set(block) - {'max_torque'})} "
                                 f"(known: max_torque)")
        entry = block.get("max_torque") if isinstance(block, dict) else None
        if not isinstance(entry, dict) or "value" not in entry:
            raise ParameterError(f"{p}: missing key 'motors.{name}.max_torque' ({{value, unit: N m}})")
        if set(entry) - {"value", "unit"}:
            raise ParameterError(f"{p}: 'motors.{name}.max_torque' has unknown key(s) "
                                 f"{sorted(set(entry) - {'value', 'unit'})} (known: value, unit)")
        if entry.get("unit") != "N m":
            raise ParameterError(f"{p}: 'motors.{name}.max_torque' unit must be 'N m', got {entry.get('unit')!r}")
        v = entry["value"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0 or not np.isfinite(v):
            raise ParameterError(f"{p}: 'motors.{name}.max_torque' must be a number > 0, got {v!r}")
        out.append(float(v))
    return MotorLimits(max_torque=np.array(out))
