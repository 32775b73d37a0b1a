"""Diagnose recordings of an *independent* simulator (``benchmarks/independent_robot.py``).

The tool's own studies hide effects with the extended model it fits. Here every recording
comes from a simulator written separately (own 9x9 dynamics from body kinematics, own effect
forms, own sensor model, plain ``mcap`` writer, no truth topic), under random
piecewise-constant torques (fitting run) and random smooth torques (held-out run), 10 s each
at 100 Hz with the paper's noise. Cases: every catalog effect alone, pairs of effects, clean
runs, and wrong parameter files (the tool gets parameters that differ from the simulated
robot where it does not refit them). Each case runs on several seed pairs.

Scoring (``score``): an effect case is *right* when every true effect is named -- alone, or
in an ambiguous group of its look-alikes -- with every parameter within 20 % (a parameter
that is zero in truth within 20 % of the catalog's typical size), no other effect is named,
and the model is judged adequate. "Detected, small" names an effect too (left out of the model as
not mattering on these runs); a parameter the diagnosis says this recording does not determine
counts as right when the Fisher criterion at the truth agrees (``truth_fisher``), and so does an
effect it says is not identifiable; a parameter of an effect of several parameters also counts as
right beyond 20 % when that criterion cannot tell its estimate from the truth (``_indistinguishable``),
and an effect named in its nested form -- without the parameters that criterion says the recording
cannot reveal (wheel slip for a traction limit never reached) -- counts when the rest are right. A clean run is right when nothing is named; a
wrong-parameter-file run when the tool says "model inadequate" and names nothing.

Writes the block between the INDEPENDENT markers of docs/diagnose.md, the JSON results and
(``--recordings DIR``) keeps the recordings for ``benchmarks/diagnose.py``.

    .venv/bin/python benchmarks/diagnose_independent.py [--workers 2] [--seeds 3] [--cases a,b,...]

``--families all`` (or a list): every catalog effect at two magnitudes x excitation family (open-loop
families of benchmarks/diagnose_calibration.py and ``closed_loop``, the independent robot's own velocity
loop) x seed pair, resumable from ``docs/diagnose_families.jsonl`` by code version (``families_main``).
``--sim-check N``: the simulator's default integration against its RK45 reference (``sim_check``).

    nice .venv/bin/python benchmarks/diagnose_independent.py --families all --seeds 3 --workers 2 --doc
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import zlib
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import independent_robot as ir  # noqa: E402

TOLERANCE = 0.2
DURATION = 10.0
DT = 0.01


@dataclass
class Case:
    """One case: the true robot (``world``), what the tool should find (``truth``: catalog effect ->
    parameters), what the tool is told (``file``: parameter-file overrides; ``casters``,
    ``imu_position``: robot configuration), and the kind (effect, pair, clean, wrong)."""

    label: str
    kind: str
    description: str
    world: dict = field(default_factory=dict)
    truth: dict = field(default_factory=dict)
    file: dict = field(default_factory=dict)
    casters: tuple = ()
    imu_position: tuple | None = None


TWO_CASTERS = ((0.35, 0.12), (0.35, -0.12))
LOAD = {"mass": 15.0, "x": 0.12, "y": 0.05, "inertia": 0.2}

CASES = [
    Case("coulomb_wheels", "effect", "Coulomb 0.3 N m at both wheels, sharp sign", {"coulomb_w": 0.3},
         {"coulomb_wheels": {"c_w": 0.3}}),
    Case("coulomb_pivot", "effect", "Coulomb 0.3 N m at the pivot, sharp sign", {"coulomb_p": 0.3},
         {"coulomb_pivot": {"c_p": 0.3}}),
    Case("stribeck_wheels", "effect", "Stribeck excess 0.4 N m, v_s 0.5 rad/s, sharp sign", {"stribeck": (0.4, 0.5)},
         {"stribeck_wheels": {"s_w": 0.4, "v_s": 0.5}}),
    Case("rolling_resistance", "effect", "rolling resistance c_rr 0.003 as contact forces",
         {"c_rr": 0.003}, {"rolling_resistance": {"c_rr": 0.003}}),
    Case("caster_configured", "effect", "6 N drag at two casters (0.35, ±0.12) m, configured",
         {"caster_drag": 6.0, "casters": TWO_CASTERS}, {"caster_drag": {"f_cst": 6.0}}, casters=TWO_CASTERS),
    Case("caster_unknown", "effect", "6 N drag at one caster (-0.45, 0) m, not configured",
         {"caster_drag": 6.0, "casters": ((-0.45, 0.0),)}, {"caster_drag": {"f_cst": 6.0}}),
    Case("caster_front_pair", "effect", "6 N dry drag shared by two front casters (0.15, ±0.2) m, not configured",
         {"caster_drag": 6.0, "casters": ((0.15, 0.2), (0.15, -0.2))}, {"caster_drag": {"f_cst": 6.0}}),
    Case("wheel_slip", "effect", "creep 0.03 rad/(s N m), no traction limit", {"slip_k": 0.03},
         {"wheel_slip": {"k_slip": 0.03}}),
    Case("traction_limit", "effect", "creep 0.02 rad/(s N m), traction saturating at 3 N m per wheel",
         {"slip_k": 0.02, "slip_tmax": 3.0}, {"traction_limit": {"k_slip": 0.02, "t_trac": 3.0}}),
    Case("floor_slope", "effect", "gravity component (0.03, -0.025) m/s² on both centres of mass",
         {"slope": (0.03, -0.025)}, {"floor_slope": {"g_x": 0.03, "g_y": -0.025}}),
    Case("air_drag", "effect", "air drag 20 N s²/m² at the pivot", {"c_air": 20.0}, {"air_drag": {"c_air": 20.0}}),
    Case("gain_right", "effect", "right motor delivers 0.92 x command", {"gain": (-0.08, 0.0, 0.0)},
         {"gain_right": {"k_r": -0.08}}),
    Case("gain_left", "effect", "left motor delivers 1.06 x command", {"gain": (0.0, 0.06, 0.0)},
         {"gain_left": {"k_l": 0.06}}),
    Case("gain_pivot", "effect", "pivot motor delivers 0.92 x command", {"gain": (0.0, 0.0, -0.08)},
         {"gain_pivot": {"k_p": -0.08}}),
    Case("torque_saturation", "effect", "every drive saturates at 3.2 N m", {"u_max": (3.2, 3.2, 3.2)},
         {"torque_saturation": {"u_max": 3.2}}),
    Case("saturation_right", "effect", "right drive alone saturates at 3.0 N m", {"u_max": (3.0, np.inf, np.inf)},
         {"saturation_right": {"u_max_r": 3.0}}),
    Case("current_lag", "effect", "first-order current lag 30 ms on all motors", {"lag": 0.03},
         {"current_lag": {"T_i": 0.03}}),
    Case("imu_bias", "effect", "IMU bias (0.04, -0.03) m/s², 6 mrad/s", {"imu_bias": (0.04, -0.03, 0.006)},
         {"imu_bias": {"b_ax": 0.04, "b_ay": -0.03, "b_gz": 0.006}}),
    Case("gyro_bias_small", "effect", "gyro bias 5.9 mrad/s only (20°/min)", {"imu_bias": (0.0, 0.0, 0.0059)},
         {"imu_bias": {"b_ax": 0.0, "b_ay": 0.0, "b_gz": 0.0059}}),
    Case("imu_lever_arm", "effect", "IMU at (0.08, -0.04) m in B'', not configured", {"imu_position": (0.08, -0.04)},
         {"imu_lever_arm": {"d_x": 0.08, "d_y": -0.04}}),
    Case("imu_misalignment", "effect", "IMU yaw misalignment 0.05 rad", {"imu_yaw": 0.05},
         {"imu_misalignment": {"psi": 0.05}}),
    Case("imu_misalignment_small", "effect", "IMU yaw misalignment 0.01 rad (0.6°)", {"imu_yaw": 0.01},
         {"imu_misalignment": {"psi": 0.01}}),
    Case("imu_latency", "effect", "IMU samples 25 ms old", {"imu_latency": 0.025}, {"imu_latency": {"d_imu": 0.025}}),
    Case("encoder_scale", "effect", "right encoder reads 1.03 x angle", {"encoder_scale": (0.03, 0.0)},
         {"encoder_scale": {"e_r": 0.03, "e_l": 0.0}}),
    Case("wheel_friction_asymmetry", "effect", "b_r = b_w + 0.04, b_l = b_w - 0.04", {"db_w": 0.04},
         {"wheel_friction_asymmetry": {"db_w": 0.04}}),
    Case("radius_one_wheel", "effect", "right wheel radius +3 %, left nominal", {"radius_change": (0.03, 0.0)},
         {"wheel_radii": {"dr_r": 0.03, "dr_l": 0.0}}),
    Case("radius_asymmetry", "effect", "radii +1.5 % right, -1.5 % left", {"radius_change": (0.015, -0.015)},
         {"wheel_radii": {"dr_r": 0.015, "dr_l": -0.015}}),
    Case("imu_configured", "clean", "IMU at (0.08, -0.04) m, configured: nothing to find",
         {"imu_position": (0.08, -0.04)}, {}, imu_position=(0.08, -0.04)),
    Case("none", "clean", "no effect (negative control)", {}, {}),
    # two at once
    Case("bias+coulomb", "pair", "IMU bias beside wheel Coulomb friction",
         {"imu_bias": (0.03, -0.02, 0.004), "coulomb_w": 0.3},
         {"imu_bias": {"b_ax": 0.03, "b_ay": -0.02, "b_gz": 0.004}, "coulomb_wheels": {"c_w": 0.3}}),
    Case("stribeck+coulomb", "pair", "Stribeck 0.3 N m (v_s 0.5) beside Coulomb 0.2 N m at the wheels",
         {"stribeck": (0.3, 0.5), "coulomb_w": 0.2},
         {"stribeck_wheels": {"s_w": 0.3, "v_s": 0.5}, "coulomb_wheels": {"c_w": 0.2}}),
    Case("slope+gain", "pair", "floor slope beside a right-motor gain error",
         {"slope": (-0.03, 0.02), "gain": (-0.08, 0.0, 0.0)},
         {"floor_slope": {"g_x": -0.03, "g_y": 0.02}, "gain_right": {"k_r": -0.08}}),
    Case("pivot+misalignment", "pair", "pivot Coulomb beside an IMU yaw misalignment",
         {"coulomb_p": 0.3, "imu_yaw": 0.03}, {"coulomb_pivot": {"c_p": 0.3}, "imu_misalignment": {"psi": 0.03}}),
    Case("lag+lever", "pair", "current lag beside an IMU lever arm",
         {"lag": 0.03, "imu_position": (0.06, 0.05)},
         {"current_lag": {"T_i": 0.03}, "imu_lever_arm": {"d_x": 0.06, "d_y": 0.05}}),
    Case("drag+encoder", "pair", "air drag beside a right-encoder scale error",
         {"c_air": 20.0, "encoder_scale": (0.03, 0.0)},
         {"air_drag": {"c_air": 20.0}, "encoder_scale": {"e_r": 0.03, "e_l": 0.0}}),
    Case("caster+asymmetry", "pair", "configured casters' drag beside a wheel friction asymmetry",
         {"caster_drag": 6.0, "casters": TWO_CASTERS, "db_w": 0.04},
         {"caster_drag": {"f_cst": 6.0}, "wheel_friction_asymmetry": {"db_w": 0.04}}, casters=TWO_CASTERS),
    Case("saturation+pivot", "pair", "right drive saturating beside pivot Coulomb friction",
         {"u_max": (3.0, np.inf, np.inf), "coulomb_p": 0.3},
         {"saturation_right": {"u_max_r": 3.0}, "coulomb_pivot": {"c_p": 0.3}}),
    # wrong parameter files
    Case("phantom_load", "wrong", "file has a 15 kg platform load at (0.12, 0.05) m that is not there", {}, {},
         file={"load": LOAD}),
    Case("missing_load", "wrong", "robot carries 20 kg at (0.15, -0.10) m, file has none",
         {"params_load": {"mass": 20.0, "x": 0.15, "y": -0.10, "inertia": 0.3}}, {}),
    Case("wrong_l1", "wrong", "file says l1 = 0.28 m, the robot has 0.25 m", {}, {}, file={"l1": 0.28}),
]
BY_LABEL = {c.label: c for c in CASES}


TRACTION_CURVES = ("magic", "tanh", "clip")  # ``independent_robot.World.traction_curve``


def with_traction_curve(case: Case, curve: str = "magic") -> Case:
    """The case with the independent robot's traction curve ``curve`` (``--traction-curve``; the same creep
    slope and limit, another knee) where the case has a traction limit; other cases unchanged."""
    if curve not in TRACTION_CURVES:
        raise ValueError(f"unknown traction curve {curve!r} (known: {', '.join(TRACTION_CURVES)})")
    if curve == "magic" or "slip_tmax" not in case.world:
        return case
    return replace(case, world={**case.world, "traction_curve": curve},
                   description=case.description + f" ({curve} traction curve)")


def world_of(case: Case, base: dict) -> tuple[ir.World, dict]:
    """The simulator's World and true parameters of a case."""
    w = dict(case.world)
    p = dict(base)
    if "params_load" in w:
        p = ir.with_load(p, **w.pop("params_load"))
    return ir.World(**w), p


def tool_inputs(case: Case):
    """Parameter file (OtbotParams) and robot configuration (EffectGeometry) the tool is given."""
    from otbot_hw.diagnose.geometry import EffectGeometry
    from otbot_hw.params import nominal

    P = nominal()
    f = dict(case.file)
    if "load" in f:
        ld = f.pop("load")
        P = P.with_load(ld["mass"], ld["x"], ld["y"], ld["inertia"])
    if f:
        P = P.replace(**f)
    return P, EffectGeometry(tuple(case.casters), case.imu_position, "case")


def seeds(rep: int) -> tuple[int, int]:
    return 31 + 2 * rep, 32 + 2 * rep


def family_noise_seed(family: str, seed: int) -> list[int]:
    """The fitting run's noise seed: its own per excitation family (a family's name folded in), so that the
    families' misses are not one noise draw seen five times (they shared seed + 1000 until 2026-11-26)."""
    return [seed + 1000, zlib.crc32(family.encode())]


def make_recordings(case: Case, rep: int, folder: Path, duration: float = DURATION,
                    family: str = "piecewise", heldout_cache: Path | None = None) -> list[Path]:
    """Fitting (piecewise-constant torques, an excitation ``family`` of benchmarks/diagnose_calibration.py, or
    ``closed_loop``: ``independent_robot.closed_loop``, the robot tracking a random twist with its own PI loop
    on its noisy encoder rates) and held-out (smooth torques) recordings of one case. ``heldout_cache``: a
    folder where the held-out recording (the same for every family) is kept and reused."""
    world, p = world_of(case, ir.load_params())
    paths = []
    for kind, seed in zip(("piecewise", "smooth"), seeds(rep)):
        path = folder / f"{case.label}_{rep}_{'fit' if kind == 'piecewise' else 'heldout'}.mcap"
        if kind == "smooth" and heldout_cache is not None:
            path = Path(heldout_cache) / f"{case.label}_{rep}_{duration:g}s_heldout.mcap"
            if path.exists():
                paths.append(path)
                continue
        if kind == "piecewise" and family == "closed_loop":  # the robot tracking a twist with its own PI loop
            U, sens = ir.closed_loop(ir.Otbot(p, world), duration, DT, seed, noise_seed=family_noise_seed(family, seed))
            ir.write_mcap(path, DT, U, sens)
        elif kind == "piecewise" and family != "piecewise":
            import diagnose_calibration as dc

            U = dc.excitation(family, duration, DT, seed)
            robot = ir.Otbot(p, world)
            ir.write_mcap(path, DT, U, robot.sensors(robot.run(U, DT),
                                                     np.random.default_rng(family_noise_seed(family, seed))))
        elif kind == "smooth" and heldout_cache is not None:  # complete files only in the cache
            part = path.with_name(path.stem + f".{os.getpid()}.part.mcap")
            ir.record(part, world, kind, seed, duration, DT, params=p)
            part.replace(path)
        else:
            ir.record(path, world, kind, seed, duration, DT, params=p)
        paths.append(path)
    return paths


def _zero_tolerance(param: str) -> float:
    """Absolute tolerance for a parameter that is zero in truth: 20 % of the catalog's typical size."""
    from otbot_hw.diagnose.catalog import CATALOG

    for e in CATALOG:
        for m in e.magnitudes:
            if param in m and m[param] != 0:
                return TOLERANCE * abs(m[param])
    return 1e-3


def score(case: Case, r: dict, fisher: dict | None = None) -> dict:
    """Right or wrong, with the estimates and errors (see module doc). With ``fisher`` (``truth_fisher``), a
    true effect the recording cannot reveal by that criterion also counts as found when the diagnosis says
    it is not identifiable from this recording (and only then)."""
    from otbot_hw.diagnose.catalog import effect as catalog_effect

    named = [e["name"] for e in r["effects"]]
    groups = [[c["name"] for c in g["candidates"]] for g in r["ambiguous"]]
    est: dict[str, dict[str, float]] = {e["name"]: {k: v["value"] for k, v in e["parameters"].items()}
                                        for e in r["effects"]}
    for g in r["ambiguous"]:
        for c in g["candidates"]:
            est.setdefault(c["name"], {k: v["value"] for k, v in c["parameters"].items()})
    # "detected, small": named with its parameters, left out of the model because on these runs it does not
    # matter physically (air drag 10 N s^2/m^2 at 0.15 m/s: 0.7 % of the torque) -- found when they are right
    small = [e["name"] for e in r.get("detected_small", [])]
    for e in r.get("detected_small", []):
        est.setdefault(e["name"], {k: v["value"] for k, v in e["parameters"].items()})
    errors, found = {}, {}
    for eff, params in case.truth.items():
        in_group = next((g for g in groups if eff in g), None)
        look = set(catalog_effect(eff).lookalikes) | {e for g in groups for e in g
                                                       if eff in catalog_effect(e).lookalikes}
        ok_group = in_group is not None and all(x == eff or x in look or x in case.truth for x in in_group)
        present = eff in named or ok_group or eff in small
        nested = None if present else _nested_form(eff, params, named, (fisher or {}).get(eff))
        present = present or nested is not None
        errs = {}
        for k, v in params.items():
            if nested is not None and k not in est.get(nested, {}):
                continue  # the part the recording cannot reveal (``_nested_form``)
            got = est.get(nested or eff, {}).get(k)
            if got is None:
                errs[k] = None
            elif v != 0:
                errs[k] = (got - v) / abs(v)
            else:
                errs[k] = (got - v) / _zero_tolerance(k) * TOLERANCE  # scaled so that |err| <= 0.2 passes
        errors[eff] = errs
        # a parameter of a found effect that the diagnosis says this recording does not determine counts as
        # right when the Fisher criterion at the truth agrees (``truth_fisher``: a 20 % change of that parameter
        # alone does not show)
        undetermined = {x["name"] for x in r.get("not_identifiable", [])
                        if x.get("kind") == "parameter" and x.get("effect") == eff}
        per_param = (fisher or {}).get(eff, {}).get("parameters", {})
        found[eff] = present and all((e is not None and abs(e) <= TOLERANCE)
                                     or (k in undetermined and per_param.get(k, {}).get("identifiable") is False)
                                     or _indistinguishable(e, per_param.get(k))
                                     for k, e in errs.items())
        if fisher is not None and not fisher[eff]["identifiable"] and not present:
            found[eff] = eff in {x["name"] for x in r.get("not_identifiable", []) if x.get("kind") == "effect"}
    truth_names = set(case.truth)
    truth_names |= {n for eff, ps in case.truth.items() if found.get(eff)
                    for n in [_nested_form(eff, ps, named, (fisher or {}).get(eff))] if n}
    extra = [n for n in named if n not in truth_names]
    extra += [",".join(g) for g in groups if not (set(g) & truth_names)]
    adequate = bool(r["model_adequate"])
    if case.kind == "clean":
        right = not named and not groups and adequate
    elif case.kind == "wrong":
        right = not adequate and not named and not groups
    else:
        right = adequate and all(found.values()) and not extra
    return {"right": right, "found": found, "errors": errors, "extra": extra, "estimate": est}


def _nested_form(eff: str, params: dict, named: list[str], fisher: dict | None) -> str | None:
    """A named effect that is the true effect ``eff`` with the parameters this recording cannot reveal left
    out (its parameters a subset of ``eff``'s; every left-out one not identifiable by the Fisher criterion
    at the truth, ``fisher``): a traction limit at 3 N m under constant wheel torques of 1 N m is pure creep,
    and "wheel slip" with the creep slope is the answer the recording allows. None if there is none."""
    from otbot_hw.diagnose.catalog import effect as catalog_effect

    per_param = (fisher or {}).get("parameters", {})
    for n in named:
        mine = set(catalog_effect(n).parameters)
        if n != eff and mine < set(params) and all(per_param.get(k, {}).get("identifiable") is False
                                                   for k in set(params) - mine):
            return n
    return None


def _indistinguishable(err: float | None, fisher_param: dict | None) -> bool:
    """Whether the relative error ``err`` of an estimate does not show by the Fisher criterion at the truth
    (``fisher_param``: chi2 of a ``TOLERANCE`` change of that parameter and the chi2 a fit needs): its chi2,
    (err / TOLERANCE)^2 x that (linear in the parameter), below the need -- the recording cannot tell the
    estimate from the truth, so 20 % is finer than it can resolve (a 3 mrad/s gyro bias in 10 s at the
    paper's 13.7 mrad/s noise: std 0.45 mrad/s, 15 %). Beyond 20 % only where a 20 % change does not show."""
    if err is None or not fisher_param or "chi2" not in fisher_param:
        return False
    return bool((err / TOLERANCE) ** 2 * fisher_param["chi2"] < fisher_param["needed"])


def truth_fisher(case: Case, fit_data, P, geometry) -> dict[str, dict]:
    """The Fisher criterion at the truth, per true effect of ``case``: its signature energy in the fitting
    recording at the true size (``identifiability.signature_chi2``, the free nominal parameters projected
    out) against what a nested fit needs (``needed_chi2``); for an effect of several parameters also each
    parameter alone (``parameters``: a ``TOLERANCE`` change of it at the truth, against one parameter's need),
    which scores a parameter the diagnosis says this recording does not determine."""
    from otbot_hw.diagnose.identifiability import needed_chi2, signature_chi2
    from otbot_hw.diagnose.select import free_nominal
    from otbot_hw.model.effects import ExtendedModel

    model = ExtendedModel.paper(P).with_values(geometry.effect_values())
    out = {}
    for eff, params in case.truth.items():
        chi2, n = signature_chi2(fit_data, model, free_nominal(fit_data), dict(params))
        need = needed_chi2(len(params), n)
        out[eff] = {"chi2": chi2, "needed": need, "identifiable": bool(chi2 >= need)}
        if len(params) > 1:  # each parameter alone: does a TOLERANCE change of it, at the truth, show?
            on = model.with_values(dict(params))
            out[eff]["parameters"] = {}
            for k, v in params.items():
                step = v * (1 + TOLERANCE) if v != 0 else _zero_tolerance(k)
                c, n = signature_chi2(fit_data, on, free_nominal(fit_data), {k: step})
                out[eff]["parameters"][k] = {"chi2": c, "needed": needed_chi2(1, n),
                                             "identifiable": bool(c >= needed_chi2(1, n))}
    return out


def run_case(case: Case | str, rep: int = 0, keep: Path | None = None, duration: float = DURATION,
             family: str = "piecewise", fisher: bool = False, heldout_cache: Path | None = None,
             traction_curve: str = "magic") -> dict:
    """Simulate, write, load and diagnose one case on seed pair ``rep`` (recordings of ``duration`` s; the
    fitting run under the excitation ``family``); ``fisher``: also the Fisher criterion at the truth
    (``truth_fisher``), which scores a "not identifiable" answer; ``traction_curve``: the independent
    robot's traction knee in a traction case (``with_traction_curve``)."""
    from otbot_hw.diagnose.data import load
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.recording import read_recording

    case = with_traction_curve(BY_LABEL[case] if isinstance(case, str) else case, traction_curve)
    t0, c0 = time.perf_counter(), time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(keep) if keep else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        paths = [folder / f"{case.label}_{rep}_{k}.mcap" for k in ("fit", "heldout")]
        if not (keep and duration == DURATION and family == "piecewise" and all(p.exists() for p in paths)):
            paths = make_recordings(case, rep, folder, duration, family, heldout_cache)  # kept ones are reused
        assert read_recording(paths[0]).truth_q is None
        t_sim, c_sim = time.perf_counter() - t0, time.process_time() - c0
        P, geometry = tool_inputs(case)
        fit_data = load(paths[:1])
        r = diagnose(fit_data, P, load(paths[1:]), geometry=geometry)
        fish = truth_fisher(case, fit_data, P, geometry) if fisher else None
    s = score(case, r, fish)
    hb, ha = r["fit_before"]["heldout"], r["fit_after"]["heldout"]
    worst = min(hb, key=lambda ch: hb[ch]["fit_percent"]) if hb else None
    return {"case": case.label, "kind": case.kind, "rep": rep, "seeds": list(seeds(rep)), "family": family,
            "traction_curve": case.world.get("traction_curve", "magic"),
            "shape_refinements": r.get("shape_refinements", []),
            "description": case.description, "truth": case.truth,
            "named": [e["name"] for e in r["effects"]],
            "ambiguous": [[c["name"] for c in g["candidates"]] for g in r["ambiguous"]],
            "small": [e["name"] for e in r["detected_small"]],
            "model_adequate": r["model_adequate"], "suspects": r["suspect_parameters"],
            "withheld": [w["name"] for w in r["withheld"]],
            "significance": {e["name"]: e["significance"]["statement"] for e in r["effects"]},
            **s, "worst_channel": worst,
            "heldout_before": hb[worst]["fit_percent"] if worst else None,
            "heldout_after": ha[worst]["fit_percent"] if worst else None,
            "verdict": r["verdict"], "sim_s": t_sim, "diagnose_s": r["elapsed_s"], "diagnose_cpu_s": r.get("cpu_s"), "fisher": fish,
            # the diagnosis's list holds effects, parameters and held-out recordings beyond the fitting range
            # (``kind``): the effects here, the others by kind
            "not_identifiable": [x["name"] for x in r.get("not_identifiable", []) if x.get("kind") == "effect"],
            "not_identifiable_parameters": [f"{x.get('effect', 'nominal')}.{x['name']}" for x in
                                            r.get("not_identifiable", []) if x.get("kind") == "parameter"],
            "sim_cpu_s": c_sim, "total_s": time.perf_counter() - t0, "total_cpu_s": time.process_time() - c0}


def _reported(r: dict) -> str:
    parts = list(r["named"]) + ["{" + ", ".join(sorted(g)) + "}" for g in r["ambiguous"]]
    if not r["model_adequate"]:
        parts = ["model inadequate" + (f" (withheld {', '.join(r['withheld'])})" if r["withheld"] else "")]
    if r["small"]:
        parts.append("small: " + ", ".join(r["small"]))
    return "; ".join(parts) or "none"


def _errors(r: dict) -> str:
    out = []
    for eff, errs in r["errors"].items():
        for k, v in errs.items():
            out.append(f"{k} " + ("missing" if v is None else f"{100 * v:+.0f} %"))
    return ", ".join(out) or "-"


def tables(rows: list[dict], labels: list[str]) -> list[str]:
    out = ["| case | kind | truth | right | reported per seed pair | errors per seed pair | diagnose time (s) |",
           "|---|---|---|---|---|---|---|"]
    for lab in labels:
        rs = sorted((r for r in rows if r["case"] == lab and "error" not in r), key=lambda r: r["rep"])
        if not rs:
            continue
        truth = "; ".join(f"{e}: " + ", ".join(f"{k} = {v:g}" for k, v in p.items()) for e, p in rs[0]["truth"].items())
        out.append(f"| {lab}: {rs[0]['description']} | {rs[0]['kind']} | {truth or '-'} | "
                   f"{sum(r['right'] for r in rs)}/{len(rs)} | {' / '.join(_reported(r) for r in rs)} | "
                   f"{' / '.join(_errors(r) for r in rs)} | {max(r['diagnose_s'] for r in rs):.1f} |")
    return out


def summary(rows: list[dict]) -> dict:
    ok = [r for r in rows if "error" not in r]
    eff = [r for r in ok if r["kind"] in ("effect", "pair")]
    out = {"runs": len(rows), "failed_runs": len(rows) - len(ok),
           "effect_runs": len(eff), "effect_right": sum(r["right"] for r in eff),
           "single_right": sum(r["right"] for r in eff if r["kind"] == "effect"),
           "single_runs": sum(r["kind"] == "effect" for r in eff),
           "pair_right": sum(r["right"] for r in eff if r["kind"] == "pair"),
           "pair_runs": sum(r["kind"] == "pair" for r in eff)}
    for kind in ("clean", "wrong"):
        rs = [r for r in ok if r["kind"] == kind]
        out[f"{kind}_runs"], out[f"{kind}_right"] = len(rs), sum(r["right"] for r in rs)
    out["effect_rate"] = out["effect_right"] / max(out["effect_runs"], 1)
    out["worst_diagnose_s"] = max((r["diagnose_s"] for r in ok), default=float("nan"))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--seeds", type=int, default=3, help="seed pairs per case (default 3)")
    ap.add_argument("--cases", default="", help="comma-separated case labels (default: all)")
    ap.add_argument("--recordings", type=Path, default=None, help="keep the recordings in this folder")
    ap.add_argument("--out", default=str(ROOT / "docs" / "diagnose_independent.json"), help="JSON results file")
    ap.add_argument("--no-doc", action="store_true", help="do not rewrite docs/diagnose.md")
    ap.add_argument("--families", default="", help="comma-separated excitation families of the fitting run "
                    "(benchmarks/diagnose_calibration.py's open-loop ones and closed_loop: the independent robot's "
                    "own velocity loop) or 'all': a family x effect table instead")
    ap.add_argument("--magnitudes", default="1,0.5", help="with --families: effect sizes relative to the cases' "
                    "(default 1,0.5)")
    ap.add_argument("--jsonl", default=str(ROOT / "docs" / "diagnose_families.jsonl"),
                    help="with --families: JSON lines, appended as results come (rows of this code version already "
                         "there are skipped, rows of other versions ignored)")
    ap.add_argument("--doc", action="store_true", help="with --families: write the table into docs/diagnose.md")
    ap.add_argument("--table-only", action="store_true", help="with --families: only the table from --jsonl")
    ap.add_argument("--traction-curve", default="magic", metavar="magic|tanh|clip",
                    help="knee of the independent robot's traction curve in the traction cases (same creep slope "
                         "and limit): magic (its own, the default), tanh, clip (a hard clip); in the code hash")
    ap.add_argument("--sim-check", type=int, default=0, metavar="N",
                    help="only compare the default integration of the independent simulator with the reference "
                         "(RK45 rtol 1e-8) on N cases (CPU time, differences in sensor sigmas) and exit")
    args = ap.parse_args()
    if args.traction_curve not in TRACTION_CURVES:
        print(f"error: --traction-curve {args.traction_curve!r}: one of {', '.join(TRACTION_CURVES)} expected",
              file=sys.stderr)
        return 2
    if args.sim_check:
        return sim_check(args.sim_check)
    if args.families:
        return families_main(args)
    chosen = [c for c in CASES if not args.cases or c.label in args.cases.split(",")]
    t0 = time.perf_counter()
    rows = []
    with ProcessPoolExecutor(max_workers=args.workers) as ex:
        futs = {ex.submit(run_case, c.label, rep, args.recordings, traction_curve=args.traction_curve): (c.label, rep)
                for rep in range(args.seeds) for c in chosen}
        for f in as_completed(futs):
            try:
                r = f.result()
            except Exception as exc:  # a failing run is reported, the others go on
                r = {"case": futs[f][0], "rep": futs[f][1], "error": repr(exc), "kind": BY_LABEL[futs[f][0]].kind}
            rows.append(r)
            print(f"[independent] {time.perf_counter() - t0:6.0f} s  {r['case']} #{r['rep']}: "
                  + ("ERROR " + r["error"] if "error" in r else
                     f"{'RIGHT' if r['right'] else 'wrong'}  {_reported(r)}  {_errors(r)}  ({r['diagnose_s']:.1f} s)"),
                  file=sys.stderr, flush=True)
    order = {c.label: i for i, c in enumerate(CASES)}
    rows.sort(key=lambda r: (order[r["case"]], r["rep"]))
    sm = summary(rows)
    Path(args.out).write_text(json.dumps({"summary": sm, "runs": rows}, indent=1, default=float) + "\n")
    labels = [c.label for c in chosen]
    lines = ["<!-- INDEPENDENT:BEGIN (written by benchmarks/diagnose_independent.py) -->", "",
             f"{sm['runs']} runs ({len(labels)} cases x {args.seeds} seed pairs; {sm['failed_runs']} failed), "
             f"{(time.perf_counter() - t0) / 60:.1f} min on {args.workers} worker process(es). Per run: 10 s "
             "piecewise-constant-torque fitting recording + 10 s smooth-torque held-out recording, 100 Hz, paper "
             "noise, from `benchmarks/independent_robot.py`, written with the plain `mcap` package (no truth topic). "
             "Right = every true effect named (alone or in a group of its look-alikes) with each parameter within "
             "20 %, nothing else named, model adequate; clean runs: nothing named; wrong parameter files: "
             "\"model inadequate\", nothing named. Errors = (recovered - true) / |true| (for a true zero: in "
             "units of 20 % of the catalog's typical size). All results: `docs/diagnose_independent.json`.", "",
             f"**Single and two-effect cases right: {sm['effect_right']}/{sm['effect_runs']} = "
             f"{100 * sm['effect_rate']:.0f} %** (single {sm['single_right']}/{sm['single_runs']}, two at once "
             f"{sm['pair_right']}/{sm['pair_runs']}); clean runs with nothing named: {sm['clean_right']}/"
             f"{sm['clean_runs']}; wrong parameter files reported as \"model inadequate\": {sm['wrong_right']}/"
             f"{sm['wrong_runs']}. Slowest diagnosis: {sm['worst_diagnose_s']:.1f} s (two runs at a time on the "
             "2-core machine; `benchmarks/diagnose.py` times them one at a time).", ""]
    lines += tables(rows, labels)
    for r in rows:
        if "error" in r:
            lines.append(f"\nRun `{r['case']}` #{r['rep']} failed: {r['error']}")
    lines += ["", "<!-- INDEPENDENT:END -->"]
    if not args.no_doc:
        doc = ROOT / "docs" / "diagnose.md"
        text = doc.read_text()
        a = text.index("<!-- INDEPENDENT:BEGIN")
        b = text.index("<!-- INDEPENDENT:END -->") + len("<!-- INDEPENDENT:END -->")
        doc.write_text(text[:a] + "\n".join(lines) + text[b:])
    print(json.dumps(sm))
    return 0


#: one case per catalog effect (saturation_left / saturation_pivot: as saturation_right, not repeated)
FAMILY_CASES = ("coulomb_wheels", "coulomb_pivot", "stribeck_wheels", "rolling_resistance", "caster_configured",
                "wheel_slip", "traction_limit", "floor_slope", "air_drag", "gain_right", "gain_left", "gain_pivot",
                "torque_saturation", "saturation_right", "current_lag", "imu_bias", "imu_lever_arm",
                "imu_misalignment", "imu_latency", "encoder_scale", "wheel_friction_asymmetry", "radius_one_wheel")
KEEP = {"casters", "slip_tmax", "v_s", "t_trac"}  # positions and shape parameters: not scaled with the magnitude
SATURATION = {"u_max", "u_max_r", "u_max_l", "u_max_p"}  # levels: a smaller effect saturates later


def _scale(k: str, v, f: float):
    if k in KEEP:
        return v
    if k in SATURATION:  # magnitude f of a saturation: the level raised by (1 - f) / 2 of itself
        g = 1.0 + (1.0 - f) / 2.0
        return tuple(x * g for x in v) if isinstance(v, tuple) else v * g
    if k == "stribeck":
        return (v[0] * f, v[1])
    return tuple(x * f for x in v) if isinstance(v, tuple) else v * f


def magnitude_case(label: str, f: float) -> Case:
    """Case ``label`` with its effect at magnitude ``f`` (1: as listed; 0.5: half the size -- a saturation
    level 1.25 x higher; positions of casters, Stribeck speed and traction limit kept)."""
    c = BY_LABEL[label]
    if f == 1.0:
        return c
    world = {k: _scale(k, v, f) for k, v in c.world.items()}
    truth = {e: {k: _scale(k, v, f) for k, v in ps.items()} for e, ps in c.truth.items()}
    return Case(f"{label}@{f:g}", c.kind, f"{c.description} (x{f:g})", world, truth, dict(c.file), c.casters,
                c.imu_position)


HELDOUT_CACHE = Path(tempfile.gettempdir()) / "otbot-diagnose-families-heldout"
#: ``--families all``: the paper's constant torques, random piecewise-constant (0.4-1.2 s holds, +-8 N m), multisine,
#: PRBS, chirp (benchmarks/diagnose_calibration.py) and the independent robot's own closed loop
#: (``independent_robot.closed_loop``): 22 effects x 2 magnitudes x 6 families x 3 seed pairs = 792 runs
ALL_FAMILIES = ("constant", "piecewise_long", "multisine", "prbs", "chirp", "closed_loop")
#: the other hold ranges, by name only: piecewise_short is the fitting run of the study without --families
#: (every case, 3 seed pairs); piecewise_slow adds 1-3 s holds
MORE_FAMILIES = ("piecewise_short", "piecewise_slow")


def code_hash(traction_curve: str = "magic") -> str:
    """12 hex digits over what a study row depends on: the diagnosis and the model it fits (otbot_hw/diagnose/*.py,
    otbot_hw/model/*.py), the independent
    simulator (and its traction curve, ``--traction-curve``), the excitation families and, from this file, the
    cases, their magnitudes, the recording and the scoring. Rows of another hash are from another code version
    and are not mixed into a table."""
    import hashlib
    import inspect

    import diagnose_calibration as dc

    h = hashlib.sha256()
    sources = sorted((ROOT / "otbot_hw" / "diagnose").glob("*.py")) + sorted((ROOT / "otbot_hw" / "model").glob("*.py"))
    for path in sources + [ROOT / "benchmarks" / "independent_robot.py"]:
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    for fn in (dc.excitation, family_noise_seed, make_recordings, run_case, with_traction_curve, score, _nested_form, _indistinguishable, _zero_tolerance,
               truth_fisher,
               _scale, magnitude_case):
        h.update(inspect.getsource(fn).encode())
    h.update(repr([(c.label, c.kind, c.world, c.truth, c.file, c.casters, c.imu_position) for c in CASES]).encode())
    h.update(repr((DURATION, DT, TOLERANCE)).encode())
    if traction_curve != "magic":  # the default keeps the hash of the study rows written before the option
        h.update(f"traction_curve={traction_curve}".encode())
    return h.hexdigest()[:12]


def run_family_case(label: str, f: float, rep: int, family: str, version: str = "",
                    traction_curve: str = "magic") -> dict:
    """One run of the family study; the held-out recording (the same for every family) cached per code
    ``version`` (a cache of an older simulator is not reused)."""
    cache = HELDOUT_CACHE / (version or "unversioned")
    cache.mkdir(parents=True, exist_ok=True)
    r = run_case(magnitude_case(label, f), rep, None, DURATION, family, fisher=True, heldout_cache=cache,
                 traction_curve=traction_curve)
    r.update(case=label, magnitude=f, hash=version)
    return r


def _truth_ni(r: dict) -> list[str]:
    """True effects of a row the diagnosis called "not identifiable from this recording"."""
    return [e for e in r.get("truth", {}) if e in set(r.get("not_identifiable") or [])]


def family_table(rows: list[dict], fams: list[str], labels: list[str]) -> list[str]:
    """Family x effect table: right / runs per cell (both magnitudes, every seed pair); "n.i. k": k of those
    runs answered "not identifiable from this recording" for the true effect (right only where the Fisher
    criterion at the truth agrees; listed in ``ni_table``); the last rows: per family % right and runs."""
    ok = [r for r in rows if "error" not in r]
    lines = ["| effect | " + " | ".join(fams) + " |", "|---|" + "---|" * len(fams)]
    for lab in labels:
        cells = []
        for f in fams:
            rs = [r for r in ok if r["case"] == lab and r["family"] == f]
            ni = sum(bool(_truth_ni(r)) for r in rs)
            cells.append(f"{sum(r['right'] for r in rs)}/{len(rs)}" + (f" (n.i. {ni})" if ni else "") if rs else "-")
        lines.append(f"| {lab} | " + " | ".join(cells) + " |")
    cells = []
    for f in fams:
        rs = [r for r in ok if r["family"] == f]
        cells.append(f"**{100 * sum(r['right'] for r in rs) / len(rs):.0f} %** ({sum(r['right'] for r in rs)}/{len(rs)})"
                     if rs else "-")
    lines.append("| **all effects** | " + " | ".join(cells) + " |")
    failed = [sum("error" in r and r["family"] == f for r in rows) for f in fams]
    if any(failed):
        lines.append("| failed runs | " + " | ".join(str(x) for x in failed) + " |")
    return lines


def ni_table(rows: list[dict]) -> list[str]:
    """Every "not identifiable from this recording" verdict for a true effect, with the Fisher criterion at the
    truth (signature chi^2 / needed) and whether it scored right."""
    ni = [r for r in rows if "error" not in r and _truth_ni(r)]
    if not ni:
        return ["No run answered \"not identifiable from this recording\" for its true effect."]
    out = ["| family | effect | magnitude | seed pair | Fisher chi^2 at the truth / needed | right |",
           "|---|---|---|---|---|---|"]
    for r in sorted(ni, key=lambda r: (r["family"], r["case"], r["magnitude"], r["rep"])):
        for e in _truth_ni(r):
            fi = (r.get("fisher") or {}).get(e, {})
            out.append(f"| {r['family']} | {r['case']} | x{r['magnitude']:g} | {r['rep']} | "
                       f"{fi.get('chi2', float('nan')):.3g} / {fi.get('needed', float('nan')):.3g} | "
                       f"{'yes' if r['right'] else 'no'} |")
    return out


def miss_lines(rows: list[dict]) -> list[str]:
    """The confusion of the wrong runs: per family and effect, what was reported instead (counts)."""
    from collections import Counter

    wrong = [r for r in rows if "error" not in r and not r["right"]]
    out = []
    for (fam, lab) in sorted({(r["family"], r["case"]) for r in wrong}):
        c = Counter(f"{_reported(r)} [{_errors(r)}]" for r in wrong if r["family"] == fam and r["case"] == lab)
        out.append(f"* {fam} / {lab}: " + "; ".join(f"{k}" + (f" (x{n})" if n > 1 else "") for k, n in c.items()))
    return out


def _load_rows(path: Path, version: str) -> tuple[list[dict], dict]:
    """Rows of ``path`` made by code ``version``, and the counts of rows of other versions (ignored)."""
    from collections import Counter

    rows = [json.loads(x) for x in path.read_text().splitlines() if x.strip()] if path.exists() else []
    other = Counter(r.get("hash") or "none" for r in rows if r.get("hash") != version)
    mine: dict[tuple, dict] = {}  # one row per key: the last, a failed run replaced by a later success
    for r in rows:
        key = (r["family"], r["case"], r["magnitude"], r["rep"])
        if r.get("hash") == version and ("error" not in r or "error" in mine.get(key, {"error": 1})):
            mine[key] = r
    return list(mine.values()), dict(other)


def families_main(args) -> int:
    """Every catalog effect (``FAMILY_CASES``) at each magnitude x excitation family x seed pair, one row per
    run appended to ``--jsonl`` as it comes, keyed by (family, case, magnitude, seed pair) and the code hash
    (``code_hash``; rows of this version already there are skipped, rows of other versions ignored -- said
    when it happens). Run order: seed pair, magnitude, case, family (an interrupted study covers every family
    evenly). First a timed sample, three runs per worker spread evenly over the plan: the estimate of the
    whole study is printed from them (each worker's first left out; or from rows of this version already
    there) before the rest starts. The family x effect table
    is printed and (``--doc``) written between the FAMILIES markers of docs/diagnose.md."""
    fams = list(ALL_FAMILIES) if args.families == "all" else args.families.split(",")
    unknown = [f for f in fams if f not in ALL_FAMILIES + MORE_FAMILIES + ("piecewise",)]
    if unknown:
        print(f"error: unknown excitation family {', '.join(unknown)} (known: all = {', '.join(ALL_FAMILIES)}; "
              f"{', '.join(MORE_FAMILIES)})", file=sys.stderr)
        return 2
    labels = [c for c in FAMILY_CASES if not args.cases or c in args.cases.split(",")]
    try:
        mags = [float(x) for x in args.magnitudes.split(",")]
    except ValueError:
        print(f"error: --magnitudes {args.magnitudes!r}: comma-separated numbers expected", file=sys.stderr)
        return 2
    out = Path(args.jsonl)
    version = code_hash(args.traction_curve)
    rows, other = _load_rows(out, version)
    if other:
        print(f"[families] code version {version}: ignoring {sum(other.values())} rows of {out.name} from other "
              f"versions ({', '.join(f'{k}: {v}' for k, v in sorted(other.items()))})", file=sys.stderr, flush=True)
    done = {(r["family"], r["case"], r["magnitude"], r["rep"]) for r in rows if "error" not in r}  # failed: again
    if not args.table_only:
        rows = [r for r in rows if "error" not in r]
    todo = [(lab, m, fam, rep) for rep in range(args.seeds) for m in mags for lab in labels for fam in fams
            if (fam, lab, m, rep) not in done]
    t0 = time.perf_counter()
    total = len(todo)

    def estimate(sample: list[dict], left: int) -> str:
        ok = [r for r in sample if "total_s" in r]
        if not ok:
            return "no timed run yet"
        wall = float(np.median([r["total_s"] for r in ok]))
        cpu = float(np.median([r.get("total_cpu_s") or r["total_s"] for r in ok]))
        sim = float(np.median([r.get("sim_cpu_s") or r["sim_s"] for r in ok]))
        return (f"{len(ok)} timed runs: median {wall:.1f} s wall, {cpu:.1f} s CPU per run (simulation {sim:.1f} s "
                f"CPU); {left} runs left on {args.workers} worker(s): ~{left * wall / args.workers / 60:.0f} min at "
                f"this load, ~{left * cpu / args.workers / 60:.0f} min on quiet cores")

    print(f"[families] code version {version}: {len(labels)} effects x {len(mags)} magnitudes x {len(fams)} families "
          f"x {args.seeds} seed pairs = {len(labels) * len(mags) * len(fams) * args.seeds} runs, {len(rows)} done, "
          f"{total} to run", file=sys.stderr, flush=True)
    if not args.table_only and todo:
        n_done = 0
        with ProcessPoolExecutor(max_workers=args.workers) as ex, open(out, "a") as fh:
            def run_batch(batch):
                nonlocal n_done
                futs = {ex.submit(run_family_case, lab, m, rep, fam, version, args.traction_curve): (lab, m, fam, rep)
                        for lab, m, fam, rep in batch}
                got = []
                for fut in as_completed(futs):
                    lab, m, fam, rep = futs[fut]
                    try:
                        r = fut.result()
                    except Exception as exc:  # noqa: BLE001 - reported, the others go on
                        r = {"case": lab, "magnitude": m, "rep": rep, "family": fam, "error": repr(exc),
                             "kind": "effect", "hash": version}
                    rows.append(r)
                    got.append(r)
                    fh.write(json.dumps(r, default=float) + "\n")
                    fh.flush()
                    n_done += 1
                    el = time.perf_counter() - t0
                    print(f"[families {n_done}/{total} {el / 60:5.1f} min, ~{el / n_done * (total - n_done) / 60:.0f} "
                          f"min left] {fam} {lab} x{m:g} #{rep}: " + ("ERROR " + r["error"] if "error" in r else
                          f"{'RIGHT' if r['right'] else 'wrong'}  {_reported(r)}  {_errors(r)}  (sim "
                          f"{r.get('sim_cpu_s', r['sim_s']):.1f} s, diagnose "
                          f"{r.get('diagnose_cpu_s') or 0:.1f} s CPU)"),
                          file=sys.stderr, flush=True)
                return got

            sample = [r for r in rows if "total_s" in r]
            if len(sample) < 2 * args.workers:  # a timed sample first: three runs per worker spread evenly over
                pick = sorted({int(i) for i in np.linspace(0, len(todo) - 1, 3 * args.workers)})  # the plan
                first = run_batch([todo[i] for i in pick])  # (effects, families); the first of each worker
                sample += first[args.workers:] or first  # (numba compilation, caches) left out
                todo = [t for i, t in enumerate(todo) if i not in set(pick)]
            print(f"[families] estimate: {estimate(sample, len(todo))}", file=sys.stderr, flush=True)
            if todo:
                run_batch(todo)
    rows = [r for r in rows if r["family"] in fams and r["case"] in labels and r["magnitude"] in mags
            and r["rep"] < args.seeds]
    lines = family_table(rows, fams, labels)
    print("\n".join(lines))
    if args.doc:
        ok = [r for r in rows if "error" not in r]
        reps = sorted({r["rep"] for r in rows})
        cpu = [r["total_cpu_s"] for r in ok if r.get("total_cpu_s")]
        head = [f"{len(rows)} runs ({len(rows) - len(ok)} failed) of code version `{version}` "
                f"(`code_hash()`: otbot_hw/diagnose, the independent simulator, the cases and scoring): "
                f"{len(labels)} effects x magnitudes {', '.join(f'{m:g}' for m in mags)} x families "
                f"{', '.join(fams)} x seed pairs {', '.join(str(x) for x in reps)}"
                + (f"; {sum(other.values())} rows of other code versions in the JSON lines ignored" if other else "")
                + f". Right overall: {sum(r['right'] for r in ok)}/{len(ok)}. Slowest diagnosis "
                f"{max((r['diagnose_s'] for r in ok), default=float('nan')):.1f} s (wall, machine shared)"
                + (f"; median CPU per run {np.median(cpu):.1f} s (simulation "
                   f"{np.median([r['sim_cpu_s'] for r in ok if r.get('sim_cpu_s') is not None]):.1f} s)" if cpu else "")
                + ".", ""]
        tail = ["", "\"Not identifiable from this recording\" verdicts for the true effect:", ""] + ni_table(rows)
        miss = miss_lines(rows)
        tail += ["", "Wrong runs, what was reported instead (errors of the true effect's parameters):", ""] + \
            (miss or ["* none"])
        doc = ROOT / "docs" / "diagnose.md"
        text = doc.read_text()
        begin, end = "<!-- FAMILIES:BEGIN (written by benchmarks/diagnose_independent.py --families) -->", \
            "<!-- FAMILIES:END -->"
        block = begin + "\n\n" + "\n".join(head + lines + tail) + "\n\n" + end
        if begin in text:
            text = text[:text.index(begin)] + block + text[text.index(end) + len(end):]
        else:
            text += "\n" + block + "\n"
        doc.write_text(text)
    return 0


#: (case, family) pairs of ``--sim-check``: every kind of term of the independent simulator (sharp signs, slip,
#: traction curve, lag, latency, casters, saturation, slope) under every family
SIM_CHECK = (("coulomb_wheels", "chirp"), ("wheel_slip", "prbs"), ("traction_limit", "multisine"),
             ("current_lag", "constant"), ("caster_configured", "piecewise_long"), ("imu_latency", "closed_loop"),
             ("stribeck_wheels", "prbs"), ("torque_saturation", "piecewise_short"), ("floor_slope", "chirp"),
             ("coulomb_pivot", "closed_loop"), ("rolling_resistance", "piecewise_slow"), ("imu_bias", "multisine"))


def _simulate(case: Case, family: str, rep: int, reference: bool) -> tuple[list[dict], float]:
    """Sensor signals of the fitting and held-out recordings of ``case`` (``make_recordings`` without the
    files), by the reference or the default integration, and the CPU time it took."""
    import diagnose_calibration as dc

    world, p = world_of(case, ir.load_params())
    fit_seed, held_seed = seeds(rep)
    c0 = time.process_time()
    robot = ir.Otbot(p, world, reference=reference)
    if family == "closed_loop":
        U, fit = ir.closed_loop(robot, DURATION, DT, fit_seed)
    else:
        U = dc.excitation(family, DURATION, DT, fit_seed) if family != "piecewise" else \
            ir.piecewise_torques(DURATION, DT, fit_seed)
        fit = robot.sensors(robot.run(U, DT), np.random.default_rng(fit_seed + 1000))
    robot = ir.Otbot(p, world, reference=reference)
    held = robot.sensors(robot.run(ir.smooth_torques(DURATION, DT, held_seed), DT),
                         np.random.default_rng(held_seed + 1000))
    return [fit, held], time.process_time() - c0


def sim_check(n: int) -> int:
    """The default integration against the reference (RK45 rtol 1e-8) on the first ``n`` of ``SIM_CHECK``
    (10 s fitting + 10 s held-out recording each, seed pair 0): CPU time of each and the largest difference of
    the recorded signals, same noise draws, in units of the sensor noise (IMU: SIGMA_IMU; encoder rates:
    SIGMA_ENC_RATE; encoder angles -- noise-free here -- in counts of a 4096*4*10-count encoder)."""
    count = 2 * np.pi / (4096 * 4 * 10)
    print("| case | family | reference CPU (s) | default CPU (s) | speed-up | max IMU diff (sigma) | "
          "max encoder rate diff (sigma) | max encoder angle diff (counts) |")
    print("|---|---|---|---|---|---|---|---|")
    tr, tf, worst = 0.0, 0.0, [0.0, 0.0, 0.0]
    for label, family in SIM_CHECK[:n]:
        case = BY_LABEL[label]
        ref, t_ref = _simulate(case, family, 0, True)
        fast, t_fast = _simulate(case, family, 0, False)
        d = [max(max(np.abs(a[k] - b[k]).max() for k in ("acc", "gyro")) for a, b in zip(ref, fast)) / ir.SIGMA_IMU,
             max(np.abs(a["vel"] - b["vel"]).max() for a, b in zip(ref, fast)) / ir.SIGMA_ENC_RATE,
             max(np.abs(a["pos"] - b["pos"]).max() for a, b in zip(ref, fast)) / count]
        worst = [max(w, x) for w, x in zip(worst, d)]
        tr, tf = tr + t_ref, tf + t_fast
        print(f"| {label} | {family} | {t_ref:.2f} | {t_fast:.2f} | {t_ref / t_fast:.1f} | {d[0]:.1e} | {d[1]:.1e} | "
              f"{d[2]:.1e} |", flush=True)
    print(f"| **all** | | {tr:.1f} | {tf:.1f} | {tr / tf:.1f} | {worst[0]:.1e} | {worst[1]:.1e} | {worst[2]:.1e} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
