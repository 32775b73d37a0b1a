"""Whether a parameter set gives the paper's model dynamics that double precision can integrate.

Each value can pass its own rule (``otbot_hw.params``: positive, finite) while together they make the
task-space mass matrix M_bar(q) = Delta^T M Lambda (paper §3.3, ``dynamics.task_space_model``) singular
to working precision: a chassis mass of 1e30 kg next to wheel inertias of 1e-3 kg m^2 (a unit or an
exponent written wrong), or offsets of kilometres. The compiled model then divides by an exact zero
(numba raises ``ZeroDivisionError`` where numpy would give inf) or returns accelerations with no
correct digit. The nominal robot's M_bar has a condition number of about 4; ``MAX_CONDITION`` (1e12)
leaves four significant digits of the accelerations in double precision.

M_bar depends on the configuration only through the platform heading alpha and the pivot angle
phi_p; both are sampled on a grid (``ANGLES``), so a set refused here is singular somewhere the robot
can be.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from otbot_hw.model.dynamics import task_space_model
from otbot_hw.params import SCHEMA, UNITS, OtbotParams, ParameterError

#: largest condition number of M_bar accepted (dimensionless)
MAX_CONDITION = 1e12
#: alpha and phi_p (rad) at which M_bar is checked: every pair of this grid
ANGLES = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)


def worst_condition(params: OtbotParams) -> tuple[float, float, float]:
    """(largest condition number of M_bar over the grid, alpha, phi_p (rad) where it is); inf where
    M_bar is not finite."""
    worst = (0.0, 0.0, 0.0)
    zero = np.zeros(6)
    with np.errstate(all="ignore"):
        for a in ANGLES:
            for phi_p in ANGLES:
                m_bar, _ = task_space_model(np.array([0.0, 0.0, a, 0.0, 0.0, phi_p]), zero, params)
                c = float(np.linalg.cond(m_bar)) if np.all(np.isfinite(m_bar)) else float("inf")
                if not c <= worst[0]:  # (nan counts as the worst)
                    worst = (c if c == c else float("inf"), float(a), float(phi_p))
    return worst


def check_well_posed(params: OtbotParams, source: str = "parameters") -> OtbotParams:
    """``params`` if M_bar's condition number stays within ``MAX_CONDITION`` everywhere on the grid;
    else ParameterError (one line: the condition number, where, and the largest and smallest values)."""
    cond, a, phi_p = worst_condition(params)
    if cond <= MAX_CONDITION:
        return params
    values = {name: abs(getattr(params, name)) for _, name, _, _ in SCHEMA if getattr(params, name) != 0.0}
    hi = max(values, key=values.get)
    lo = min(values, key=values.get)
    raise ParameterError(
        f"{source}: these parameters make the model singular: its task-space mass matrix (paper §3.3) has "
        f"condition number {cond:.3g} at alpha = {a:.2f} rad, phi_p = {phi_p:.2f} rad (at most {MAX_CONDITION:g}; "
        f"the nominal robot's is about 4); largest {hi} = {getattr(params, hi):g} {UNITS[hi]}, smallest "
        f"{lo} = {getattr(params, lo):g} {UNITS[lo]}: a unit or an exponent written wrong?")


def load_params(path: str | Path | None = None) -> OtbotParams:
    """``OtbotParams.load(path)`` (default ``config/otbot.yaml``) checked by ``check_well_posed``."""
    params = OtbotParams.load(path)
    return check_well_posed(params, str(path) if path is not None else "config/otbot.yaml")
