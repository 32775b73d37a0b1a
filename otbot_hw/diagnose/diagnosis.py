"""The diagnosis of recordings against an identified model, end to end.

1. nominal fit ("before"): re-identify the free nominal parameters on the fitting
   recordings (``refit``), starting from the given parameters;
2. locate: flag the windows where the nominal model and the recordings part ways;
3. select: screen the catalog, nested fits, accept by evidence, judge by physics (``select``,
   ``significance``); report ambiguous groups and small detections;
4. judge the final model (``adequacy``): at the noise level, nothing on a bound, nominal
   parameters plausible -- else "model inadequate" and no finding is named;
5. evidence: before/after statistics per channel on fitting and held-out recordings,
   the nominal-parameter shift, standard deviations that hold with correlated residuals
   (``refit.robust_std``), a verdict, optional PNG plots.

Returns one JSON-ready dict (see ``docs/diagnose.md`` for the fields).
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from otbot_hw.diagnose import catalog as cat
from otbot_hw.diagnose.adequacy import assess, implausible_shifts, on_bound
from otbot_hw.diagnose.data import DiagnosisData, check_testable
from otbot_hw.diagnose.geometry import EffectGeometry
from otbot_hw.diagnose.identifiability import (effect_identifiability, not_identifiable_effects,
                                               saturation_not_identifiable, undetermined_effect_parameters)
from otbot_hw.diagnose.locate import locate, summarize
from otbot_hw.diagnose.refinements import caster_pair, refine_shape
from otbot_hw.diagnose.refit import default_nfev, refit, robust_std, single_blas_thread
from otbot_hw.diagnose.report import channel_stats, plot_residuals, verdict
from otbot_hw.diagnose.rules import AMBIGUOUS_DBIC, FINAL_NFEV, NOMINAL_NFEV
from otbot_hw.diagnose.select import choose, free_nominal
from otbot_hw.json_output import json_safe
from otbot_hw.model.effects import ExtendedModel, parameter_unit
from otbot_hw.params import OtbotParams


CORRELATION_NOTE = 0.98  # |correlation| of an effect and a nominal parameter worth reporting
STD_INFLATION_WARN = 2.0  # HAC / white-noise std above this: warn about model-form error



def _finite(v):
    return None if v is None or not np.isfinite(v) else float(v)


def _params_json(fit, names, std: dict | None = None):
    std = fit.std if std is None else std
    return {n: {"value": float(fit.values[n]), "std": _finite(std.get(n)), "unit": parameter_unit(n)}
            for n in names}


def save_model(path: Path, fit, effects: list[dict], ambiguous: list[dict], recordings: list[str],
               discovered: list[dict] | None = None) -> None:
    """Write the diagnosed model (the final fit: refit nominal parameters and effects, with std) as a
    parameter YAML with an ``effects`` section: what ``otbot simulate`` and ``otbot track`` load. An
    ambiguous group's best candidate is in the final fit (it predicts as well as its look-alikes);
    the header says so. ``discovered``: laws beyond the catalog (``discover``) the fit holds, named in
    the header."""
    import dataclasses

    from otbot_hw.params import PARAM_INDEX

    std = {n: float(s) for n, s in fit.std.items() if n in PARAM_INDEX and s is not None and np.isfinite(s)}
    model = fit.model
    model = type(model)(dataclasses.replace(model.params, std=std), model.eff)
    lines = ["Diagnosed model (otbot diagnose --out): nominal parameters refit together with the accepted",
             "effects; std = one standard deviation. Recordings: " + ", ".join(Path(r).name for r in recordings),
             "Accepted effects: " + (", ".join(e["name"] for e in effects) or "none")]
    if discovered:
        lines.append("Model inadequate for the catalog; laws discovered beyond it (diagnose/discover.py), refit by "
                     "simulation: " + ", ".join(lw["law"] for lw in discovered))
    for g in ambiguous:
        names = [c["name"] for c in g["candidates"]]
        lines.append(f"Ambiguous, the data cannot tell apart: {' / '.join(names)}. The file holds the best of them "
                     f"({names[0]}), which predicts this data as well as the others; before relying on it elsewhere "
                     f"(another fixture, load or floor) separate them: {g['experiment']}")
    model.save(path, header="\n".join(lines), effect_std={n: s for n, s in fit.std.items() if n not in PARAM_INDEX})


def _correlated_nominal(fit, effect_params, nominal: list[str], limit: float = CORRELATION_NOTE) -> list[dict]:
    """Nominal parameters an effect parameter trades off against in the fit (|correlation| >= limit)."""
    if fit.correlation is None or not np.all(np.isfinite(fit.correlation)):
        return []
    idx = {n: i for i, n in enumerate(fit.names)}
    out = []
    for p in effect_params:
        for n in nominal:
            if p in idx and n in idx:
                c = float(fit.correlation[idx[p], idx[n]])
                if abs(c) >= limit:
                    out.append({"effect_parameter": p, "nominal_parameter": n, "correlation": c})
    return out


def _candidate_json(c, effects: dict, std: dict | None = None, fit=None) -> dict:
    """A candidate's JSON entry; values from ``fit`` (default its own nested fit), ``std`` likewise."""
    e = effects.get(c.effect) or cat.effect(c.effect)
    fit = fit or c.fit
    out = {"name": e.name, "title": e.title, "category": e.category,
           "parameters": _params_json(fit, e.parameters, std),
           "significance": c.significance,
           "evidence": {"delta_bic": c.dbic, "delta_aic": c.daic, "residual_correlation_factor": c.kappa,
                        "effective_delta_bic": c.evidence, "screening_delta_bic": c.screen_dbic,
                        "simulation_screening_delta_bic": c.sim_screen_dbic,
                        "heldout_delta_cost": _finite(c.dholdout)}}
    return out


def _in_place_of(recordings, final, base, effects, lead, other):
    """(std, fit) of the final fit with the ambiguous group's ``other`` member in place of its ``lead``: the
    lead's parameters back to the nominal fit's values (none), the other's free, started from its nested fit."""
    out_p, in_p = effects[lead.effect].parameters, effects[other.effect].parameters
    names = [n for n in final.names if n not in out_p] + [n for n in in_p if n not in final.names]
    start = final.model.with_values({n: base.model.get(n) for n in out_p if n not in in_p})
    start = start.with_values({n: other.fit.values[n] for n in in_p if n in other.fit.values})
    fit = refit(recordings, start, names, max_nfev=FINAL_NFEV)
    return fit.std, fit


def _small_needed(recordings, holdout, params, sel, final, progress):
    """Effects with evidence listed as detected but small (``significance``: they do not matter by what they
    do on these runs) are left out of the model -- unless the model without them is inadequate and with them
    adequate: then the data need them, and they are accepted (their significance statement still says how
    small they are). Returns the final fit (with them, or ``final``)."""
    if not sel.small or assess(recordings, holdout, final, params).adequate:
        return final
    names = list(final.names)
    start = {}
    for c in sel.small:
        for p in c.parameters:
            if p not in names:
                names.append(p)
                start[p] = c.fit.values[p]
    fit = refit(recordings, final.model.with_values(start), names, max_nfev=FINAL_NFEV)
    if not assess(recordings, holdout, fit, params).adequate:
        return final
    progress(f"[diagnose] the model is adequate only with {', '.join(c.effect for c in sel.small)} "
             "(detected, small): accepted")
    sel.accepted += sel.small
    sel.small = []
    return fit


def diagnose(recordings: list[DiagnosisData], params: OtbotParams, holdout: list[DiagnosisData] | None = None,
             report_dir: Path | None = None, progress=lambda msg: None, model_out: Path | None = None,
             geometry: EffectGeometry | None = None) -> dict:
    """Diagnose ``recordings`` against ``params``; ``holdout`` recordings judge prediction only.
    ``geometry``: caster and IMU positions from the robot configuration (default: none known).
    ``model_out``: also write the diagnosed model there (``save_model``; not when the model is inadequate).

    Runs with one BLAS thread (``single_blas_thread``): the parallel work is the simulations on
    the prediction threads; the fitter's linear algebra is on tall, thin matrices."""
    with single_blas_thread():
        return _diagnose(recordings, params, holdout, report_dir, progress, model_out, geometry)


def _diagnose(recordings, params, holdout, report_dir, progress, model_out, geometry) -> dict:
    t_start, cpu_start = time.perf_counter(), time.process_time()
    holdout = holdout or []
    geometry = geometry or EffectGeometry()
    if not recordings:
        raise ValueError("diagnose needs at least one fitting recording")
    check_testable(recordings)
    unusable = {d.name: dict(d.unusable) for d in recordings + holdout if d.unusable}
    notes = {d.name: list(d.notes) for d in recordings + holdout if d.notes}
    truncated = [{"recording": d.name, "complete_samples": len(d), "duration_s": float(d.t[-1])}
                 for d in recordings + holdout if d.truncated]
    nominal_free = free_nominal(recordings)
    start = ExtendedModel.paper(params).with_values(geometry.effect_values())
    progress(f"[diagnose] nominal fit of {', '.join(nominal_free)} on {len(recordings)} recording(s)")
    base = refit(recordings, start, nominal_free, max_nfev=NOMINAL_NFEV)
    progress(f"[diagnose] nominal fit: {base.message} ({base.nfev} evaluations)")
    windows = locate(recordings + holdout, base.model)
    progress(f"[diagnose] located {len(windows)} flagged window(s)")
    wandered = implausible_shifts(base.values, params, base.std) + on_bound(base.values)
    if wandered:
        progress(f"[diagnose] the nominal fit moved {', '.join(dict.fromkeys(w['parameter'] for w in wandered))} "
                 "implausibly: the first nested fits start from the file's values")
    # effects are screened about the file's values too: the nominal fit absorbs part of an effect into the
    # nominal parameters (air drag under constant torques into b_w and I_c; a traction limit into I_p on its
    # bound) and the screening about that fit, a local score test, no longer sees it
    sel = choose(recordings, holdout, base, nominal_free, progress, geometry.casters_configured, start,
                 bool(wandered))
    final = sel.final_fit
    if final is base and not base.success and base.nfev >= NOMINAL_NFEV:
        # nothing found and the nominal fit stopped on its budget: it is the model judged, so it is converged
        # (to the fitter's default budget, as before the budget) before the verdict and the discovery step
        base = final = refit(recordings, base.model, nominal_free, max_nfev=default_nfev(len(nominal_free)) - base.nfev,
                             scale=base.scale)
        progress(f"[diagnose] nominal fit continued: {base.message} ({base.nfev} evaluations)")
    shape_tried = []
    if not geometry.casters_configured:
        final = caster_pair(recordings, sel, final, progress)
    if sel.accepted or sel.ambiguous:  # the nested fits stop early (decisions); converge the reported one
        final = refit(recordings, final.model, final.names, max_nfev=FINAL_NFEV, scale=final.scale)
        progress(f"[diagnose] final fit: {final.message} ({final.nfev} evaluations)")
        # and from the file's nominal values with the effects as fitted: a friction effect trades off against
        # b_w along a flat valley, and the fit from the nominal fit's b_w stopped in it (Stribeck on a chirp:
        # s_w -30 %; from the file's values -> +5 %); the better of the two is reported
        alt = refit(recordings, final.model.with_values({n: start.get(n) for n in nominal_free}), final.names,
                    max_nfev=FINAL_NFEV)
        if sum(alt.rss.values()) < sum(final.rss.values()):
            progress(f"[diagnose] final fit from the file's nominal values fits better: {alt.message} "
                     f"({alt.nfev} evaluations)")
            final = alt
        final, shape_tried = refine_shape(recordings, sel, final, start, progress)
    final = _small_needed(recordings, holdout, params, sel, final, progress)
    # standard deviations that hold with correlated residuals (model-form error), never below the usual ones
    std = dict(final.std)
    inflation = 1.0
    if sel.accepted or sel.ambiguous:
        hac = robust_std(recordings, final)
        for n, s_hac in hac.items():
            s0 = std.get(n, float("nan"))
            if np.isfinite(s_hac) and np.isfinite(s0) and s0 > 0:
                inflation = max(inflation, s_hac / s0)
                std[n] = max(s0, s_hac)
            elif not np.isfinite(s_hac):
                std[n] = float("nan")
    adequacy = assess(recordings, holdout, final, params)
    progress(f"[diagnose] model adequate: {adequacy.adequate}")
    effects = []
    for c in sel.accepted:
        item = _candidate_json(c, sel.effects, std, final)
        item["evidence"]["lookalikes_tried"] = [t.effect for t in sel.tried if t.effect != c.effect]
        item["trades_off_against"] = _correlated_nominal(final, sel.effects[c.effect].parameters, nominal_free)
        effects.append(item)
    ambiguous = []
    for grp in sel.ambiguous:
        exps = []
        for c in grp:
            e = sel.effects[c.effect]
            if any(o.effect in e.lookalikes for o in grp) or not exps:
                exps.append(e.separating_experiment)
        # the group's best member is in the final model: its values and std from the final fit; each other
        # member from the same final fit with it in the best one's place (its nested fit held the other
        # accepted effects: beside Stribeck friction held, a Coulomb look-alike read c_w +30 % once rolling
        # resistance led the tie)
        members = [_candidate_json(grp[0], sel.effects, std, final)]
        for c in grp[1:]:  # (an inadequate model's groups are withheld by their best member's name alone: no refit)
            members.append(_candidate_json(c, sel.effects, *(_in_place_of(recordings, final, base, sel.effects, grp[0], c)
                                                              if adequacy.adequate else (None, None))))
        ambiguous.append({"candidates": members,
                          "bic_margin": AMBIGUOUS_DBIC, "residual_correlation_factor": grp[0].kappa,
                          "experiment": "; ".join(dict.fromkeys(exps))})
    small = [_candidate_json(c, sel.effects) for c in sel.small]
    # what this recording cannot reveal: effects at the catalog's smallest size, parameters on a bound
    identifiability = effect_identifiability(sel.energy)
    found = {c.effect for c in sel.accepted + sel.small} | {c.effect for g in sel.ambiguous for c in g}
    not_identifiable = adequacy.not_identifiable + not_identifiable_effects(
        identifiability, found, {n: e.title for n, e in sel.effects.items()})
    not_identifiable += undetermined_effect_parameters(
        effects + [g["candidates"][0] for g in ambiguous],
        {p: v for e in sel.effects.values() for p, v in e.magnitudes[0].items()})
    listed = {x["name"] for x in not_identifiable}
    not_identifiable += [x for x in saturation_not_identifiable(recordings, sel.effects.values(), found)
                         if x["name"] not in listed]
    withheld = []
    if not adequacy.adequate:
        withheld = [{"name": e["name"], "parameters": e["parameters"]} for e in effects] + \
                   [{"name": g["candidates"][0]["name"], "parameters": g["candidates"][0]["parameters"],
                     "ambiguous_with": [c["name"] for c in g["candidates"][1:]]} for g in ambiguous]
        effects, ambiguous = [], []
    discovered, law_fit = None, None
    if not adequacy.adequate:  # beyond the catalog: what the nominal model misses, by grouped sparse regression
        from otbot_hw.diagnose.discover import discover_laws

        discovered, law_fit = discover_laws(recordings, holdout, base, nominal_free, params, progress)
    k_before, k_after = base.n_params, final.n_params
    fit_before = {"fitting": channel_stats(recordings, base.model, k_before),
                  "heldout": channel_stats(holdout, base.model, k_before)}
    fit_after = {"fitting": channel_stats(recordings, final.model, k_after),
                 "heldout": channel_stats(holdout, final.model, k_after)}
    shift = {}
    for n in nominal_free:
        b, a = base.values[n], final.values.get(n, base.values[n])
        shift[n] = {"file": float(getattr(params, n)), "before": b, "before_std": _finite(base.std.get(n)),
                    "after": a, "after_std": _finite(std.get(n, final.std.get(n))), "shift": a - b,
                    "unit": parameter_unit(n)}
    warnings = []
    if inflation > STD_INFLATION_WARN:
        warnings.append(f"the residuals of the final fit are correlated (model-form error the catalog does not "
                        f"capture): standard deviations are the HAC estimates, up to {inflation:.1f} x the "
                        "white-noise ones")
    for t in truncated:
        warnings.append(f"{t['recording']} was cut short: diagnosed on its {t['complete_samples']} complete samples "
                        f"({t['duration_s']:.3g} s)")
    result = {
        "model_adequate": adequacy.adequate,
        "effects": effects,
        "ambiguous": ambiguous,
        "detected_small": small,
        "withheld": withheld,
        "discovered": discovered,
        "not_identifiable": not_identifiable,
        "identifiability": identifiability,
        "adequacy": adequacy.to_dict(),
        "suspect_parameters": adequacy.suspect_parameters,
        "geometry": geometry.to_dict(),
        "located": [w.to_dict() for w in windows],
        "located_summary": summarize(windows),
        "fit_before": fit_before,
        "fit_after": fit_after,
        "nominal_shift": shift,
        "std_inflation": inflation,
        "shape_refinements": shape_tried,
        "screening": [{"equation_residual_delta_bic": dict(sorted(s.single.items(), key=lambda kv: kv[1])),
                       "greedy_selection": s.selected,
                       "simulation_score_delta_bic": dict(sorted(ss.items(), key=lambda kv: kv[1]))}
                      for s, ss in zip(sel.screenings, sel.sim_screenings + [{}] * len(sel.screenings))],
        "candidates": [{"name": c.effect, "delta_bic": c.dbic, "delta_aic": c.daic,
                        "residual_correlation_factor": c.kappa, "heldout_delta_cost": _finite(c.dholdout),
                        "parameters": _params_json(c.fit, c.parameters)}
                       for c in sel.tried],
        "truncated_recordings": truncated,
        "warnings": warnings,
        "unusable_channels": unusable,
        "notes": notes,
        "recordings": [d.name for d in recordings],
        "holdout": [d.name for d in holdout],
        "elapsed_s": 0.0,
        "cpu_s": 0.0,
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
    if model_out is not None and adequacy.adequate:
        save_model(Path(model_out), dataclasses.replace(final, std=std), effects, ambiguous, result["recordings"])
        result["model_file"] = str(model_out)
    elif model_out is not None and law_fit is not None and discovered.get("improves"):
        save_model(Path(model_out), law_fit, [], [], result["recordings"], discovered=discovered["laws"])
        result["model_file"] = str(model_out)
    result["elapsed_s"] = time.perf_counter() - t_start
    result["cpu_s"] = time.process_time() - cpu_start  # this process, all its threads (prediction threads included)
    return json_safe(result)
