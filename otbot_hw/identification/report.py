"""Reports of identification results: JSON, text tables and fitting plots (paper Figs 8-9).

Parameters are keyed by the paper's symbols (``I_p0`` for the pivot test's
unloaded-platform inertia); all values SI. When the truth is known (simulation):
the error, the error in units of the reported sigma and the Cramer-Rao bound.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any


from otbot_hw.identification.model import CHANNEL_UNITS
from otbot_hw.params import UNITS


def _num(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


def step_to_dict(res, crb: dict[str, float] | None = None) -> dict[str, Any]:
    """JSON-ready result of a ``StepResult``.

    Keys: step, converged, parameters ({symbol: {value, std}}, null unless converged),
    fit_percent ({experiment/channel: %}), correlation, start (of the reported fit), reasons,
    attempts (every start tried),
    and with a known truth: truth, error, error_sigma (and cramer_rao_std when given).
    """
    fit = res.fit
    sym = res.symbol
    params = ({sym(n): {"value": fit.estimate[n], "std": _num(fit.std[n])} for n in fit.names}
              if res.converged else None)
    out: dict[str, Any] = {
        "step": res.step,
        "experiment": res.spec.description,
        "converged": bool(res.converged),
        "parameters": params,
        "fit_percent": {k: _num(v) for k, v in fit.fit_percent.items()},
        "residual_ratio": {k: _num(v) for k, v in fit.residual_ratio.items()},
        "correlation": {"names": [sym(n) for n in fit.names],
                        "matrix": [[_num(v) for v in row] for row in fit.correlation]},
        "start": {sym(n): fit.guess[n] for n in fit.names},
        "units": {sym(n): UNITS[n] for n in fit.names},
        "reasons": list(res.reasons) + ([] if res.converged else list(fit.reasons)),
        "attempts": [_clean_attempt(a, sym) for a in res.attempts],
        "wall_time": res.wall_time,
    }
    if not res.converged:
        out["last_iterate"] = {sym(n): fit.estimate[n] for n in fit.names}
    if res.truth is not None:
        out["truth"] = {sym(n): v for n, v in res.truth.items()}
        err = {n: fit.estimate[n] - res.truth[n] for n in fit.names}
        out["error"] = {sym(n): e for n, e in err.items()}
        out["error_sigma"] = {sym(n): _num(err[n] / fit.std[n]) if fit.std[n] > 0 else None for n in fit.names}
    if crb is not None:
        out["cramer_rao_std"] = {sym(n): _num(v) for n, v in crb.items()}
    return out


def _clean_attempt(a: dict, sym) -> dict:
    out = {"start": a["start"]}
    if a.get("error"):
        out["error"] = a["error"]
        return out
    out["guess"] = {sym(n): v for n, v in a["guess"].items()}
    out["estimate"] = {sym(n): v for n, v in a["estimate"].items()}
    out.update(cost=a["cost"], converged=a["converged"], reasons=a["reasons"], nfev=a["nfev"])
    return out


def step_table(res, crb: dict[str, float] | None = None) -> str:
    """A plain-text report (parameters, correlation, fit percent) like getpvec/compare."""
    fit = res.fit
    sym = res.symbol
    lines = [f"step {res.step} ({res.spec.description}): "
             + ("converged" if res.converged else "NOT CONVERGED")]
    head = f"{'param':<6} {'estimate':>12} {'std':>10} {'start':>11}"
    if res.truth is not None:
        head += f" {'truth':>11} {'error':>11} {'err/std':>8}"
    if crb is not None:
        head += f" {'CRB std':>10}"
    lines.append(head + "  unit")
    for n in fit.names:
        row = f"{sym(n):<6} {fit.estimate[n]:>12.6g} {fit.std[n]:>10.3g} {fit.guess[n]:>11.5g}"
        if res.truth is not None:
            e = fit.estimate[n] - res.truth[n]
            row += f" {res.truth[n]:>11.5g} {e:>11.3g} {e / fit.std[n] if fit.std[n] > 0 else float('nan'):>8.2f}"
        if crb is not None:
            row += f" {crb[n]:>10.3g}"
        lines.append(row + f"  {UNITS[n]}")
    lines.append("correlation:")
    names = [sym(n) for n in fit.names]
    lines.append("       " + " ".join(f"{s:>7}" for s in names))
    for s, row in zip(names, fit.correlation):
        lines.append(f"{s:<6} " + " ".join(f"{v:>7.3f}" for v in row))
    lines.append("fit percent (NRMSE): " + ", ".join(f"{k} {v:.2f} %" for k, v in fit.fit_percent.items()))
    if not res.converged:
        for r in res.reasons + fit.reasons:
            lines.append(f"  reason: {r}")
    return "\n".join(lines)


def plot_fit(folder: str | Path, res) -> list[str]:
    """One PNG per experiment: measured vs predicted per channel, residuals beneath."""
    return plot_experiments(folder, res.experiments, res.fit, f"Step {res.step}: {res.spec.description}"
                            + ("" if res.converged else " (NOT CONVERGED)"))


def plot_experiments(folder: str | Path, experiments, fit, title: str) -> list[str]:
    """One PNG per experiment of ``fit`` (a ``FitResult`` of ``experiments``, in order): measured vs
    predicted per channel with its fit %, the residuals with +-3 sigma beside (``<name>_fit.png``)."""
    from otbot_hw.plots import _plt

    plt = _plt()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for e, pred in zip(experiments, fit.predicted):
        chans = list(e.channels)
        fig, axes = plt.subplots(len(chans), 2, figsize=(11, 2.2 * len(chans) + 0.6), squeeze=False,
                                 gridspec_kw={"width_ratios": [3, 2]})
        for i, c in enumerate(chans):
            key = f"{e.name}/{c}"
            ax = axes[i, 0]
            ax.plot(e.t, e.measured[c], lw=0.8, color="0.5", label="measured")
            ax.plot(e.t, pred[c], lw=1.4, color="C3", label="predicted")
            ax.set_ylabel(f"{c} ({CHANNEL_UNITS[c]})", fontsize=8)
            ax.set_title(f"{c}: fit {fit.fit_percent[key]:.2f} %", fontsize=9)
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=7, loc="best")
            ax2 = axes[i, 1]
            ax2.plot(e.t, e.measured[c] - pred[c], lw=0.7)
            ax2.axhline(3 * e.sigma[c], color="k", lw=0.6, ls="--")
            ax2.axhline(-3 * e.sigma[c], color="k", lw=0.6, ls="--")
            ax2.set_title("residual (dashed: +-3 sigma)", fontsize=9)
            ax2.grid(True, alpha=0.3)
        axes[-1, 0].set_xlabel("t (s)")
        axes[-1, 1].set_xlabel("t (s)")
        fig.suptitle(f"{title}: {e.name}" if len(experiments) > 1 else title)
        fig.tight_layout()
        path = folder / f"{e.name}_fit.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        out.append(str(path))
    return out
