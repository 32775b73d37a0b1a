"""The extended model: the paper's parameters plus an effect vector (``ExtendedModel``) and its YAML file
(``config/otbot.yaml`` layout plus an ``effects`` section).

The effects are catalogued in ``otbot_hw.model.effect_catalog`` (names, units, bounds; re-exported here,
the vocabulary of the model object), their physics is ``otbot_hw.model.effect_physics``, the sensor
effects ``otbot_hw.model.sensor_model``; the integrators live in ``otbot_hw.simulation.integrators``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from otbot_hw.model.constants import GRAVITY  # noqa: F401
from otbot_hw.model.effect_catalog import *  # noqa: F401,F403  (the catalog: the model's vocabulary)
from otbot_hw.model.effect_catalog import (EFFECT_INDEX, EFFECT_PARAM_NAMES, EFFECT_UNITS, F_CST, GEOMETRY_PARAMS, S_W,
                                           TIED_PARAMS, effect_vector, parameter_bounds, parameter_unit)
from otbot_hw.params import OtbotParams


@dataclass(frozen=True)
class ExtendedModel:
    """The paper's parameters plus an effect vector: what simulation, identification and control use."""

    params: OtbotParams
    eff: np.ndarray

    @classmethod
    def paper(cls, params: OtbotParams) -> "ExtendedModel":
        return cls(params, effect_vector())

    def get(self, name: str) -> float:
        """Value of a nominal parameter, an effect-vector entry or a tied catalog parameter."""
        if name in TIED_PARAMS:
            return float(self.eff[EFFECT_INDEX[TIED_PARAMS[name][0]]])
        if name in EFFECT_INDEX:
            return float(self.eff[EFFECT_INDEX[name]])
        return float(getattr(self.params, name))

    def with_values(self, values: dict[str, float]) -> "ExtendedModel":
        """A copy with some nominal/effect/tied parameters set."""
        eff = self.eff.copy()
        nominal = {}
        for k, v in values.items():
            if k in TIED_PARAMS:
                for t in TIED_PARAMS[k]:
                    eff[EFFECT_INDEX[t]] = v
            elif k in EFFECT_INDEX:
                eff[EFFECT_INDEX[k]] = v
            else:
                nominal[k] = float(v)
        params = self.params.replace(**nominal) if nominal else self.params
        return ExtendedModel(params, eff)

    def active_effects(self) -> dict[str, float]:
        """Effect entries that differ from the paper's model (the Stribeck speed only with Stribeck
        friction, the caster geometry only with caster drag)."""
        base = effect_vector()
        return {n: float(self.eff[i]) for i, n in enumerate(EFFECT_PARAM_NAMES)
                if self.eff[i] != base[i] and not (n == "v_s" and self.eff[S_W] == 0.0)
                and not (n in GEOMETRY_PARAMS and self.eff[F_CST] == 0.0)}

    # -- model files: the parameter YAML plus an optional ``effects`` section ----------------
    @classmethod
    def from_dict(cls, data, source: str = "<dict>") -> "ExtendedModel":
        """Parameters and effects from the YAML structure. ``effects`` maps effect-parameter names
        (``EFFECT_PARAMS``; ``c_w`` sets both wheels) to ``{value, unit[, std]}``; absent = paper's model."""
        from otbot_hw.model.well_posed import check_well_posed
        from otbot_hw.params import EFFECTS_SECTION, OtbotParams, ParameterError, read_entry

        params = check_well_posed(OtbotParams.from_dict(data, source, allow_effects=True), source)
        block = data.get(EFFECTS_SECTION) or {}
        if not isinstance(block, dict):
            raise ParameterError(f"{source}: section '{EFFECTS_SECTION}' must be a mapping of effect parameters")
        values: dict[str, float] = {}
        for name, entry in block.items():
            key = f"{EFFECTS_SECTION}.{name}"
            if name not in EFFECT_INDEX and name not in TIED_PARAMS:
                raise ParameterError(f"{source}: unknown effect parameter '{key}' "
                                     f"(known: {', '.join(EFFECT_PARAM_NAMES + tuple(TIED_PARAMS))})")
            v, _ = read_entry(source, key, entry, parameter_unit(name))
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise ParameterError(f"{source}: '{key}' value must be a finite number, got {v!r}")
            v = float(v)
            lo, hi = parameter_bounds(name)
            if not lo <= v <= hi:
                raise ParameterError(f"{source}: '{key}' = {v} is outside its physical range [{lo}, {hi}]")
            values[name] = v
        try:
            return cls(params, effect_vector()).with_values(values).checked()
        except ValueError as exc:
            raise ParameterError(f"{source}: {exc}") from None

    @classmethod
    def load(cls, path=None) -> "ExtendedModel":
        """Load a parameter YAML with or without ``effects`` (default: ``config/otbot.yaml``)."""
        from otbot_hw.params import DEFAULT_PARAMS_FILE, read_yaml

        p = path if path is not None else DEFAULT_PARAMS_FILE
        return cls.from_dict(read_yaml(p, "parameter file"), source=str(p))

    def checked(self) -> "ExtendedModel":
        """Self, after the cross-checks ``effect_vector`` applies (ValueError otherwise)."""
        effect_vector({n: float(v) for n, v in zip(EFFECT_PARAM_NAMES, self.eff)})
        return self

    def to_dict(self, effect_std: dict[str, float] | None = None) -> dict:
        """The YAML structure: the parameter sections plus ``effects`` (active entries only)."""
        out = self.params.to_dict()
        effect_std = effect_std or {}
        active = self.active_effects()
        if active:
            block = {}
            for n, v in active.items():
                entry = {"value": v, "unit": EFFECT_UNITS[n]}
                s = effect_std.get(n, effect_std.get(next((t for t, m in TIED_PARAMS.items() if n in m), ""), None))
                if s is not None and np.isfinite(s):
                    entry["std"] = float(s)
                block[n] = entry
            out["effects"] = block
        return out

    def save(self, path, header: str = "", effect_std: dict[str, float] | None = None) -> None:
        """Write the model as YAML (``config/otbot.yaml`` layout plus the ``effects`` section)."""
        from otbot_hw.params import write_yaml

        write_yaml(path, self.to_dict(effect_std), header)

