"""The bench session's report: Markdown with PNG plots, like an identification report of MATLAB's.

``write_report(folder, summary, final)``: ``report.md`` (steps with their checks, gates and fit,
the parameters with std (and, when simulated, truth and error / sigma), the diagnosis, the
timings, the files) and PNGs: per recording of the final joint fit, measured vs predicted per
channel and the residuals (``identification.report.plot_experiments``), and the estimates with
their 1 and 3 sigma intervals next to the truth when it is known.
"""
from __future__ import annotations

from pathlib import Path

from otbot_hw.identification.report import plot_experiments
from otbot_hw.identification.session import SESSION_UNITS
from otbot_hw.identification.uncertainty import SESSION_PARAMS


def plot_estimates(path: Path, parameters: dict, truth: dict | None) -> str:
    """One small axis per parameter: the estimate with its 1 and 3 sigma bars, the truth as a cross."""
    from otbot_hw.plots import _plt

    plt = _plt()
    fig, axes = plt.subplots(3, 4, figsize=(12, 6.5))
    for ax, n in zip(axes.ravel(), SESSION_PARAMS):
        v, s = parameters[n]["value"], parameters[n]["std"] or 0.0
        ax.errorbar([0], [v], yerr=[3 * s], fmt="none", ecolor="C0", alpha=0.35, lw=6, label="3 sigma")
        ax.errorbar([0], [v], yerr=[s], fmt="o", color="C0", capsize=4, label="estimate, 1 sigma")
        if truth is not None and n in truth:
            ax.plot([0], [truth[n]], "x", color="C3", ms=9, mew=2, label="truth")
        ax.set_xticks([])
        ax.set_title(f"{n} ({SESSION_UNITS[n]})" + ("" if s > 0 else ", not estimated"), fontsize=9)
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Estimates with their std" + (" and the simulated robot's truth" if truth else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return str(path)


def _fmt(v, digits: int = 5) -> str:
    return "-" if v is None else f"{v:.{digits}g}"


def write_report(folder: Path, summary: dict, final) -> list[str]:
    """Write ``folder/report.md`` and its PNGs; returns the files written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    files: list[str] = []
    if final.joint is not None and final.method == "joint":
        exps = [e for st in final.steps.values() for e in st.result.experiments]
        files += plot_experiments(folder, exps, final.joint, "Bench session, joint fit of all recordings")
    else:
        for s, st in final.steps.items():
            files += plot_experiments(folder, st.result.experiments, st.result.fit, f"Step {s}")
    truth = summary.get("truth")
    files.append(plot_estimates(folder / "estimates.png", summary["parameters"], truth))
    L = [f"# Bench identification: {summary['session']}", "",
         f"Verdict: **{'passed' if summary['passed'] else 'not passed'}**; excitation {summary['excitation']}; "
         f"estimates from {'a joint fit of all recordings' if summary['method'] == 'joint' else 'the chained steps'} "
         "(std include the earlier steps' uncertainty).", ""]
    L += ["## Steps", "", "| step | status | attempts | accepted recording | fit % (joint fit) | gates |",
          "|---|---|---|---|---|---|"]
    for s, d in summary["steps"].items():
        fit = ", ".join(f"{k.split('/')[-1]} {v:.1f}" for k, v in (d.get("fit") or {}).items() if v is not None)
        gates = d.get("verdict") or "-"
        if d.get("reasons"):
            gates += ": " + "; ".join(d["reasons"])
        L.append(f"| {s} | {d['status']} | {d['attempts']} | {d.get('accepted_recording') or '-'} | {fit or '-'} | "
                 f"{gates} |")
    L += ["", "Checks of each accepted attempt (from the sensors, before and after the excitation):", ""]
    for s, d in summary["steps"].items():
        for c in d.get("checks") or []:
            L.append(f"- {s}, {c['name']}: {'ok' if c['passed'] else 'FAILED'}: {c['message']}")
    L += ["", "## Parameters", ""]
    head = "| parameter | value | std | unit |"
    line = "|---|---|---|---|"
    if truth:
        head += " truth | error / std |"
        line += "---|---|"
    L += [head, line]
    es = summary.get("error_sigma") or {}

    def truth_cells(n: str) -> str:  # a simulated robot's truth and error / std of ``n``
        return f" {_fmt(truth.get(n), 6)} | {_fmt(es.get(n), 3)} |" if truth else ""

    for n, p in summary["parameters"].items():
        L.append(f"| {n} | {_fmt(p['value'], 6)} | {_fmt(p['std'], 3)} | {summary['units'][n]} |" + truth_cells(n))
    up = summary.get("unloaded_platform") or {}
    if up:
        L += ["", "The unloaded platform (a floor run sees the chassis' and the platform's masses only together):", "",
              "| parameter | value | std | in the parameter file | source |" + (" truth | error / std |" if truth else ""),
              "|---|---|---|---|---|" + ("---|---|" if truth else "")]
        for n, d in up.items():
            L.append(f"| {n} | {_fmt(d['value'], 6)} | {_fmt(d['std'], 3)} | {_fmt(d['file'], 6)} | {d['source']} |"
                     + truth_cells(n))
    combos = summary.get("combinations") or {}
    if combos:
        L += ["", "Identified combinations (kg): " + "; ".join(
            f"{n} = {_fmt(d['value'], 6)} +- {_fmt(d['std'], 3)}" for n, d in combos.items())]
    for m in summary.get("notices") or []:
        L += ["", f"**Notice:** {m}"]
    L += ["", "![estimates](estimates.png)", ""]
    if summary.get("designs"):
        L += ["## Designed excitation", "", "| step | parameter | Cramer-Rao bound, designed / paper (design point) |",
              "|---|---|---|"]
        for s, d in summary["designs"].items():
            for n, r in (d.get("crb_ratio") or {}).items():
                L.append(f"| {s} | {n} | {r:.2f} |")
        L.append("")
    diag = summary.get("diagnosis")
    L += ["## Missing physics (otbot diagnose)", ""]
    if diag is None:
        L.append("Not run.")
    else:
        L.append(f"Verdict: {diag['verdict']}.")
        for label in ("unloaded", "loaded"):
            if label in diag:
                d = diag[label]
                L.append(f"- {label} robot ({', '.join(d['recordings'])}): {d['verdict']}")
    L += ["", "## Fits", ""]
    for f in files:
        if f.endswith("_fit.png"):
            L.append(f"![{Path(f).stem}]({Path(f).name})")
    t = summary["timing"]
    L += ["", "## Time", "",
          f"Wall time {t['wall_time']:.1f} s (runs {t['runs_wall_time']:.1f} s for {t['robot_time']:.1f} s of robot "
          f"time, identification {t['identification_wall_time']:.1f} s, diagnosis {t['diagnosis_wall_time']:.1f} s), "
          f"CPU time {t['cpu_time']:.1f} s.", ""]
    md = folder / "report.md"
    md.write_text("\n".join(L) + "\n")
    return [str(md), *files]

