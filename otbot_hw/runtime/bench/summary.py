"""The bench procedure's result as ``otbot bench --json`` gives it (``summary``): steps, parameters with
std, the unloaded platform's values and where they came from (``unloaded_platform``), the identified
combinations, notices, timing, and for a simulated robot the truth with each error in std. The Markdown
report is ``report``.
"""
from __future__ import annotations

from typing import Any

from otbot_hw.identification.uncertainty import SESSION_PARAMS
from otbot_hw.json_output import json_safe
from otbot_hw.runtime.bench.session import SessionFolder
from otbot_hw.runtime.bench.steps import BenchSettings


def unloaded_platform(final, settings: BenchSettings, session: SessionFolder, label: str
                      ) -> tuple[dict, list[str]]:
    """The unloaded platform's m_p0, x_F0, y_F0 as the session used them ({value, std, file, source}) and
    the notices: the file against this robot, what the recordings cannot separate."""
    file_p = settings.params_start
    meas = session.data.get("measurements", {}).get("m_p0")
    std = final.std
    out = {}
    for n, paper in (("m_p0", "m_p"), ("x_F0", "x_F"), ("y_F0", "y_F")):
        if n == "m_p0" and meas is not None:
            src = meas["source"]
        elif n in final.estimated:
            src = "estimated by the joint fit of the floor runs"
        else:
            src = "the parameter file's value, taken as exact"
        out[n] = {"value": float(final.values[n]), "std": float(std.get(n, 0.0)),
                  "file": float(getattr(file_p, paper)), "source": src}
    notices = []
    off = [m for n, u in (("m_p0", "kg"), ("x_F0", "m"), ("y_F0", "m"))
           if out[n]["source"] != "the parameter file's value, taken as exact"
           and not out[n]["source"].startswith("not weighed")
           and (m := _platform_mismatch(n, u, out[n]["file"], out[n]))]
    if off:
        notices.append(f"the unloaded platform in {label} does not match this robot: {'; '.join(off)}; the "
                       "bench used the measured and estimated values (params.yaml; update the file, or weigh the "
                       "platform and let the bench estimate its centre)")
    if meas is not None and meas["source"].startswith("not weighed"):
        tot = final.combination({"m_c": 1.0, "m_p0": 1.0})
        notices.append(f"the unloaded platform was not weighed: the recordings cannot separate the chassis' mass "
                       f"m_c from the platform's m_p0 (a floor run sees only m_c + m_p0 = {tot['value']:.5g} +- "
                       f"{tot['std']:.2g} kg)" + (", nor the loaded platform's m_p from m_p0 (the load's mass "
                                                  "m_p - m_p0 is identified)" if "platform" in final.steps else "")
                       + f"; m_c, x_B, I_c" + (", m_p, I_p, x_F, y_F" if "platform" in final.steps else "")
                       + f" are reported for m_p0 = {meas['value']:.4g} +- {meas['std']:.2g} kg and their std "
                       "include it; the robot's dynamics depend only on the identified combinations "
                       "('combinations'); weigh the platform for the separate values")
    return out, notices


def summary(proc, final, diagnosis, wall: float, cpu: float) -> dict:
    """The procedure's JSON-ready result: per step its status, fit, estimates, recordings and checks; the
    session's parameters with std, correlation, the unloaded platform and the identified combinations,
    notices, timing; for a simulated robot the truth and the error in std. ``proc``: the
    ``procedure.BenchProcedure`` that ran; ``final``: its last ``SessionResult``."""
    params = final.parameters()
    steps = {}
    for s in proc.s.steps:
        rec = proc.session.step(s)
        acc = next((a for a in reversed(rec["attempts"]) if a["status"] == "passed"), None)
        st = final.steps.get(s)
        d = st.to_dict() if st is not None else {}
        steps[s] = {"status": rec["status"], "converged": d.get("converged"), "verdict": d.get("verdict"),
                    "fit": d.get("fit"), "estimate": d.get("estimate"), "reasons": d.get("reasons", []),
                    "recordings": [a["recording"] for a in rec["attempts"] if a.get("recording")],
                    "accepted_recording": acc["recording"] if acc else None,
                    "check_recordings": [r for a in rec["attempts"] for r in a.get("check_recordings", [])],
                    "checks": acc["checks"] if acc else [], "attempts": len(rec["attempts"])}
    out: dict[str, Any] = {
        "session": str(proc.session.path), "passed": bool(final.passed), "excitation": proc.s.excitation,
        "steps": steps, "parameters": params, "method": final.method,
        "units": final.to_dict()["units"], "correlation": final.to_dict()["correlation"],
        "diagnosis": diagnosis, "designs": proc.designs or None, "idle_watchdog_resets": len(proc.idle_resets),
        "timing": {"wall_time": wall, "cpu_time": cpu, "runs_wall_time": proc.timing.runs,
                   "robot_time": proc.timing.robot_time, "identification_wall_time": proc.timing.identification,
                   "diagnosis_wall_time": proc.timing.diagnosis},
    }
    out["unloaded_platform"], notices = unloaded_platform(final, proc.s, proc.session,
                                                         proc.metadata.get("params_file", "the parameter file"))
    out["combinations"] = {"m_c+m_p0": final.combination({"m_c": 1.0, "m_p0": 1.0})}
    if "platform" in final.steps:
        out["combinations"]["m_p-m_p0"] = final.combination({"m_p": 1.0, "m_p0": -1.0})
    out["notices"] = proc.notices + notices + list(final.notices)  # (e.g. a nuisance held at the file's value)
    if proc.sim is not None:
        truth = proc.sim.truth()
        out["truth"] = {n: truth[n] for n in SESSION_PARAMS}
        out["error_sigma"] = {n: ((params[n]["value"] - truth[n]) / params[n]["std"]
                                  if params[n]["std"] > 0 else None) for n in SESSION_PARAMS
                              if n in final.estimated}
        out["load"] = dict(zip(("mass", "x", "y", "inertia"), proc.sim.load)) if proc.sim.load else None
        combo_truth = {"m_c+m_p0": truth["m_c"] + truth["m_p0"], "m_p-m_p0": truth["m_p"] - truth["m_p0"]}
        for n, d in out["combinations"].items():
            out["truth"][n] = combo_truth[n]
            if d["std"] > 0:
                out["error_sigma"][n] = (d["value"] - combo_truth[n]) / d["std"]
        for n, d in out["unloaded_platform"].items():
            out["truth"][n] = truth[n]
            if d["std"] > 0:
                out["error_sigma"][n] = (d["value"] - truth[n]) / d["std"]
    return json_safe(out)


def _platform_mismatch(name: str, unit: str, file_value: float, d: dict) -> str | None:
    """A sentence when the file's value of the unloaded platform's ``name`` is off by > 3 std of the bench's."""
    if d["std"] > 0 and abs(d["value"] - file_value) > 3.0 * d["std"]:
        how = "weighed" if d["source"].startswith("weighed") else "estimated"
        return f"{name} {file_value:.4g} {unit} in the file, {how} {d['value']:.4g} +- {d['std']:.2g} {unit}"
    return None
