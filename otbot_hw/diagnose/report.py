"""Before/after evidence of a diagnosis: per-channel statistics, residual plots, verdict, JSON.

Per channel (over all recordings of a set, fitting or held-out):

* ``fit_percent`` = 100 (1 - ||y - y_sim|| / ||y - mean(y)||) (NRMSE fit, simulation);
* ``rms``: residual RMS in the channel's unit;
* ``aic``/``bic``: N ln(RSS/N) + 2k / k ln N, k = free parameters of the model;
* ``ljung_box_q``/``ljung_box_p``: whiteness of the residual (Q over ``LB_LAGS`` lags,
  chi-square p-value; small p = not white);
* ``max_input_xcorr`` and ``xcorr_bound``: largest |normalised cross-correlation| between the
  residual and any commanded torque over lags 0..``LB_LAGS``, and the 95 % bound 1.96/sqrt(N).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import stats

from otbot_hw.diagnose.data import CHANNEL_UNITS, CHANNELS, DiagnosisData
from otbot_hw.diagnose.residuals import torque_residual
from otbot_hw.diagnose.simulated_run import simulate_outputs
from otbot_hw.model.effects import ExtendedModel

LB_LAGS = 20


def _acf(r: np.ndarray, lags: int) -> np.ndarray:
    r = r - r.mean()
    d = r @ r
    if d <= 0:
        return np.zeros(lags)
    return np.array([(r[h:] @ r[:-h]) / d for h in range(1, lags + 1)])


def _xcorr(r: np.ndarray, u: np.ndarray, lags: int) -> float:
    r = r - r.mean()
    best = 0.0
    for j in range(u.shape[1]):
        x = u[:, j] - u[:, j].mean()
        den = np.sqrt((r @ r) * (x @ x))
        if den <= 0:
            continue
        for h in range(0, lags + 1):
            best = max(best, abs(r[h:] @ x[:len(x) - h]) / den)
    return float(best)


def channel_stats(recordings: list[DiagnosisData], model: ExtendedModel, k: int) -> dict[str, dict]:
    """Statistics per channel (see module doc) of ``model`` on ``recordings``; {} for an empty set."""
    if not recordings:
        return {}
    sims = [simulate_outputs(d, model) for d in recordings]
    out = {}
    for ch in CHANNELS:
        ys, rs, us = [], [], []
        for d, s in zip(recordings, sims):
            y = d.measured(ch)
            if y is None:
                continue
            ys.append(y - y.mean())
            rs.append(y - s[ch])
            us.append(d.u)
        if not ys:
            continue
        y, r = np.concatenate(ys), np.concatenate(rs)
        n = len(r)
        rss = float(r @ r)
        acf = sum(len(x) * _acf(x, LB_LAGS) for x in rs) / n
        q = float(n * (n + 2) * np.sum(acf ** 2 / (n - np.arange(1, LB_LAGS + 1))))
        xc = max(_xcorr(x, u, LB_LAGS) for x, u in zip(rs, us))
        norm_y = float(np.linalg.norm(y))
        out[ch] = {
            "unit": CHANNEL_UNITS[ch],
            "fit_percent": float(100.0 * (1.0 - np.sqrt(rss) / norm_y)) if norm_y > 0 else float("nan"),
            "rms": float(np.sqrt(rss / n)),
            "aic": float(n * np.log(max(rss, 1e-300) / n) + 2 * k),
            "bic": float(n * np.log(max(rss, 1e-300) / n) + k * np.log(n)),
            "ljung_box_q": q,
            "ljung_box_p": float(max(stats.chi2.sf(q, LB_LAGS), 1e-300)),
            "max_input_xcorr": xc,
            "xcorr_bound": float(1.96 / np.sqrt(n)),
            "samples": n,
        }
    return out


def _discovered_text(disc: dict | None) -> str:
    """Sentences on the laws found beyond the catalog (``discover``, stepped by the diagnosis), empty without one."""
    if not disc or not disc.get("laws"):
        tried = (disc or {}).get("tried") or []
        if not tried:
            return ""
        close = ", ".join(f"{t['law']} (held-out {100 * t['heldout_gain']:+.0f} %, p {t['p_value']:.2g})"
                          for t in tried[:3])
        return f" No law of the discovery library passes its gates; the closest: {close}."
    parts = []
    for lw in disc["laws"]:
        vals = lw.get("refit") or {k: {"value": v, "std": lw["std"].get(k), "unit": ""} for k, v in lw["effect"].items()}
        ps = ", ".join(f"{k} = " + (f"{v['value']:g}" if k.startswith("cogn_") else _fmt(v["value"], v["std"]))
                       + f" {v['unit']}".rstrip() for k, v in vals.items())
        parts.append(f"{lw['law']} ({ps}): {lw['meaning']}")
    text = " Beyond the catalog, discovered: " + "; ".join(parts) + "."
    rs = disc.get("resimulation")
    if rs:
        ch = ", ".join(f"{c} {v['before_noise_ratio']:.2g} -> {v['after_noise_ratio']:.2g}"
                       for c, v in rs["channels"].items())
        text += (f" Re-simulating the {rs['set']} recordings with them stepped, residual RMS / noise: {ch}"
                 + (" (the model with them is adequate)." if disc.get("adequate_with_laws") else "."))
    return text


def _not_identifiable_text(items: list[dict]) -> str:
    """Sentences on what this recording cannot determine (``identifiability``); empty when nothing."""
    params = [i for i in items if i["kind"] == "parameter"]
    effects = [i for i in items if i["kind"] == "effect"]
    out = [f"Not identifiable from the fitting recordings: {r['name']}: {r['why']}; record {r['record']}."
           for r in items if r["kind"] == "range"]
    for p in params:
        out.append(f"Not identifiable from this recording: {p['name']} ({p['why']}); record {p['record']}.")
    sat = [e for e in effects if "never acts" in e["why"]]
    effects = [e for e in effects if e not in sat]
    if effects:
        out.append("Not identifiable from this recording at the catalog's smallest size: "
                   + "; ".join(f"{e['title']} (record {e['record']})" for e in effects) + ".")
    if sat:
        out.append("Torque saturation above the largest recorded commands is not identifiable from this recording ("
                   + "; ".join(f"{e['name']}: {e['why'].split('(')[1].split(')')[0]}" for e in sat)
                   + "); record commands near the drives' limits.")
    return " ".join(out)


def verdict(result: dict) -> str:
    """One plain-language paragraph from the diagnosis JSON."""
    parts = []
    for t in result.get("truncated_recordings", []):
        parts.append(f"{t['recording']} was cut short: diagnosed on its {t['complete_samples']} complete samples.")
    if not result.get("model_adequate", True):
        ad = result["adequacy"]
        why = []
        if ad["channels"]:
            worst = max(ad["channels"], key=lambda c: c.get("z", c["noise_ratio"]))
            chans = sorted({c["channel"] for c in ad["channels"]})
            where = f" over samples {worst['samples'][0]}-{worst['samples'][1]}" if "samples" in worst else ""
            why.append(f"channels {', '.join(chans)} stay above the noise level (worst: {worst['channel']} of "
                       f"{worst['recording']} ({worst['set']}), residual RMS {worst['noise_ratio']:.2f} x noise{where}, "
                       f"limit {worst['limit']:.2f} at a test size of {100 * ad.get('alpha', 0.01):g} % per diagnosis)")
        if ad["on_bound"]:
            why.append("estimates on a bound: " + ", ".join(f"{b['parameter']} = {b['value']:.4g}"
                                                           for b in ad["on_bound"]))
        if ad["moved"]:
            why.append("implausible refit: " + ", ".join(f"{m['parameter']} {m['file']:.4g} -> {m['refit']:.4g} "
                                                         f"({m['change']}, limit {m['limit']})" for m in ad["moved"]))
        withheld = ", ".join(w["name"] for w in result.get("withheld", []))
        parts.append("Model inadequate: no catalog effect brings the model to the data -- " + "; ".join(why) + "."
                     + (f" Not named ({withheld} would be fitted, but on a wrong model)." if withheld else "")
                     + f" Suspect parameters: {', '.join(result['suspect_parameters'])}. To do: {ad['advice']}."
                     + _discovered_text(result.get("discovered")))
        return " ".join(parts)
    for e in result["effects"]:
        ps = ", ".join(f"{n} = {_fmt(v['value'], v['std'])} {v['unit']}" for n, v in e["parameters"].items())
        sig = e.get("significance", {}).get("statement")
        parts.append(f"Left out: {e['title']}, {ps}" + (f" ({sig})." if sig else "."))
        for t in e.get("trades_off_against", []):
            parts.append(f"Its {t['effect_parameter']} trades off against {t['nominal_parameter']} (correlation "
                         f"{t['correlation']:.2f}): {cat_experiment(e['name'])}.")
    for grp in result["ambiguous"]:
        names = " / ".join(c["title"] for c in grp["candidates"])
        parts.append(f"The data cannot tell apart {names} (BIC within {grp['bic_margin']:.0f} effective samples); "
                     f"to separate them: {grp['experiment']}.")
    for e in result.get("detected_small", []):
        parts.append(f"Detected, small: {e['title']}: {e['significance']['statement']}.")
    if result["effects"] or result["ambiguous"]:
        # relative shift of parameters that are not near zero (a centre-of-mass offset of 1 mm moving
        # to 0 is no evidence)
        moved = [(abs(v["shift"]) / max(abs(v["before"]), abs(v["after"])), n, v)
                 for n, v in result.get("nominal_shift", {}).items()
                 if v["shift"] is not None and max(abs(v["before"]), abs(v["after"])) > 0.01]
        moved = [m for m in moved if m[0] > 0.05]
        if moved:
            _, n, v = max(moved, key=lambda m: m[0])
            parts.append(f"The nominal fit had absorbed it: {n} {v['before']:.4g} -> {v['after']:.4g} {v['unit']}.")
    if not (result["effects"] or result["ambiguous"] or result.get("detected_small")):
        parts.append("No missing physics found: no catalog effect improves the model by the evidence threshold.")
    parts.append(_not_identifiable_text(result.get("not_identifiable") or []))
    key = "heldout" if result["fit_before"].get("heldout") else "fitting"
    before, after = result["fit_before"].get(key, {}), result["fit_after"].get(key, {})

    def ok(v):
        return v is not None and np.isfinite(v)

    usable = [c for c in before if ok(before[c]["fit_percent"]) and ok(after[c]["fit_percent"])]
    if (result["effects"] or result["ambiguous"]) and usable:
        ch = max(usable, key=lambda c: after[c]["fit_percent"] - before[c]["fit_percent"])
        label = "Held-out" if key == "heldout" else "Fitting"
        parts.append(f"{label} fit of {ch}: {before[ch]['fit_percent']:.0f} % -> {after[ch]['fit_percent']:.0f} %.")
    parts += [w[0].upper() + w[1:] + "." for w in result.get("warnings", []) if "cut short" not in w]
    return " ".join(p for p in parts if p)


def cat_experiment(name: str) -> str:
    """The separating experiment of catalog effect ``name``."""
    from otbot_hw.diagnose.catalog import effect

    return effect(name).separating_experiment


def _fmt(v: float, s: float) -> str:
    from otbot_hw.diagnose.significance import format_with_std

    if s is None or not np.isfinite(s):
        return f"{v:.4g} (std not identifiable)"
    return format_with_std(v, s)


def plot_residuals(path: Path, data: DiagnosisData, before: ExtendedModel, after: ExtendedModel,
                   windows: list, title: str) -> str:
    """PNG: simulation residual per channel and torque residual per joint, before (grey) and after
    (blue), with the windows located against the nominal model shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sb, sa = simulate_outputs(data, before), simulate_outputs(data, after)
    tb, ta = torque_residual(data, before), torque_residual(data, after)
    chans = data.channels()
    rows = len(chans) + 3
    fig, axes = plt.subplots(rows, 1, figsize=(10, 1.6 * rows), sharex=True)
    mine = [w for w in windows if w.recording == data.name]
    for ax, ch in zip(axes, chans):
        y = data.measured(ch)
        ax.plot(data.t, y - sb[ch], color="0.6", lw=0.8, label="before")
        ax.plot(data.t, y - sa[ch], color="tab:blue", lw=0.8, label="after")
        ax.set_ylabel(f"{ch}\n[{CHANNEL_UNITS[ch]}]", fontsize=8)
        for w in mine:
            if w.kind == "simulation" and w.channel == ch:
                ax.axvspan(w.t_start, w.t_end, color="tab:red", alpha=0.12, lw=0)
    L = data.window
    for j, name in enumerate(("tau_r", "tau_l", "tau_p")):
        ax = axes[len(chans) + j]
        ax.plot(data.t[L:-L], tb[L:-L, j], color="0.6", lw=0.8)
        ax.plot(data.t[L:-L], ta[L:-L, j], color="tab:blue", lw=0.8)
        ax.set_ylabel(f"{name} res.\n[N m]", fontsize=8)
        for w in mine:
            if w.kind == "torque" and w.channel == name:
                ax.axvspan(w.t_start, w.t_end, color="tab:red", alpha=0.12, lw=0)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(title + " (shaded: windows flagged against the nominal model)", fontsize=9)
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return str(path)
