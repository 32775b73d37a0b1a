"""Sensitivity sweep of step 3 (paper Figs 10-11): error vs initial-guess deviation.

For each noise seed the platform experiment is simulated once on ``truth``; then
step 3 is identified from guesses ``deviation`` away from the truth (see
``experiments.deviation_guess``: a load of d * 500 kg guessed d * 0.45 m off).
Work items (one per seed and block of deviations) run on an ``Executor``: local
processes by default, a Dask cluster when given.
"""
from __future__ import annotations

import math
import time
from typing import Any, Sequence

import numpy as np

from otbot_hw.identification.executors import Executor, SerialExecutor
from otbot_hw.params import OtbotParams, UNITS

PLATFORM = ("m_p", "I_p", "x_F", "y_F")


def sweep_task(task: dict[str, Any]) -> list[dict[str, Any]]:
    """Identify step 3 from every deviation of ``task`` on one simulated experiment (runs on a worker)."""
    from otbot_hw.identification.errors import IdentificationError
    from otbot_hw.identification.experiments import deviation_guess, simulate_experiment
    from otbot_hw.identification.model import set_prediction_threads
    from otbot_hw.identification.steps import identify_step

    set_prediction_threads(task.get("threads", 1))
    truth = OtbotParams.from_dict(task["truth"], source="sweep truth")
    base = OtbotParams.from_dict(task["base"], source="sweep base")
    rec = simulate_experiment("platform", truth, seed=task["seed"])
    out = []
    for d in task["deviations"]:
        t0 = time.perf_counter()
        guess = deviation_guess("platform", truth, d, angle=task.get("angle", math.pi / 4))
        point: dict[str, Any] = {"deviation": d, "seed": task["seed"], "angle": task.get("angle"), "guess": guess}
        try:
            res = identify_step("platform", [rec], base, guess=guess, global_start=task["global_start"],
                                truth=truth)
        except IdentificationError as exc:
            point.update(converged=False, error_message=str(exc), wall_time=time.perf_counter() - t0)
            out.append(point)
            continue
        f = res.fit
        point.update(
            converged=res.converged,
            estimate=f.estimate, std=f.std,
            error={n: f.estimate[n] - getattr(truth, n) for n in PLATFORM},
            starts=len(res.attempts), accepted=res.attempts[-1]["start"], nfev=sum(a.get("nfev", 0) or 0 for a in res.attempts),
            reasons=res.reasons, wall_time=time.perf_counter() - t0)
        point["error_sigma"] = {n: point["error"][n] / f.std[n] if f.std[n] > 0 else None for n in PLATFORM}
        out.append(point)
    return out


def deviation_grid(max_deviation: float = 1.0, points: int = 40) -> list[float]:
    """``points`` deviations evenly spaced in (0, max_deviation] (fractions)."""
    return [max_deviation * (i + 1) / points for i in range(points)]


def run_sweep(truth: OtbotParams, deviations: Sequence[float], seeds: Sequence[int],
              executor: Executor | None = None, base: OtbotParams | None = None, global_start: bool = True,
              block: int = 10, progress=None, angle: float = math.pi / 4,
              spread_directions: bool = False) -> dict[str, Any]:
    """Run the sweep; returns JSON-ready ``{points, summary, wall_time, executor, ...}``.

    truth: the simulated robot (e.g. ``nominal().with_load(...)``); base: known
    parameters for the fit (default ``truth``); block: deviations per work item; angle:
    direction (rad, platform frame) in which the guessed load is moved, or, with
    ``spread_directions``, seed i of n uses 2 pi i / n.
    """
    executor = executor or SerialExecutor()
    base = base or truth
    devs = [float(d) for d in deviations]
    tasks = []
    seeds = list(seeds)
    for j, s in enumerate(seeds):
        a = 2 * math.pi * j / len(seeds) if spread_directions else angle
        for i in range(0, len(devs), block):
            tasks.append({"truth": truth.to_dict(), "base": base.to_dict(), "seed": int(s),
                          "deviations": devs[i:i + block], "global_start": global_start, "angle": a})
    t0 = time.perf_counter()
    chunks = executor.map(sweep_task, tasks, progress=progress)
    wall = time.perf_counter() - t0
    points = [p for c in chunks for p in c]
    return {
        "truth": {n: getattr(truth, n) for n in PLATFORM},
        "deviations": devs, "seeds": [int(s) for s in seeds], "global_start": global_start,
        "points": points, "summary": summarize(points), "wall_time": wall, "fits": len(points),
        "executor": executor.describe(),
    }


def summarize(points: list[dict[str, Any]]) -> dict[str, Any]:
    """Converged fraction overall and per deviation; which start each fit was accepted from;
    per parameter the largest |error|, the fraction of converged points with |error| <= 3
    reported sigma, and ``spread_over_deviations``: the largest difference between the estimates
    of one seed from different deviations (0 when the guess does not change the result)."""
    conv = [p for p in points if p["converged"]]
    out: dict[str, Any] = {"points": len(points), "converged": len(conv),
                           "converged_fraction": len(conv) / len(points) if points else float("nan")}
    starts: dict[str, int] = {}
    for p in conv:
        starts[p["accepted"]] = starts.get(p["accepted"], 0) + 1
    out["accepted_start"] = starts
    by_dev: dict[float, list] = {}
    for p in points:
        by_dev.setdefault(p["deviation"], []).append(p["converged"])
    out["converged_fraction_by_deviation"] = {f"{d:g}": float(np.mean(v)) for d, v in sorted(by_dev.items())}
    per = {}
    for n in PLATFORM:
        errs = np.array([abs(p["error"][n]) for p in conv]) if conv else np.array([])
        zs = np.array([abs(p["error_sigma"][n]) for p in conv if p["error_sigma"][n] is not None])
        by_seed: dict[int, list[float]] = {}
        for p in conv:
            by_seed.setdefault(p["seed"], []).append(p["estimate"][n])
        spreads = [max(v) - min(v) for v in by_seed.values() if len(v) > 1]
        per[n] = {"max_abs_error": float(errs.max()) if len(errs) else None,
                  "median_abs_error": float(np.median(errs)) if len(errs) else None,
                  "within_3_sigma": float(np.mean(zs <= 3)) if len(zs) else None,
                  "spread_over_deviations": float(max(spreads)) if spreads else None, "unit": UNITS[n]}
    out["parameters"] = per
    return out


def plot_sweep(folder, result: dict[str, Any]) -> list[str]:
    """|error| vs deviation for m_p, I_p (one PNG) and x_F, y_F (another), like Figs 10-11."""
    from pathlib import Path

    from otbot_hw.plots import _plt

    plt = _plt()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    pts = result["points"]
    files = []
    for fname, names in (("sweep_mass_inertia.png", ("m_p", "I_p")), ("sweep_centre_of_mass.png", ("x_F", "y_F"))):
        fig, axes = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
        for ax, n in zip(axes, names):
            ok = [p for p in pts if p["converged"]]
            bad = [p for p in pts if not p["converged"]]
            if ok:
                d = np.array([100 * p["deviation"] for p in ok])
                e = np.array([abs(p["error"][n]) for p in ok])
                ax.semilogy(d, np.maximum(e, 1e-12), ".", ms=4, alpha=0.6, label="converged (one dot per seed)")
                devs = sorted(set(d))
                med = [np.median(e[d == v]) for v in devs]
                ax.semilogy(devs, med, "-", color="C1", lw=1.2, label="median")
                s = np.array([p["std"][n] for p in ok])
                ax.semilogy(devs, [3 * np.median(s[d == v]) for v in devs], "--", color="k", lw=0.8,
                            label="3 x median reported sigma")
            if bad:
                top = ax.get_ylim()[1] if ok else 1.0
                ax.plot([100 * p["deviation"] for p in bad], [top] * len(bad), "rx", label="not converged")
            ax.set_ylabel(f"|error {n}| ({UNITS[n]})")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7, loc="best")
        if result.get("global_start"):
            used = result["summary"]["accepted_start"].get("guess", 0)
            axes[-1].set_xlabel("deviation of the fallback guess (% of 500 kg at 0.45 m); "
                                f"{used} of {len(pts)} fits started from it, the rest from the equation-error "
                                "estimate", fontsize=8)
        else:
            axes[-1].set_xlabel("initial-guess deviation (% of 500 kg at 0.45 m); every fit starts from its guess")
        axes[0].set_title(f"Step 3 sensitivity: {len(result['seeds'])} noise seeds, "
                          f"{result['summary']['converged_fraction'] * 100:.1f} % converged")
        fig.tight_layout()
        path = folder / fname
        fig.savefig(path, dpi=110)
        plt.close(fig)
        files.append(str(path))
    return files
