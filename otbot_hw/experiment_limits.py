"""Limits of an identification experiment: what the excitation may ask of the robot.

One place for the numbers, read from ``config/robot.yaml`` section ``experiment_limits``
(every entry ``{value, unit}``):

==================  =======  ===================================================================
key                 unit     meaning
==================  =======  ===================================================================
torque              N m      largest |tau| of any motor during an experiment (at most the
                             motors' ``max_torque``)
wheel_speed         rad/s    largest |phi_r_dot|, |phi_l_dot| (wheel joint rates)
pivot_speed         rad/s    largest |phi_p_dot| (platform relative to the chassis, the pivot motor)
platform_speed      m/s      largest speed of the pivot point P over the floor
travel_radius       m        the free area: a disc around the start that P must not leave, the
                             stop after the excitation included
stop_deceleration   m/s^2    deceleration the stop after the excitation achieves (for the
                             stopping distance v^2 / (2 a) added to the travel)
==================  =======  ===================================================================

The designed excitation (``identification.design``) stays within them on its predicted
motion; the runtime's safety supervisor can enforce the same numbers during the run
(``ExperimentLimits`` is plain data; ``motion_margins`` evaluates a predicted or recorded
motion against it). The defaults admit the paper's experiments (chassis: 10 N m, wheels
up to 12.1 rad/s, pivot 5.6 rad/s, P at up to 0.96 m/s, 0.97 m from the start plus
0.36 m to stop).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from otbot_hw.params import ParameterError, read_entry, read_yaml

SECTION = "experiment_limits"
#: key -> unit in the configuration file
LIMIT_UNITS: dict[str, str] = {"torque": "N m", "wheel_speed": "rad/s", "pivot_speed": "rad/s",
                               "platform_speed": "m/s", "travel_radius": "m", "stop_deceleration": "m/s^2"}


@dataclass(frozen=True)
class ExperimentLimits:
    """Limits of an identification experiment (SI units; see the module docstring)."""

    torque: float = 10.0
    wheel_speed: float = 12.5
    pivot_speed: float = 6.0
    platform_speed: float = 1.0
    travel_radius: float = 1.5
    stop_deceleration: float = 1.0

    def __post_init__(self) -> None:
        for k in LIMIT_UNITS:
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                raise ParameterError(f"{SECTION}.{k} must be a number > 0 ({LIMIT_UNITS[k]}), got {v!r}")

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    def replace(self, **changes: float) -> "ExperimentLimits":
        import dataclasses

        return dataclasses.replace(self, **changes)


def limits_from_dict(section: Mapping[str, Any] | None, source: str = "<dict>") -> ExperimentLimits:
    """``ExperimentLimits`` from a configuration section (missing keys keep their defaults)."""
    if section is None:
        return ExperimentLimits()
    if not isinstance(section, Mapping):
        raise ParameterError(f"{source}: section '{SECTION}' must be a mapping")
    unknown = set(section) - set(LIMIT_UNITS)
    if unknown:
        raise ParameterError(f"{source}: unknown key(s) {sorted(unknown)} in '{SECTION}' (known: {list(LIMIT_UNITS)})")
    vals = {}
    for k, entry in section.items():
        v, _ = read_entry(source, f"{SECTION}.{k}", entry, LIMIT_UNITS[k])
        vals[k] = v
    try:
        return ExperimentLimits(**vals)
    except ParameterError as exc:
        raise ParameterError(f"{source}: {exc}") from None


def load_experiment_limits(path: str | Path | None = None) -> ExperimentLimits:
    """Read section ``experiment_limits`` of the hardware configuration (default ``config/robot.yaml``).

    The torque limit must not exceed any motor's ``motors.<name>.max_torque``.
    """
    from otbot_hw.motors import DEFAULT_ROBOT_FILE, load_motor_limits

    p = Path(path) if path is not None else DEFAULT_ROBOT_FILE
    data = read_yaml(p) or {}
    lim = limits_from_dict(data.get(SECTION), str(p))
    if "motors" in data:
        peak = float(np.min(load_motor_limits(p).max_torque))
        if lim.torque > peak:
            raise ParameterError(f"{p}: '{SECTION}.torque' {lim.torque} N m exceeds the motors' max_torque {peak} N m")
    return lim


def motion_fractions(q: np.ndarray, qd: np.ndarray, u: np.ndarray, limits: ExperimentLimits) -> dict[str, np.ndarray]:
    """Each limited quantity per sample of a floor motion, as a fraction of its limit (> 1: violated).

    q, qd (n, 6) states (x, y, alpha, phi_r, phi_l, phi_p) and rates; u (n, 3) N m. The travel is the
    distance of P from its start plus the stopping distance v^2 / (2 stop_deceleration) at that sample.
    """
    q, qd, u = np.atleast_2d(q), np.atleast_2d(qd), np.atleast_2d(u)
    speed = np.hypot(qd[:, 0], qd[:, 1])
    dist = np.hypot(q[:, 0] - q[0, 0], q[:, 1] - q[0, 1]) + speed ** 2 / (2.0 * limits.stop_deceleration)
    return {
        "torque": np.max(np.abs(u), axis=1) / limits.torque,
        "wheel_speed": np.max(np.abs(qd[:, 3:5]), axis=1) / limits.wheel_speed,
        "pivot_speed": np.abs(qd[:, 5]) / limits.pivot_speed,
        "platform_speed": speed / limits.platform_speed,
        "travel_radius": dist / limits.travel_radius,
    }


def motion_margins(q: np.ndarray, qd: np.ndarray, u: np.ndarray, limits: ExperimentLimits) -> dict[str, float]:
    """Peak of each limited quantity over a floor motion, as a fraction of its limit (> 1: violated)."""
    return {k: float(np.max(v)) for k, v in motion_fractions(q, qd, u, limits).items()}


def violations(margins: Mapping[str, float], limits: ExperimentLimits, tol: float = 1e-6) -> list[str]:
    """Sentences naming each limit a motion exceeds (empty: within every limit)."""
    out = []
    for k, m in margins.items():
        if m > 1.0 + tol:
            out.append(f"{k.replace('_', ' ')} reaches {m * getattr(limits, k):.3g} {LIMIT_UNITS[k]} "
                       f"(limit {getattr(limits, k):.3g} {LIMIT_UNITS[k]})")
    return out
