"""Typed reading of ``config/robot.yaml``'s mappings (``drivers.config``): numbers with their units,
bounds, whole periods, node IDs, signs, EDS paths; unknown keys refused. Every error is a
``ParameterError`` naming ``file: 'a.b.c'``."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from otbot_hw.params import ParameterError

#: Longest detection time a configuration may give (s): TPDO staleness, the loop's liveness, the fault
#: reaction's SYNCs. A longer one turns the detection off in effect.
MAX_DETECTION = 2.0


class ConfigReader:
    """Typed access to nested YAML mappings with errors naming ``file: 'a.b.c'``."""

    def __init__(self, path: Path):
        self.path = path

    def err(self, key: str, msg: str) -> ParameterError:
        return ParameterError(f"{self.path}: '{key}' {msg}")

    def section(self, data: dict, key: str) -> dict:
        v = data.get(key.split(".")[-1]) if isinstance(data, dict) else None
        if not isinstance(v, dict):
            raise ParameterError(f"{self.path}: missing section '{key}'")
        return v

    def raw(self, d: dict, key: str, name: str, default: Any = ...):
        if key not in d:
            if default is ...:
                raise self.err(name, "is missing")
            return default
        return d[key]

    def only(self, d: dict, name: str, known: tuple[str, ...]) -> None:
        """Refuse keys of mapping ``name`` not in ``known``: a misspelt optional key would keep its default."""
        unknown = [k for k in d if k not in known]
        if unknown:
            raise self.err(name, f"has unknown key(s) {unknown} (known: {', '.join(known)})")

    def number(self, d: dict, key: str, name: str, unit: str | None, default: Any = ..., positive: bool = True,
               integer: bool = False, maximum: tuple[float, str] | None = None):
        """A number (``{value, unit}`` where ``unit`` is given), finite, > 0 unless ``positive`` is False,
        whole if ``integer``, at most ``maximum`` = (value, why) if given."""
        v = self.raw(d, key, name, default)
        if v is default and default is not ...:
            return default
        if unit is not None:
            if not isinstance(v, dict) or "value" not in v:
                raise self.err(name, f"must be {{value: NUMBER, unit: {unit}}}, got {v!r}")
            self.only(v, name, ("value", "unit"))
            if v.get("unit") != unit:
                raise self.err(name, f"unit must be '{unit}', got {v.get('unit')!r}")
            v = v["value"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise self.err(name, f"must be a finite number, got {v!r}")
        if integer and (not float(v).is_integer()):
            raise self.err(name, f"must be a whole number, got {v!r}")
        if positive and not v > 0:
            raise self.err(name, f"must be > 0, got {v!r}")
        if maximum is not None and v > maximum[0]:
            raise self.err(name, f"must be at most {maximum[0]:g}{' ' + unit if unit else ''} ({maximum[1]}), got {v:g}")
        return int(v) if integer else float(v)

    def periods(self, d: dict, key: str, name: str, rate: float, default: int) -> int:
        """A whole number of control periods, written {value: N, unit: periods}; a time in s is
        rounded up to whole periods of ``rate`` Hz. At most ``MAX_DETECTION`` s of periods: these are
        detection times, and a longer one turns the detection off in effect."""
        v = self.raw(d, key, name, None)
        if v is None:
            return default
        if isinstance(v, dict) and v.get("unit") == "s":
            secs = self.number(d, key, name, "s", maximum=(MAX_DETECTION, "a detection time"))
            return max(1, int(np.ceil(secs * rate - 1e-9)))
        n = self.number(d, key, name, "periods")
        if not float(n).is_integer() or n < 1:
            raise self.err(name, f"must be a whole number of periods >= 1, got {n!r}")
        if n / rate > MAX_DETECTION:
            raise self.err(name, f"must be at most {MAX_DETECTION:g} s of periods ({int(MAX_DETECTION * rate)} at "
                                 f"{rate:g} Hz: a detection time), got {n:g}")
        return int(n)

    def node_id(self, d: dict, name: str) -> int:
        v = self.number(d, "node_id", f"{name}.node_id", None, integer=True)
        if not 1 <= v <= 127:
            raise self.err(f"{name}.node_id", f"must be a CANopen node ID 1..127, got {v}")
        return v

    def sign(self, d: dict, key: str, name: str) -> int:
        v = self.raw(d, key, name, 1)
        if v not in (1, -1) or isinstance(v, bool):
            raise self.err(name, f"must be 1 or -1, got {v!r}")
        return int(v)

    def eds(self, d: dict, name: str) -> Path:
        v = self.raw(d, "eds", name)
        if not isinstance(v, str) or not v:
            raise self.err(name, f"must be a file name, got {v!r}")
        p = Path(v) if Path(v).is_absolute() else self.path.parent / v
        if p.is_dir():
            raise self.err(name, f"names {p}, which is a folder, not an EDS file")
        if not p.is_file():
            raise self.err(name, f"names {p}, which does not exist")
        return p
