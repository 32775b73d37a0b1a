"""Where effects act, from the robot configuration (``config/robot.yaml``).

Two places matter to the catalog: the passive casters (caster drag acts at their contact
points) and the IMU (a lever arm from the pivot adds tangential and centripetal
accelerations). Both are hardware facts, so they live beside the IMU mounting rotation in
the hardware configuration, not among the identified model parameters of
``config/otbot.yaml`` (whose reader accepts exactly the paper's parameters):

.. code-block:: yaml

    casters:                      # optional: one to four contact points in the chassis frame B' (m)
      - {x: {value: 0.35, unit: m}, y: {value: 0.12, unit: m}}
      - {x: {value: 0.35, unit: m}, y: {value: -0.12, unit: m}}
    imu:
      mounting:
        position: {x: {value: 0.0, unit: m}, y: {value: 0.0, unit: m}}   # optional, in B'' (m)

Absent keys mean "not known": the diagnosis then fits the position (one caster at
(x_c1, y_c1); the IMU lever arm (d_x, d_y)) and reports it with its uncertainty, or as
undetermined when the data cannot fix it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from otbot_hw.model.effects import MAX_CASTERS
from otbot_hw.params import ParameterError, read_yaml

POSITION_LIMIT = 1.0  # m: |x|, |y| of a caster or of the IMU beyond this is not on Otbot


@dataclass(frozen=True)
class EffectGeometry:
    """Caster contacts (B', m; empty = not configured) and IMU position (B'', m; None = not configured)."""

    casters: tuple[tuple[float, float], ...] = ()
    imu_position: tuple[float, float] | None = None
    source: str = ""

    @property
    def casters_configured(self) -> bool:
        return bool(self.casters)

    def effect_values(self) -> dict[str, float]:
        """Effect-vector entries the configuration fixes (``ExtendedModel.with_values``)."""
        out: dict[str, float] = {}
        if self.casters:
            out["n_cst"] = float(len(self.casters))
            for i, (x, y) in enumerate(self.casters, start=1):
                out[f"x_c{i}"], out[f"y_c{i}"] = x, y
        if self.imu_position is not None:
            out["d_x"], out["d_y"] = self.imu_position
        return out

    def to_dict(self) -> dict:
        return {"source": self.source, "casters": [list(c) for c in self.casters] or None,
                "imu_position": None if self.imu_position is None else list(self.imu_position)}


def _length(source: str, key: str, entry: Any) -> float:
    if not isinstance(entry, dict) or "value" not in entry:
        raise ParameterError(f"{source}: '{key}' must be a mapping {{value, unit: m}}")
    if entry.get("unit") != "m":
        raise ParameterError(f"{source}: '{key}' unit must be 'm', got {entry.get('unit')!r}")
    v = entry["value"]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise ParameterError(f"{source}: '{key}' value must be a finite number of metres, got {v!r}")
    if abs(v) > POSITION_LIMIT:
        raise ParameterError(f"{source}: '{key}' = {v} m is farther than {POSITION_LIMIT} m from the pivot")
    return float(v)


def _point(source: str, key: str, entry: Any) -> tuple[float, float]:
    if not isinstance(entry, dict) or set(entry) != {"x", "y"}:
        raise ParameterError(f"{source}: '{key}' must have exactly the keys x and y ({{value, unit: m}} each)")
    return _length(source, f"{key}.x", entry["x"]), _length(source, f"{key}.y", entry["y"])


def geometry_from_dict(data: Any, source: str = "<dict>") -> EffectGeometry:
    """Caster and IMU positions from the hardware configuration's structure (see module doc)."""
    if not isinstance(data, dict):
        raise ParameterError(f"{source}: expected a mapping of sections")
    casters: list[tuple[float, float]] = []
    if data.get("casters") is not None:
        block = data["casters"]
        if not isinstance(block, list) or not 1 <= len(block) <= MAX_CASTERS:
            raise ParameterError(f"{source}: 'casters' must be a list of 1 to {MAX_CASTERS} contact points")
        casters = [_point(source, f"casters[{i}]", c) for i, c in enumerate(block)]
    imu_pos = None
    mounting = (data.get("imu") or {}).get("mounting") if isinstance(data.get("imu"), dict) else None
    if isinstance(mounting, dict) and mounting.get("position") is not None:
        imu_pos = _point(source, "imu.mounting.position", mounting["position"])
    return EffectGeometry(tuple(casters), imu_pos, source)


def load_geometry(path: str | Path | None = None) -> EffectGeometry:
    """Read the geometry keys from a hardware configuration file (default ``config/robot.yaml``)."""
    from otbot_hw.motors import DEFAULT_ROBOT_FILE

    p = Path(path) if path is not None else DEFAULT_ROBOT_FILE
    return geometry_from_dict(read_yaml(p, "hardware configuration"), str(p))
