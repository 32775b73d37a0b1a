"""The diagnosis of recordings against an identified model, end to end.

1. nominal fit ("before"): re-identify the free nominal parameters on the fitting
   recordings (``refit``), starting from the given parameters;
2. locate: flag the windows where the nominal model and the recordings part ways;
3. select: screen the catalog, nested fits, accept / report ambiguous (``select``);
4. evidence: before/after statistics per channel on fitting and held-out recordings,
   the nominal-parameter shift, a verdict, optional PNG plots.

Returns one JSON-ready dict (see ``docs/diagnose.md`` for the fields).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from otbot_hw.diagnose import catalog as cat
from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.locate import locate, summarize
from otbot_hw.diagnose.refit import refit
from otbot_hw.diagnose.report import channel_stats, plot_residuals, verdict
from otbot_hw.diagnose.select import AMBIGUOUS_DBIC, choose, free_nominal
from otbot_hw.model.effects import ExtendedModel, parameter_unit
from otbot_hw.params import OtbotParams


def _json_safe(obj):
    """Non-finite floats -> None, numpy scalars -> Python numbers (the JSON is strict: allow_nan=False)."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def _finite(v):
    return None if v is None or not np.isfinite(v) else float(v)


def _params_json(fit, names):
    return {n: {"value": float(fit.values[n]), "std": _finite(fit.std.get(n)), "unit": parameter_unit(n)}
            for n in names}


def save_model(path: Path, fit, effects: list[dict], ambiguous: list[dict], recordings: list[str]) -> None:
    """Write the diagnosed model (the final fit: refit nominal parameters and effects, with std) as a
    parameter YAML with an ``effects`` section: what ``otbot simulate`` and ``otbot track`` load. An
    ambiguous group's best candidate is in the final fit (it predicts as well as its look-alikes);
    the header says so."""
    import dataclasses

    from otbot_hw.params import PARAM_INDEX

    std = {n: float(s) for n, s in fit.std.items() if n in PARAM_INDEX and s is not None and np.isfinite(s)}
    model = fit.model
    model = type(model)(dataclasses.replace(model.params, std=std), model.eff)
    lines = ["Diagnosed model (otbot diagnose --out): nominal parameters refit together with the accepted",
             "effects; std = one standard deviation. Recordings: " + ", ".join(Path(r).name for r in recordings),
             "Accepted effects: " + (", ".join(e["name"] for e in effects) or "none")]
    for g in ambiguous:
        names = [c["name"] for c in g["candidates"]]
        lines.append(f"Ambiguous, the data cannot tell apart: {' / '.join(names)}. The file holds the best of them "
                     f"({names[0]}), which predicts this data as well as the others; before relying on it elsewhere "
                     f"(another fixture, load or floor) separate them: {g['experiment']}")
    model.save(path, header="\n".join(lines), effect_std={n: s for n, s in fit.std.items() if n not in PARAM_INDEX})


def diagnose(recordings: list[DiagnosisData], params: OtbotParams, holdout: list[DiagnosisData] | None = None,
             report_dir: Path | None = None, progress=lambda msg: None, model_out: Path | None = None) -> dict:
    """Diagnose ``recordings`` against ``params``; ``holdout`` recordings judge prediction only.
    ``model_out``: also write the diagnosed model there (``save_model``)."""
    t_start = time.perf_counter()
    holdout = holdout or []
    if not recordings:
        raise ValueError("diagnose needs at least one fitting recording")
    unusable = {d.name: dict(d.unusable) for d in recordings + holdout if d.unusable}
    notes = {d.name: list(d.notes) for d in recordings + holdout if d.notes}
    nominal_free = free_nominal(recordings)
    progress(f"[diagnose] nominal fit of {', '.join(nominal_free)} on {len(recordings)} recording(s)")
    base = refit(recordings, ExtendedModel.paper(params), nominal_free)
    progress(f"[diagnose] nominal fit: {base.message} ({base.nfev} evaluations)")
    windows = locate(recordings + holdout, base.model)
    progress(f"[diagnose] located {len(windows)} flagged window(s)")
    sel = choose(recordings, holdout, base, nominal_free, progress)
    final = sel.final_fit
    effects = []
    for c in sel.accepted:
        e = cat.effect(c.effect)
        effects.append({"name": e.name, "title": e.title, "category": e.category,
                        "parameters": _params_json(final, e.parameters),
                        "evidence": {"delta_bic": c.dbic, "delta_aic": c.daic, "screening_delta_bic": c.screen_dbic,
                                     "simulation_screening_delta_bic": c.sim_screen_dbic,
                                     "max_fit_gain_percent": c.fit_gain,
                                     "heldout_delta_cost": _finite(c.dholdout),
                                     "lookalikes_tried": [t.effect for t in sel.tried if t.effect != c.effect]}})
    ambiguous = []
    for grp in sel.ambiguous:
        exps = []
        for c in grp:
            e = cat.effect(c.effect)
            if any(o.effect in e.lookalikes for o in grp) or not exps:
                exps.append(e.separating_experiment)
        ambiguous.append({
            "candidates": [{"name": c.effect, "title": cat.effect(c.effect).title,
                            "parameters": _params_json(c.fit, cat.effect(c.effect).parameters),
                            "delta_bic": c.dbic, "heldout_delta_cost": _finite(c.dholdout)} for c in grp],
            "bic_margin": AMBIGUOUS_DBIC,
            "experiment": "; ".join(dict.fromkeys(exps))})
    k_before, k_after = base.n_params, final.n_params
    fit_before = {"fitting": channel_stats(recordings, base.model, k_before),
                  "heldout": channel_stats(holdout, base.model, k_before)}
    fit_after = {"fitting": channel_stats(recordings, final.model, k_after),
                 "heldout": channel_stats(holdout, final.model, k_after)}
    shift = {}
    for n in nominal_free:
        b, a = base.values[n], final.values.get(n, base.values[n])
        shift[n] = {"before": b, "before_std": _finite(base.std.get(n)), "after": a,
                    "after_std": _finite(final.std.get(n)), "shift": a - b, "unit": parameter_unit(n)}
    result = {
        "effects": effects,
        "ambiguous": ambiguous,
        "located": [w.to_dict() for w in windows],
        "located_summary": summarize(windows),
        "fit_before": fit_before,
        "fit_after": fit_after,
        "nominal_shift": shift,
        "screening": [{"equation_residual_delta_bic": dict(sorted(s.single.items(), key=lambda kv: kv[1])),
                       "greedy_selection": s.selected,
                       "simulation_score_delta_bic": dict(sorted(ss.items(), key=lambda kv: kv[1]))}
                      for s, ss in zip(sel.screenings, sel.sim_screenings + [{}] * len(sel.screenings))],
        "candidates": [{"name": c.effect, "delta_bic": c.dbic, "delta_aic": c.daic, "max_fit_gain_percent": c.fit_gain,
                        "heldout_delta_cost": _finite(c.dholdout),
                        "parameters": _params_json(c.fit, cat.effect(c.effect).parameters)} for c in sel.tried],
        "unusable_channels": unusable,
        "notes": notes,
        "recordings": [d.name for d in recordings],
        "holdout": [d.name for d in holdout],
        "elapsed_s": 0.0,
    }
    result["verdict"] = verdict(result)
    if report_dir is not None:
        report_dir = Path(report_dir)
        plots = []
        for i, d in enumerate((recordings[:2] + holdout[:1])):
            tag = "heldout" if d in holdout else "fitting"
            plots.append(plot_residuals(report_dir / f"residuals_{tag}_{i}.png", d, base.model, final.model,
                                        windows, f"{Path(d.name).name} ({tag})"))
        result["plots"] = plots
    if model_out is not None:
        save_model(Path(model_out), final, effects, ambiguous, result["recordings"])
        result["model_file"] = str(model_out)
    result["elapsed_s"] = time.perf_counter() - t_start
    return _json_safe(result)
