"""Statistics of a whole session on simulated robots that differ from nominal (issue 15, item 7).

``perturbed_robot(seed)`` draws a robot the identification has never seen: masses,
inertias and frictions within +-``spread.scale`` of nominal, the chassis' centre of
mass moved by up to ``spread.com_shift`` m, and a load on the platform (mass, position
within ``spread.load_radius`` m of the pivot, own inertia). The unloaded platform's
mass and centre of mass and the geometry stay nominal: the paper takes them for
granted (§4.3.1, they are weighed and measured).

``session_trial`` simulates the session's recordings on such a robot, each step's
experiment on its fixture (``experiments.PAPER_EXPERIMENTS``: wheel on the stand, pivot
with the wheels locked, chassis unloaded on the floor, platform loaded on the floor)
by ``otbot_hw.simulation.runs.simulated_recording``, identifies them with
``session.identify_session`` and returns, per parameter, the truth, the estimates and
the std of each way of reporting it. ``benchmarks/bench_accuracy.py`` aggregates.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from otbot_hw.experiment_limits import ExperimentLimits, motion_margins
from otbot_hw.identification.design import RobotSpread
from otbot_hw.identification.experiments import PAPER_EXPERIMENTS, STEPS, ExperimentSpec, simulate_experiment
from otbot_hw.identification.uncertainty import LOADED_STEPS, NUISANCE_PARAMS, SESSION_PARAMS
from otbot_hw.params import OtbotParams, nominal


def perturbed_robot(seed: int, base: OtbotParams | None = None,
                    spread: RobotSpread | None = None) -> tuple[OtbotParams, OtbotParams, dict[str, float]]:
    """(unloaded robot, robot with its load, the load {mass, x, y, inertia}) for a seed."""
    base = base or nominal()
    sp = spread or RobotSpread()
    rng = np.random.default_rng([15, seed])

    def f() -> float:
        return float(rng.uniform(1.0 - sp.scale, 1.0 + sp.scale))

    unloaded = base.replace(
        m_c=base.m_c * f(), I_c=base.I_c * f(),
        x_B=base.x_B + float(rng.uniform(-sp.com_shift, sp.com_shift)),
        y_B=base.y_B + float(rng.uniform(-sp.com_shift, sp.com_shift)),
        I_a=base.I_a * f(), b_w=base.b_w * f(), b_p=base.b_p * f(), I_p=base.I_p * f())
    ang = float(rng.uniform(0.0, 2.0 * math.pi))
    rad = sp.load_radius * math.sqrt(float(rng.uniform()))
    load = {"mass": float(rng.uniform(*sp.load_mass)), "x": rad * math.cos(ang), "y": rad * math.sin(ang),
            "inertia": float(rng.uniform(*sp.load_inertia))}
    return unloaded, unloaded.with_load(**load), load


#: The prior of ``every_parameter_robot`` (issue 21): every mass, inertia and friction +-30 % (the unloaded
#: platform's too), every centre of mass moved up to 5 cm, a 0-300 kg load within 0.2 m of the pivot.
EVERY_PARAMETER = RobotSpread(scale=0.3, com_shift=0.05, load_mass=(0.0, 300.0), load_radius=0.2,
                              load_inertia=(0.0, 5.0))


def every_parameter_robot(seed: int, base: OtbotParams | None = None,
                          spread: RobotSpread = EVERY_PARAMETER) -> tuple[OtbotParams, OtbotParams, dict[str, float]]:
    """(unloaded robot, robot with its load, the load) with *every* dynamic parameter off the file's: the
    chassis' and the unloaded platform's masses, inertias and centres of mass, the wheels' inertia and both
    frictions (uniform within +-``spread.scale``, centres +-``spread.com_shift`` m in x and y), and a load of
    ``spread.load_mass`` kg (uniform) within ``spread.load_radius`` m of the pivot with its own inertia
    (uniform in ``spread.load_inertia``). Geometry (l1, l2, r) stays the file's."""
    base = base or nominal()
    sp = spread
    rng = np.random.default_rng([21, seed])

    def f() -> float:
        return float(rng.uniform(1.0 - sp.scale, 1.0 + sp.scale))

    def d() -> float:
        return float(rng.uniform(-sp.com_shift, sp.com_shift))

    unloaded = base.replace(m_c=base.m_c * f(), I_c=base.I_c * f(), x_B=base.x_B + d(), y_B=base.y_B + d(),
                            m_p=base.m_p * f(), I_p=base.I_p * f(), x_F=base.x_F + d(), y_F=base.y_F + d(),
                            I_a=base.I_a * f(), b_w=base.b_w * f(), b_p=base.b_p * f())
    ang = float(rng.uniform(0.0, 2.0 * math.pi))
    rad = sp.load_radius * math.sqrt(float(rng.uniform()))
    load = {"mass": float(rng.uniform(*sp.load_mass)), "x": rad * math.cos(ang), "y": rad * math.sin(ang),
            "inertia": float(rng.uniform(*sp.load_inertia))}
    return unloaded, unloaded.with_load(**load), load


def simulate_session(unloaded: OtbotParams, loaded: OtbotParams, seed: int,
                     specs: Mapping[str, ExperimentSpec] | None = None, steps=STEPS) -> dict[str, list]:
    """{step: [Recording]} of a session on this robot: each step's experiment on its fixture (noise seeded)."""
    out = {}
    for i, step in enumerate(steps):
        spec = (specs or {}).get(step) or PAPER_EXPERIMENTS[step]
        truth = loaded if step in LOADED_STEPS else unloaded
        out[step] = [simulate_experiment(step, truth, seed=10 * seed + i, spec=spec)]
    return out


def session_trial(item: Mapping[str, Any]) -> dict[str, Any]:
    """One seed: identify a simulated session and report each parameter's error and stds.

    item: seed, method ("joint" / "propagate"), specs (per step, optional), spread (optional),
    limits (``ExperimentLimits``, for ``margins``: the floor runs' peaks on the true robot as fractions of them).
    Returns seed, passed, verdicts per step, reasons, notices, wall/cpu time, truth, load and per parameter
    (the session's and the nuisance x_F0, y_F0 when estimated) the final value/std, the chained value and its
    naive (step-alone) and propagated std.
    """
    from otbot_hw.identification.session import identify_session

    seed = int(item["seed"])
    unloaded, loaded, load = perturbed_robot(seed, spread=item.get("spread"))
    recs = simulate_session(unloaded, loaded, seed, item.get("specs"))
    res = identify_session(recs, nominal(), method=item.get("method", "joint"), specs=item.get("specs"))
    truth = res.truth or {}
    std = res.std
    params = {}
    for n in SESSION_PARAMS + NUISANCE_PARAMS:
        if n not in res.estimated:
            continue
        params[n] = {"truth": truth.get(n), "value": res.values[n], "std": std[n], "chained": res.chained[n],
                     "naive_std": res.naive_std.get(n), "propagated_std": res.chained_std.get(n)}
    limits = item.get("limits") or ExperimentLimits()
    margins = {s: motion_margins(r[0].truth_q, r[0].truth_qd, r[0].torque, limits)
               for s, r in recs.items() if PAPER_EXPERIMENTS[s].fixture == "floor"}
    return {"seed": seed, "passed": res.passed, "method": res.method, "load": load, "margins": margins,
            "verdicts": {s: st.gates.verdict for s, st in res.steps.items()},
            "reasons": res.reasons + [r for st in res.steps.values() for r in st.gates.reasons], "notices": res.notices,
            "wall_time": res.wall_time, "cpu_time": res.cpu_time, "params": params}
