"""A designed excitation scaled to the robot on the floor: the bench's fixture probe says how much heavier
(or lighter) this robot is than believed, and the design's torques are scaled down until its predicted
peaks stay within the experiment limits on that robot (``fit_excitation``, used by ``procedure``).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from otbot_hw.experiment_limits import ExperimentLimits
from otbot_hw.identification.experiments import ExperimentSpec
from otbot_hw.model.kinematics import forward_kinematics_matrix
from otbot_hw.params import OtbotParams
from otbot_hw.runtime.bench import checks as chk
from otbot_hw.runtime.bench.excitation import predicted_margins, predicted_motion
from otbot_hw.runtime.supervisor import SafetyConfig

UNKNOWN_COM = 0.05    # m: how far the chassis' centre of mass may lie from the file's (issue 21's prior)
UNKNOWN_INERTIA = 0.3  # fraction: how far the chassis' inertia may lie from the mass-scaled one
LIMIT_FILL = 0.95     # a designed excitation is scaled so that its peaks predicted on this robot stay below this
                      # fraction of each limit (the probe's mass estimate leaves the centres of mass unknown)


def fit_excitation(base: ExperimentSpec, probe, probe_u: np.ndarray, best: OtbotParams, loaded: bool,
                   limits: ExperimentLimits, safety: SafetyConfig, period: float
                   ) -> tuple[ExperimentSpec, float, chk.Check]:
    """Floor steps, designed excitation: the design keeps the limits on the prior's corner robots (+-20 %),
    this robot may lie beyond. The probe's measured pivot speed against the one predicted for the
    best-known robot says how much heavier (or lighter) it is, rho = v_predicted / v_measured; the body
    that is still unknown (the chassis in step chassis, the loaded platform in step platform) is scaled so
    (mass and inertia), the excitation's peaks predicted on that robot (in step chassis also with its
    centre of mass moved by UNKNOWN_COM and its inertia by UNKNOWN_INERTIA, which a forward probe cannot
    tell), and the torques scaled down (speeds and travel go about linearly with them) until every peak
    is within LIMIT_FILL of its limit. Returns the scaled excitation, the scale and the check that says so."""
    scale = 1.0
    pspec = dataclasses.replace(base, profile=probe_u, torque=tuple(float(v) for v in probe_u[0]),
                                duration=len(probe_u) * period)
    M = forward_kinematics_matrix(np.zeros(6), best)[:2]
    _, qd = predicted_motion(pspec, best)
    v_pred = float(np.max(np.linalg.norm(qd[:, 3:6] @ M.T, axis=1)))
    n = min(len(probe_u), len(probe))
    v_meas = float(np.max(np.linalg.norm(np.asarray(probe.joint_vel[:n], dtype=float) @ M.T, axis=1)))
    rho = float(np.clip(v_pred / max(v_meas, 1e-9), 0.25, 20.0))
    total = best.m_c + best.m_p
    if loaded:
        guess = best.replace(m_p=max(total * rho - best.m_c, 0.1 * best.m_p), I_p=best.I_p * rho)
    else:
        guess = best.replace(m_c=max(total * rho - best.m_p, 0.1 * best.m_c), I_c=best.I_c * rho)
    safety = safety.within(limits, "floor")
    robots = [guess]
    if not loaded:  # what a forward probe cannot tell: the chassis' centre and inertia
        c = UNKNOWN_COM
        robots += [guess.replace(x_B=guess.x_B + dx, y_B=guess.y_B + dy, I_c=guess.I_c * f)
                   for dx, dy in ((c, c), (c, -c), (-c, c), (-c, -c)) for f in (1 - UNKNOWN_INERTIA, 1 + UNKNOWN_INERTIA)]
    spec = base
    for _ in range(3):
        every = [predicted_margins(spec, r, limits, safety.max_wheel_rate, safety.max_pivot_rate)
                 for r in robots]
        margins = {k: max((m[k] for m in every), key=lambda v: v[0] / v[1]) for k in every[0]}
        worst = max((p / lim for k, (p, lim) in margins.items() if k != "torque"), default=0.0)
        if worst <= LIMIT_FILL:
            break
        scale *= LIMIT_FILL / worst
        spec = scaled(base, scale)
    text = (f"the probe moved the robot at {v_meas:.3f} m/s, {v_pred:.3f} m/s predicted: about {rho:.2f} x the "
            f"mass believed; largest predicted peaks on that robot"
            + (f" with its centre of mass within {UNKNOWN_COM:g} m and inertia within {UNKNOWN_INERTIA:.0%}"
               if len(robots) > 1 else "") + ": "
            + ", ".join(f"{k.replace('_', ' ')} {p:.3g} of {lim:.3g}" for k, (p, lim) in margins.items()))
    text += (f"; the designed torques scaled by {scale:.3f} to stay within the limits" if scale < 1.0 else
             "; the designed torques as designed")
    return spec, scale, chk.Check("robot_limits", True, text, value=scale)


def scaled(spec: ExperimentSpec, k: float) -> ExperimentSpec:
    """``spec`` with its torques multiplied by ``k``."""
    if k == 1.0:
        return spec
    U = spec.torques() * k
    return dataclasses.replace(spec, profile=U, torque=tuple(float(v) for v in U[0]),
                               description=f"{spec.description}, scaled by {k:.3f} to this robot")
