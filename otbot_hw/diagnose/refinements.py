"""Refinements of a selected model, tried after the selection: forms the catalog's nested search does not
step through because they only make sense once an effect is found.

- ``caster_pair``: caster drag found with no casters configured -> two casters instead of one;
- ``refine_shape``: an effect with a shape parameter (``catalog.SHAPE_REFINEMENTS``, the traction knee) -> the
  shape freed, kept on BIC evidence, look-alikes accepted beside the catalog's shape refit away.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from otbot_hw.diagnose import catalog as cat
from otbot_hw.diagnose.refit import refit
from otbot_hw.diagnose.rules import ACCEPT_DBIC, FINAL_NFEV
from otbot_hw.diagnose.significance import significance


PAIR_SPREAD = 0.15  # m: the pair's start, (x, +-PAIR_SPREAD) about the single caster's fitted x
PAIR_EVIDENCE = 10.0  # BIC gain the pair needs over the single caster


def caster_pair(recordings, sel, final, progress):
    """Casters not configured and caster drag found: one fitted caster is the catalog's model, but a robot
    with two casters (say at (0.15, +-0.2) m) drags differently when it turns -- the single caster at
    their midpoint leaves a misfit above the noise. Refit with two casters, started at (x, +-PAIR_SPREAD)
    about the single caster's x (two casters at one point are one caster, so the pair nests it), and keep
    the pair when it gains ``PAIR_EVIDENCE`` of BIC (2 more parameters). The caster entry then reports
    f_cst (the summed drag) and both positions."""
    names = [c.effect for c in sel.accepted] + [g[0].effect for g in sel.ambiguous]
    if "caster_drag" not in names or "x_c1" not in final.names:
        return final
    x = final.values["x_c1"]
    start = final.model.with_values({"n_cst": 2.0, "x_c1": x, "y_c1": PAIR_SPREAD, "x_c2": x, "y_c2": -PAIR_SPREAD})
    free = list(final.names) + ["x_c2", "y_c2"]
    pair = refit(recordings, start, free, max_nfev=FINAL_NFEV)
    n = sum(pair.n_samples.values())
    gain = (sum(pair.rss.values()) - sum(final.rss.values())) + 2 * np.log(max(n, 2))
    progress(f"[diagnose] two casters instead of one: dBIC {gain:.1f}")
    if gain < -PAIR_EVIDENCE:
        e = sel.effects["caster_drag"]
        sel.effects["caster_drag"] = dataclasses.replace(e, parameters=tuple(e.parameters) + ("x_c2", "y_c2"))
        for c in list(sel.accepted) + [g[0] for g in sel.ambiguous]:
            if c.effect == "caster_drag":
                pars = sel.effects["caster_drag"].parameters
                c.significance = significance("caster_drag", {k: pair.values[k] for k in pars},
                                              {k: pair.std.get(k, float("nan")) for k in pars}, pair.model, recordings)
        return pair
    return final


def refine_shape(recordings, sel, final, start, progress):
    """Found effects with a shape parameter (``catalog.SHAPE_REFINEMENTS``: the traction curve's knee): refit with
    it free, started from its catalog form (0; from the catalog's other starts while none gains), and keep it when
    it gains its BIC evidence (1 more parameter); the effect entry then reports it with the others. An effect accepted beside it before (the selection fitted
    the catalog's shape: a look-alike took up part of the knee's misfit -- encoder scale and wheel radii beside
    a tanh traction curve) is then refit away and dropped when it no longer gains ``ACCEPT_DBIC``. Returns
    (final fit, what was tried: {effect, parameter, value, std, delta_bic, kept, dropped})."""
    names = [c.effect for c in sel.accepted] + [g[0].effect for g in sel.ambiguous]
    tried = []
    for eff, (param, evidence, starts) in cat.SHAPE_REFINEMENTS.items():
        if eff not in names or param in final.names:
            continue
        n = sum(final.n_samples.values())
        fit, gain = None, np.inf
        for x0 in starts:  # the catalog's form first; another start only when it gains nothing (a knee far
            f = refit(recordings, final.model.with_values({param: x0}), list(final.names) + [param],
                      max_nfev=FINAL_NFEV)  # from it: the fit from 0 stalled before a hard clip); the best kept
            g = (sum(f.rss.values()) - sum(final.rss.values())) + np.log(max(n, 2))
            if g < gain:
                fit, gain = f, g
            if gain < -evidence:
                break
        progress(f"[diagnose] {eff} with its {param} free: {param} = {fit.values[param]:.3g}, dBIC {gain:.1f}")
        std = fit.std.get(param, float("nan"))
        tried.append({"effect": eff, "parameter": param, "value": float(fit.values[param]),
                      "std": float(std) if np.isfinite(std) else None, "delta_bic": float(gain),
                      "kept": bool(gain < -evidence)})
        if gain < -evidence:
            e = sel.effects[eff]
            sel.effects[eff] = dataclasses.replace(e, parameters=tuple(e.parameters) + (param,))
            for c in list(sel.accepted) + [g[0] for g in sel.ambiguous]:
                if c.effect == eff:
                    pars = sel.effects[eff].parameters
                    c.significance = significance(eff, {k: fit.values[k] for k in pars},
                                                  {k: fit.std.get(k, float("nan")) for k in pars}, fit.model,
                                                  recordings)
            final = fit
            tried[-1]["dropped"] = []
            for c in reversed([c for c in sel.accepted if c.effect != eff]):
                out = [p for p in sel.effects[c.effect].parameters
                       if p in final.names and p not in sel.effects[eff].parameters]
                if not out:
                    continue
                without = refit(recordings, final.model.with_values({p: start.get(p) for p in out}),
                                [n for n in final.names if n not in out], max_nfev=FINAL_NFEV)
                loss = (sum(without.rss.values()) - sum(final.rss.values())) - len(out) * np.log(max(n, 2))
                progress(f"[diagnose] {c.effect} beside {eff} with its {param}: dBIC {loss:.1f} to keep it")
                if loss < ACCEPT_DBIC:
                    sel.accepted.remove(c)
                    tried[-1]["dropped"].append(c.effect)
                    final = without
    return final, tried
