"""Whole-session accuracy on simulated robots that differ from nominal (report script, not a test).

Run: ``nice -n 10 .venv/bin/python benchmarks/bench_accuracy.py [--seeds 50] [--json out.json] [--plot DIR]``

For each seed a robot is drawn by ``identification.study.perturbed_robot`` (masses, inertias,
frictions +-20 %, chassis centre of mass moved up to 5 cm, a 20-300 kg load anywhere within
0.35 m of the pivot with its own inertia), the session's four experiments are simulated on
their fixtures (``simulated_recording``) and identified by ``identify_session``:

1. **Honest uncertainty.** For every parameter, the fraction of seeds whose error is within 3
   reported sigma (target >= 95 %), the mean reported sigma and the RMS error over it
   (about 1 when the sigma is right), for three ways of reporting: *naive* (each step's own std,
   earlier steps taken as exact: today's chaining), *propagated* (the chained estimates with the
   earlier steps' covariance propagated) and *joint* (one fit of all recordings, the default).
2. **Gates.** How often each step passes its quality gates (a correct model and white noise:
   nearly always; a false "redo" costs a rerun).
3. **Designed excitation.** The chassis and platform experiments designed once on the nominal
   robot, kept within the limits on the corners of the prior (``design.prior_scenarios``: the
   design cannot know the robot or the load), against the paper's constant
   torques at equal duration, both within ``ExperimentLimits``: mean reported sigma of each, the
   ratio (the measured sigma reduction), the within-3-sigma fraction of the designed sessions and
   the largest fraction of each limit reached on the true robots.
4. **Compute time** of the whole procedure per session (wall and CPU), and of the design.

Prints markdown tables (docs/identification.md, section "A whole session").
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from otbot_hw.identification.uncertainty import NUISANCE_PARAMS, SESSION_PARAMS  # noqa: E402

HOW = (("naive", "chained", "naive_std"), ("propagated", "chained", "propagated_std"), ("joint", "value", "std"))


def within(errs: np.ndarray, std: np.ndarray, k: float = 3.0) -> float:
    return float(np.mean(np.abs(errs) <= k * std))


def column(trials: list[dict], name: str, key: str) -> np.ndarray:
    return np.array([t["params"][name][key] for t in trials if name in t["params"]], dtype=float)


def honesty_table(trials: list[dict]) -> str:
    lines = ["| parameter | truth range | " + " | ".join(f"{h}: within 3 sigma | {h}: mean sigma | {h}: RMS of error/sigma"
                                                     for h, _, _ in HOW) + " |",
             "|---|---|" + "---|" * (3 * len(HOW))]
    for n in SESSION_PARAMS + NUISANCE_PARAMS:  # (the nuisance x_F0, y_F0: the sessions that estimated them)
        truth = column(trials, n, "truth")
        if not len(truth):
            continue
        row = f"| {n} | {truth.min():.4g} .. {truth.max():.4g} |"
        for _, val, sd in HOW:
            err = column(trials, n, val) - truth
            s = column(trials, n, sd)
            row += f" {100 * within(err, s):.0f} % | {s.mean():.3g} | {np.sqrt(np.mean((err / s) ** 2)):.2f} |"
        lines.append(row)
    return "\n".join(lines)


def trial(item: dict) -> dict:
    """``study.session_trial``; a session whose identification raises (``IdentificationError``, e.g. a
    parameter the joint fit finds not identifiable) is a failed session with that reason, no estimates."""
    from otbot_hw.identification.errors import IdentificationError
    from otbot_hw.identification.study import session_trial

    try:
        return session_trial(item)
    except IdentificationError as exc:
        return {"seed": int(item["seed"]), "passed": False, "error": f"{type(exc).__name__}: {exc}",
                "verdicts": {}, "reasons": [f"raised {type(exc).__name__}: {exc}"], "params": {}}


def gates_table(sets: dict[str, list[dict]]) -> str:
    lines = ["| session | sessions passed | " + " | ".join(f"{s} passed" for s in ("wheel", "pivot", "chassis", "platform"))
             + " | sessions that raised |", "|---|---|---|---|---|---|---|"]
    for label, trials in sets.items():
        row = f"| {label} | {100 * np.mean([t['passed'] for t in trials]):.0f} % |"
        for s in ("wheel", "pivot", "chassis", "platform"):
            v = [t["verdicts"].get(s) == "pass" for t in trials]
            row += f" {100 * np.mean(v):.0f} % |"
        row += f" {sum('error' in t for t in trials)} of {len(trials)} |"
        lines.append(row)
    return "\n".join(lines)


def design_table(paper: list[dict], designed: list[dict], designs: dict) -> str:
    lines = ["| parameter | CRB ratio at the design point | paper: mean sigma | designed: mean sigma | "
             "sigma ratio (designed / paper) | paper: RMS error | designed: RMS error | designed: within 3 sigma |",
             "|---|---|---|---|---|---|---|---|"]
    for n in SESSION_PARAMS:
        tp, td = column(paper, n, "truth"), column(designed, n, "truth")
        sp, sd = column(paper, n, "std"), column(designed, n, "std")
        ep, ed = column(paper, n, "value") - tp, column(designed, n, "value") - td
        crb = next((d["crb_ratio"][n] for d in designs.values() if n in d["crb_ratio"]), None)
        crb_s = f"{crb:.2f}" if crb is not None else "-"
        lines.append(f"| {n} | {crb_s} | {sp.mean():.3g} | {sd.mean():.3g} | {sd.mean() / sp.mean():.2f} | "
                     f"{np.sqrt(np.mean(ep ** 2)):.3g} | {np.sqrt(np.mean(ed ** 2)):.3g} | {100 * within(ed, sd):.0f} % |")
    return "\n".join(lines)


def margins_table(paper: list[dict], designed: list[dict]) -> str:
    keys = ("torque", "wheel_speed", "pivot_speed", "platform_speed", "travel_radius")
    lines = ["| excitation | step | " + " | ".join(keys) + " |", "|---|---|" + "---|" * len(keys)]
    for label, trials in (("paper", paper), ("designed", designed)):
        for s in ("chassis", "platform"):
            row = f"| {label} | {s} |"
            for k in keys:
                v = [t["margins"][s][k] for t in trials if "margins" in t]
                row += f" {np.max(v):.2f} |"
            lines.append(row)
    return "\n".join(lines)


def time_table(sets: dict[str, list[dict]], design_time: float) -> str:
    lines = ["| session | wall time: mean | wall time: max | CPU time: mean | CPU time: max |", "|---|---|---|---|---|"]
    for label, trials in sets.items():
        w = np.array([t["wall_time"] for t in trials if "wall_time" in t])
        c = np.array([t["cpu_time"] for t in trials if "cpu_time" in t])
        lines.append(f"| {label} | {w.mean():.2f} s | {w.max():.2f} s | {c.mean():.2f} s | {c.max():.2f} s |")
    if design_time > 0:
        lines.append(f"| designing both excitations (once) | {design_time:.1f} s | | | |")
    return "\n".join(lines)


def save(plt, fig, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return str(path)


def plot(folder: Path, trials: list[dict]) -> list[str]:
    from otbot_hw.plots import _plt

    plt = _plt()
    folder.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(3, 4, figsize=(13, 8), sharey=True)
    for ax, n in zip(axes.ravel(), SESSION_PARAMS):
        truth = column(trials, n, "truth")
        for h, val, sd in HOW:
            z = (column(trials, n, val) - truth) / column(trials, n, sd)
            ax.hist(np.clip(z, -12, 12), bins=np.linspace(-12, 12, 49), alpha=0.5, label=h)
        ax.axvline(-3, color="k", lw=0.6, ls="--")
        ax.axvline(3, color="k", lw=0.6, ls="--")
        ax.set_title(n, fontsize=9)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("error / reported sigma over seeds (dashed: +-3; clipped at +-12)")
    return [save(plt, fig, folder / "session_error_sigma.png")]


def plot_designs(folder: Path, designs: list) -> list[str]:
    """Designed and paper torques, and the pivot's path on the prior's corner robots (PNG)."""
    from otbot_hw.identification.design import paper_torques, predicted_motion, prior_scenarios
    from otbot_hw.plots import _plt

    plt = _plt()
    folder.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(len(designs), 3, figsize=(14, 4 * len(designs)), squeeze=False)
    for row, d in zip(axes, designs):
        t = np.arange(len(d.torques)) / d.spec.rate
        for j, name in enumerate(("tau_r", "tau_l", "tau_p")):
            row[0].plot(t, d.torques[:, j], color=f"C{j}", label=f"{name} designed")
            row[0].plot(t, paper_torques(d.step, d.spec.duration)[:, j], color=f"C{j}", ls="--", lw=0.8)
        row[0].set_title(f"{d.step}: torques (dashed: paper)", fontsize=9)
        row[0].set_xlabel("t (s)")
        row[0].set_ylabel("N m")
        row[0].legend(fontsize=7)
        for k, (label, U) in enumerate((("designed", d.torques), ("paper", paper_torques(d.step, d.spec.duration)))):
            ax = row[1 + k]
            for robot in prior_scenarios(d.step, base_robot(d)):
                q, _ = predicted_motion(d.spec, U, robot)
                ax.plot(q[:, 0], q[:, 1], lw=0.7)
            circ = plt.Circle((0, 0), d.limits.travel_radius, fill=False, ls="--", color="k")
            ax.add_patch(circ)
            ax.set_aspect("equal")
            ax.set_title(f"{d.step}, {label}: pivot path on the prior's corner robots (dashed: free area)",
                         fontsize=8)
            ax.set_xlabel("x (m)")
    return [save(plt, fig, folder / "designed_excitation.png")]


def base_robot(d):
    from otbot_hw.params import OtbotParams

    return OtbotParams(**d.design_params)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=50, help="robots (seeds) per configuration (default 50)")
    ap.add_argument("--no-design", action="store_true", help="skip the designed-excitation comparison")
    ap.add_argument("--json", type=Path, default=None, help="write every trial to this JSON file")
    ap.add_argument("--plot", type=Path, default=None, metavar="DIR", help="histogram of error/sigma (PNG)")
    args = ap.parse_args(argv)

    from otbot_hw.identification.design import design_excitation
    from otbot_hw.params import nominal

    seeds = range(args.seeds)
    sets: dict[str, list[dict]] = {}
    designs: dict[str, dict] = {}
    design_time = 0.0
    specs = None
    if not args.no_design:
        t0 = time.perf_counter()
        d_c = design_excitation("chassis", nominal(), progress=print)
        if args.plot:
            print(f"plot: {plot_designs(args.plot, [d_c])[0]}", flush=True)
        d_p = design_excitation("platform", nominal(), knot_spacing=0.25, progress=print)
        if args.plot:
            print(f"plot: {plot_designs(args.plot, [d_c, d_p])[0]}", flush=True)
        design_time = time.perf_counter() - t0
        designs = {"chassis": d_c.to_dict(), "platform": d_p.to_dict()}
        specs = {"chassis": d_c.spec, "platform": d_p.spec}
        print(f"designed in {design_time:.1f} s; CRB ratio at the design point: "
              + ", ".join(f"{k} {v:.2f}" for d in (d_c, d_p) for k, v in d.ratio().items()), flush=True)
    runs = [("paper excitation, joint fit", {"method": "joint"}),
            ("paper excitation, propagation", {"method": "propagate"})]
    if specs:
        runs.append(("designed excitation, joint fit", {"method": "joint", "specs": specs}))
    for label, item in runs:
        out = []
        for s in seeds:
            out.append(trial({**item, "seed": s}))
            if (s + 1) % 10 == 0:
                print(f"[{label}] {s + 1}/{len(seeds)} seeds", flush=True)
        sets[label] = out
    paper = sets["paper excitation, joint fit"]
    print(f"\n## Honest uncertainty ({len(seeds)} robots, paper excitation)\n")
    print(honesty_table(paper))
    print("\n## Quality gates\n")
    print(gates_table(sets))
    fails = [(label, t["seed"], t["reasons"]) for label, ts in sets.items() for t in ts if not t["passed"]]
    for label, seed, reasons in fails:
        print(f"- {label}, seed {seed}: {'; '.join(reasons)[:400]}")
    if specs:
        designed = sets["designed excitation, joint fit"]
        print(f"\n## Designed excitation against the paper's ({len(seeds)} robots, joint fit)\n")
        print(design_table(paper, designed, designs))
        print("\nHonest uncertainty with the designed excitation:\n")
        print(honesty_table(designed))
        print("\nLargest fraction of each limit reached on the true robots:\n")
        print(margins_table(paper, designed))
    print("\n## Compute time per session\n")
    print(time_table(sets, design_time))
    if args.plot:
        for p in plot(args.plot, paper):
            print(f"plot: {p}")
    if args.json:
        args.json.write_text(json.dumps({"designs": designs, "trials": sets}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
