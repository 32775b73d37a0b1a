"""Otbot physical parameters: a typed, validated object loaded from YAML.

The YAML layout (see ``config/otbot.yaml``) groups entries in sections; every
entry is ``{value: <number>, unit: <text>}`` and may carry ``std`` (one standard
deviation, same unit) when it was identified. All values are SI.

``OtbotParams.as_array()`` gives the flat float vector used by the compiled model;
the index of each symbol is ``PARAM_INDEX[name]``.
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

#: Section, symbol, unit, rule. The rule is "positive" (> 0) or "finite".
SCHEMA: tuple[tuple[str, str, str, str], ...] = (
    ("geometry", "l1", "m", "positive"),
    ("geometry", "l2", "m", "positive"),
    ("geometry", "r", "m", "positive"),
    ("chassis", "m_c", "kg", "positive"),
    ("chassis", "I_c", "kg m^2", "positive"),
    ("chassis", "x_B", "m", "finite"),
    ("chassis", "y_B", "m", "finite"),
    ("platform", "m_p", "kg", "positive"),
    ("platform", "I_p", "kg m^2", "positive"),
    ("platform", "x_F", "m", "finite"),
    ("platform", "y_F", "m", "finite"),
    ("platform", "radius", "m", "positive"),
    ("wheel", "I_a", "kg m^2", "positive"),
    ("friction", "b_w", "N m s/rad", "nonnegative"),
    ("friction", "b_p", "N m s/rad", "nonnegative"),
)

#: Order of the flat parameter vector used by the compiled model (radius excluded).
PARAM_NAMES: tuple[str, ...] = (
    "l1", "l2", "r", "m_c", "I_c", "x_B", "y_B", "m_p", "I_p", "x_F", "y_F", "I_a", "b_w", "b_p",
)
PARAM_INDEX: dict[str, int] = {n: i for i, n in enumerate(PARAM_NAMES)}
UNITS: dict[str, str] = {name: unit for _, name, unit, _ in SCHEMA}
_RULES: dict[str, str] = {name: rule for _, name, _, rule in SCHEMA}
EFFECTS_SECTION = "effects"  # optional section of extended-model terms (otbot_hw.model.effects)
_SECTIONS: dict[str, list[str]] = {}
for _sec, _name, _, _ in SCHEMA:
    _SECTIONS.setdefault(_sec, []).append(_name)

DEFAULT_CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"
DEFAULT_PARAMS_FILE = DEFAULT_CONFIG_DIR / "otbot.yaml"


class ParameterError(ValueError):
    """A parameter file or value breaks a rule; the message names the key and the rule."""


#: largest configuration / parameter YAML read (bytes): these files are a few kB; anything this big is the
#: wrong file, and parsing hundreds of MB would take minutes and gigabytes (recordings are not capped)
MAX_YAML_BYTES = 4 * 1024 * 1024

#: YAML 1.2 floats YAML 1.1 reads as text: an exponent without a dot or without a sign (1e2, 1.0914e2)
_FLOAT_12 = r"""^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9][0-9_]*)[eE][-+]?[0-9]+$"""

_LOADER = None


def _loader():
    """The project's YAML loader: safe, YAML 1.2 exponent floats, duplicate keys an error naming both lines."""
    global _LOADER
    if _LOADER is not None:
        return _LOADER
    import re

    import yaml

    base = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

    class DuplicateKeyError(yaml.YAMLError):
        pass

    class Loader(base):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen: dict = {}
                for key_node, _ in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue  # a merge's keys may be overridden, that is what it is for
                    key = self.construct_object(key_node, deep=True)
                    try:
                        first = seen.setdefault(key, key_node.start_mark.line + 1)
                    except TypeError:
                        continue  # unhashable: the base constructor says so
                    if first != key_node.start_mark.line + 1:
                        raise DuplicateKeyError(f"key {key!r} is written twice (line {first} and line "
                                                f"{key_node.start_mark.line + 1}); keys must be unique")
            return super().construct_mapping(node, deep)

    Loader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(_FLOAT_12), list("-+0123456789."))
    Loader.DuplicateKeyError = DuplicateKeyError
    _LOADER = Loader
    return Loader


def parse_yaml(text: str) -> Any:
    """Parse YAML text with the project's loader (``read_yaml``'s rules); yaml.YAMLError on bad text."""
    import yaml

    return yaml.load(text, Loader=_loader())


def read_yaml(path: str | Path, what: str = "configuration file") -> Any:
    """Parse a YAML file (at most ``MAX_YAML_BYTES``) with YAML 1.2 floats (1e2 is a number) and unique keys;
    unreadable, oversized or malformed files raise ``ParameterError`` naming ``what``."""
    import yaml

    from otbot_hw.input_files import open_input

    p = Path(path)
    try:
        with open_input(p) as f:
            size = os.fstat(f.fileno()).st_size
            if size > MAX_YAML_BYTES:
                raise ParameterError(f"{p}: a {what} is at most {MAX_YAML_BYTES // (1024 * 1024)} MiB, this file "
                                     f"is {size / (1024 * 1024):.0f} MiB (wrong file?)")
            raw = f.read(MAX_YAML_BYTES + 1)
        if len(raw) > MAX_YAML_BYTES:
            raise ParameterError(f"{p}: a {what} is at most {MAX_YAML_BYTES // (1024 * 1024)} MiB; this input "
                                 "is longer (wrong file?)")
        return yaml.load(raw.decode("utf-8"), Loader=_loader())
    except OSError as exc:
        raise ParameterError(f"{p}: cannot read {what}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise ParameterError(f"{p}: not a text file; a {what} is YAML text") from None
    except _loader().DuplicateKeyError as exc:
        raise ParameterError(f"{p}: {what}: {exc}") from None
    except yaml.YAMLError as exc:
        raise ParameterError(f"{p}: {what} is not valid YAML: {exc}") from None


def check_value(name: str, value: Any) -> float:
    """Return ``value`` as float if it satisfies the rule of parameter ``name``."""
    if name not in _RULES:
        raise ParameterError(f"unknown parameter '{name}' (known: {', '.join(_RULES)})")
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise ParameterError(f"{name}: value must be a number, got {value!r}")
    v = float(value)
    rule = _RULES[name]
    if not math.isfinite(v):
        raise ParameterError(f"{name}: value must be finite, got {v}")
    if rule == "positive" and v <= 0.0:
        raise ParameterError(f"{name}: must be > 0 ({UNITS[name]}), got {v}")
    if rule == "nonnegative" and v < 0.0:
        raise ParameterError(f"{name}: must be >= 0 ({UNITS[name]}), got {v}")
    return v


def write_yaml(path: str | Path, data: Any, header: str = "") -> None:
    """Write ``data`` as YAML (keys in order) under ``header`` turned into comment lines."""
    import yaml

    prefix = "".join(f"# {line}\n" for line in header.splitlines())
    Path(path).write_text(prefix + yaml.safe_dump(data, sort_keys=False))


def read_entry(source: str, key: str, entry: Any, unit: str) -> tuple[Any, float | None]:
    """(raw value, std or None) of one ``{value, unit[, std]}`` entry, after checking its shape, that
    its unit is ``unit`` and that std is a number >= 0; the value's own rule is the caller's."""
    if not isinstance(entry, Mapping) or "value" not in entry:
        raise ParameterError(f"{source}: '{key}' must be a mapping with 'value' and 'unit'")
    bad = set(entry) - {"value", "unit", "std"}
    if bad:
        raise ParameterError(f"{source}: '{key}' has unknown field(s) {sorted(bad)}")
    if entry.get("unit") != unit:
        raise ParameterError(f"{source}: '{key}' unit must be '{unit}', got {entry.get('unit')!r}")
    if "std" not in entry:
        return entry["value"], None
    s = entry["std"]
    if isinstance(s, bool) or not isinstance(s, (int, float)) or not s >= 0:
        raise ParameterError(f"{source}: '{key}.std' must be a number >= 0, got {s!r}")
    return entry["value"], float(s)


@dataclass(frozen=True)
class OtbotParams:
    """Geometry and dynamic parameters of Otbot (SI units, paper Table 3 symbols).

    ``m_p, I_p, x_F, y_F`` are the *working* platform parameters (platform plus
    any load); ``radius`` is the platform footprint radius (m). ``std`` holds
    identified standard deviations for some entries (same units), else empty.
    """

    l1: float
    l2: float
    r: float
    m_c: float
    I_c: float
    x_B: float
    y_B: float
    m_p: float
    I_p: float
    x_F: float
    y_F: float
    radius: float
    I_a: float
    b_w: float
    b_p: float
    std: Mapping[str, float] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        for _, name, _, _ in SCHEMA:
            object.__setattr__(self, name, check_value(name, getattr(self, name)))
        if math.hypot(self.x_F, self.y_F) > self.radius:
            raise ParameterError(
                f"x_F, y_F: platform centre of mass ({self.x_F}, {self.y_F}) m lies outside "
                f"the platform radius {self.radius} m")

    # -- conversions -------------------------------------------------------
    def as_array(self) -> np.ndarray:
        """Flat float64 vector in ``PARAM_NAMES`` order (for the compiled model)."""
        return np.array([getattr(self, n) for n in PARAM_NAMES], dtype=float)

    def replace(self, **changes: float) -> "OtbotParams":
        """A copy with some parameters changed (validated)."""
        return dataclasses.replace(self, **changes)

    def values(self) -> dict[str, float]:
        """All parameters as a plain ``{symbol: value}`` dict."""
        return {name: getattr(self, name) for _, name, _, _ in SCHEMA}

    def with_load(self, mass: float, x: float, y: float, inertia: float = 0.0) -> "OtbotParams":
        """Working-platform parameters after placing a load on the platform.

        The load is a rigid body of ``mass`` kg with its centre of mass at
        ``(x, y)`` m in the platform frame B'' and its own vertical inertia
        ``inertia`` kg m^2 about that centre; combined by Steiner's theorem.
        """
        if mass < 0 or inertia < 0:
            raise ParameterError(f"load: mass and inertia must be >= 0, got {mass}, {inertia}")
        if mass == 0:
            return self
        m = self.m_p + mass
        xf = (self.m_p * self.x_F + mass * x) / m
        yf = (self.m_p * self.y_F + mass * y) / m
        ip = (self.I_p + self.m_p * ((self.x_F - xf) ** 2 + (self.y_F - yf) ** 2)
              + inertia + mass * ((x - xf) ** 2 + (y - yf) ** 2))
        return self.replace(m_p=m, x_F=xf, y_F=yf, I_p=ip)

    def to_dict(self) -> dict[str, dict[str, dict[str, Any]]]:
        """The YAML structure (sections of ``{value, unit[, std]}`` entries)."""
        out: dict[str, dict[str, dict[str, Any]]] = {}
        for sec, name, unit, _ in SCHEMA:
            entry: dict[str, Any] = {"value": float(getattr(self, name)), "unit": unit}
            if name in self.std:
                entry["std"] = float(self.std[name])
            out.setdefault(sec, {})[name] = entry
        return out

    # -- loading -----------------------------------------------------------
    @classmethod
    def from_dict(cls, data: Any, source: str = "<dict>", allow_effects: bool = False) -> "OtbotParams":
        """Validate the YAML structure; errors name the key and the rule broken.

        An ``effects`` section (missing-physics terms, ``otbot diagnose --out``) belongs to the
        extended model (``ExtendedModel.from_dict``); it is skipped with ``allow_effects`` and
        rejected otherwise, so a command on the paper's model never drops it silently.
        """
        if not isinstance(data, Mapping):
            raise ParameterError(f"{source}: top level must be a mapping of sections")
        if EFFECTS_SECTION in data:
            if not allow_effects:
                raise ParameterError(
                    f"{source}: section '{EFFECTS_SECTION}' holds extended-model terms (written by otbot diagnose "
                    f"--out); this command uses the paper's model only -- use otbot simulate or otbot track, or "
                    f"remove the section")
            data = {k: v for k, v in data.items() if k != EFFECTS_SECTION}
        unknown = set(data) - set(_SECTIONS)
        if unknown:
            raise ParameterError(
                f"{source}: unknown section(s) {sorted(unknown)} (known: {list(_SECTIONS)})")
        values: dict[str, float] = {}
        std: dict[str, float] = {}
        for sec, names in _SECTIONS.items():
            if sec not in data:
                raise ParameterError(f"{source}: missing section '{sec}'")
            block = data[sec]
            if not isinstance(block, Mapping):
                raise ParameterError(f"{source}: section '{sec}' must be a mapping")
            extra = set(block) - set(names)
            if extra:
                raise ParameterError(
                    f"{source}: unknown key(s) {sorted(extra)} in section '{sec}' (known: {names})")
            for name in names:
                key = f"{sec}.{name}"
                if name not in block:
                    raise ParameterError(f"{source}: missing key '{key}'")
                value, s = read_entry(source, key, block[name], UNITS[name])
                try:
                    values[name] = check_value(name, value)
                except ParameterError as exc:
                    raise ParameterError(f"{source}: '{key}': {exc}") from None
                if s is not None:
                    std[name] = s
        try:
            return cls(**values, std=std)
        except ParameterError as exc:
            raise ParameterError(f"{source}: {exc}") from None

    @classmethod
    def load(cls, path: str | Path | None = None) -> "OtbotParams":
        """Load and validate a parameter YAML file (default: ``config/otbot.yaml``)."""
        p = Path(path) if path is not None else DEFAULT_PARAMS_FILE
        data = read_yaml(p, "parameter file")
        return cls.from_dict(data, source=str(p))

    def save(self, path: str | Path, header: str = "") -> None:
        """Write the parameters as YAML in the ``config/otbot.yaml`` layout."""
        write_yaml(path, self.to_dict(), header)


def finite_number(text: str, what: str, error: type[Exception] = ValueError) -> float:
    """``float(text)``; ``error`` names ``what`` when the text is not a number or not finite."""
    try:
        v = float(text)
    except ValueError:
        raise error(f"{what}: {text!r} is not a number") from None
    if not math.isfinite(v):
        raise error(f"{what}: values must be finite, got {text!r}")
    return v


def parse_load(text: str) -> tuple[float, float, float, float]:
    """A load on the platform written 'KG@X,Y[,I]' -> (mass kg, x m, y m, own inertia kg m^2), the
    arguments of ``OtbotParams.with_load``. ``ValueError`` says what is wrong, without naming where the
    text came from (callers prefix their option: "--load mass must be >= 0 kg, got -5")."""
    if "@" not in text:
        raise ValueError(f"must look like KG@X,Y or KG@X,Y,I, got {text!r}")
    kg, pos = text.split("@", 1)
    parts = [p.strip() for p in pos.split(",")]
    if len(parts) not in (2, 3):
        raise ValueError(f"position needs X,Y or X,Y,I, got {pos!r}")
    vals = [finite_number(item, what) for what, items in (("mass", [kg.strip()]), ("position", parts))
            for item in items]
    mass, x, y = vals[:3]
    inertia = vals[3] if len(vals) == 4 else 0.0
    if mass < 0:
        raise ValueError(f"mass must be >= 0 kg, got {mass:g}")
    if inertia < 0:
        raise ValueError(f"inertia must be >= 0 kg m^2, got {inertia:g}")
    return mass, x, y, inertia


def nominal() -> OtbotParams:
    """The nominal parameters of ``config/otbot.yaml`` (paper Table 3)."""
    return OtbotParams.load(DEFAULT_PARAMS_FILE)
