"""Statistical accuracy of the identification (report script, not a test).

Run: ``.venv/bin/python benchmarks/identification_accuracy.py [--seeds 30] [--sweep-seeds 20]
[--sweep-points 40] [--json results.json] [--plot DIR] [--scheduler ADDRESS]``

1. Per step, over noise seeds (paper experiments and noise levels): for each parameter
   the fraction of seeds with |error| <= 3 reported sigma (target >= 95 %), the mean
   reported sigma over the Cramer-Rao bound at the truth (target within 20 %), the
   RMS error over the bound (an efficient estimator gives about 1) and the mean error.
   Step 3 is run on the unloaded platform and with a large off-centre load.
2. Global convergence of step 3: deviations up to 100 % (a load of 500 kg guessed at
   0.45 m), unloaded truth and large off-centre true load, our pipeline and, for
   comparison, a single TRF fit from the guess: converged fraction and, among the
   converged points, the fraction within 4 sigma of the truth (a convergence claim
   that is wrong would show there). The guessed load is moved at 45 degrees (like the
   paper) or, in the last rows, in a direction spread over 360 degrees across seeds.

3. Random loads and guesses: random true loads (0-500 kg within 0.45 m) and random
   guesses (25-100 % deviation, any direction); a plain scipy TRF (2-point Jacobian,
   no x_scale, same compiled simulator and bounds) against our pipeline: how often each
   ends within 4 sigma of the truth.

Prints markdown tables (used in docs/identification.md).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from otbot_hw.identification.executors import make_executor  # noqa: E402
from otbot_hw.params import OtbotParams, nominal  # noqa: E402

LOAD = dict(mass=300.0, x=0.3, y=-0.2, inertia=5.0)
CASES = (("wheel", False), ("pivot", False), ("chassis", False), ("platform", False), ("platform", True))


def accuracy_task(task: dict) -> dict:
    """One seed of one step: estimate, std, converged (runs on a worker)."""
    from otbot_hw.identification.errors import IdentificationError
    from otbot_hw.identification.model import set_prediction_threads
    from otbot_hw.identification.steps import identify_simulated

    set_prediction_threads(1)
    truth = OtbotParams.from_dict(task["truth"])
    try:
        res = identify_simulated(task["step"], truth, seed=task["seed"])
    except IdentificationError as exc:
        return {"converged": False, "error_message": str(exc)}
    return {"converged": res.converged, "estimate": res.fit.estimate, "std": res.fit.std,
            "fit_percent": res.fit.fit_percent}


def crb_for(step: str, truth: OtbotParams) -> dict[str, float]:
    from otbot_hw.identification.experiments import PAPER_EXPERIMENTS, simulate_experiment
    from otbot_hw.identification.model import OtbotModel
    from otbot_hw.identification.prediction_error import cramer_rao_std
    from otbot_hw.identification.steps import experiments_from_recordings

    exps = experiments_from_recordings(step, [simulate_experiment(step, truth, seed=0)], truth)
    return cramer_rao_std(OtbotModel(), exps, PAPER_EXPERIMENTS[step].free, truth)


def random_starts(out: dict, n_truths: int, n_guesses: int) -> None:
    """Section 3: plain scipy TRF vs our pipeline from random guesses on random loads."""
    if n_truths <= 0 or n_guesses <= 0:
        return
    from scipy.optimize import least_squares

    from otbot_hw.identification.experiments import deviation_guess, simulate_experiment
    from otbot_hw.identification.model import OtbotModel
    from otbot_hw.identification.residual_problem import ResidualProblem, full_vector
    from otbot_hw.identification.steps import experiments_from_recordings, identify_step, platform_bounds

    robot = nominal()
    model = OtbotModel()
    free = ["m_p", "I_p", "x_F", "y_F"]
    b = platform_bounds(robot)
    lo = np.array([b[n][0] for n in free])
    hi = np.array([b[n][1] for n in free])
    rng = np.random.default_rng(2021)
    plain_ok = ours_ok = total = 0
    for k in range(n_truths):
        mass, rad, ang = rng.uniform(0, 500), rng.uniform(0, 0.45), rng.uniform(0, 2 * np.pi)
        truth = robot.with_load(mass, rad * np.cos(ang), rad * np.sin(ang), rng.uniform(0, 0.05 * mass))
        rec = simulate_experiment("platform", truth, seed=500 + k)
        exps = experiments_from_recordings("platform", [rec], robot)
        prob = ResidualProblem(model, exps, free, full_vector(model, robot), np.ones(4), lo, hi)
        ref = identify_step("platform", [rec], robot, guess=deviation_guess("platform", truth, 0.0))
        sd = np.array([ref.fit.std[n] for n in free])
        for _ in range(n_guesses):
            g = deviation_guess("platform", truth, rng.uniform(0.25, 1.0), angle=rng.uniform(0, 2 * np.pi))
            z0 = np.array([g[n] for n in free])
            sol = least_squares(prob.residuals, z0, bounds=(lo, hi), method="trf")
            truth_v = np.array([getattr(truth, n) for n in free])
            plain_ok += bool(np.all(np.abs(sol.x - truth_v) <= 4 * sd))
            res = identify_step("platform", [rec], robot, guess=g)
            est = np.array([res.fit.estimate[n] for n in free])
            ours_ok += bool(res.converged and np.all(np.abs(est - truth_v) <= 4 * sd))
            total += 1
    print("\n## Random loads and random guesses (step 3)\n")
    print("| method | fits | ended within 4 sigma of the truth |")
    print("|---|---|---|")
    print(f"| plain scipy TRF (2-point Jacobian, no x_scale) | {total} | {100 * plain_ok / total:.1f} % |")
    print(f"| our pipeline | {total} | {100 * ours_ok / total:.1f} % |")
    out["random_starts"] = {"fits": total, "plain_ok": plain_ok, "ours_ok": ours_ok}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--sweep-seeds", type=int, default=20)
    ap.add_argument("--sweep-points", type=int, default=40)
    ap.add_argument("--plain-seeds", type=int, default=5, help="seeds of the single-fit comparison sweep")
    ap.add_argument("--random-truths", type=int, default=12)
    ap.add_argument("--random-guesses", type=int, default=6)
    ap.add_argument("--scheduler", default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--plot", type=Path, default=None)
    args = ap.parse_args()
    from otbot_hw.identification.experiments import PAPER_EXPERIMENTS
    from otbot_hw.identification.sweep import deviation_grid, plot_sweep, run_sweep

    robot = nominal()
    heavy = robot.with_load(**LOAD)
    out: dict = {"accuracy": {}, "sweeps": {}}
    t_start = time.perf_counter()
    with make_executor(args.scheduler) as ex:
        print(f"executor: {ex.describe()}", file=sys.stderr)
        # -- 1. accuracy over seeds
        tasks, keys = [], []
        for step, loaded in CASES:
            truth = heavy if loaded else robot
            for s in range(args.seeds):
                tasks.append({"step": step, "truth": truth.to_dict(), "seed": 1000 + s})
                keys.append((step, loaded))

        def prog(d, n):
            if d % max(1, n // 10) == 0 or d == n:
                print(f"accuracy: {d}/{n}", file=sys.stderr, flush=True)

        results = ex.map(accuracy_task, tasks, progress=prog)
        print("## Accuracy over noise seeds\n")
        print(f"{args.seeds} seeds per row; sigma = reported std; CRB = Cramer-Rao bound at the truth.\n")
        print("| step | parameter | truth | mean error | RMS error | mean sigma | CRB | sigma/CRB | RMS error/CRB | "
              "within 3 sigma | converged |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for step, loaded in CASES:
            truth = heavy if loaded else robot
            rs = [r for r, k in zip(results, keys) if k == (step, loaded)]
            conv = [r for r in rs if r["converged"]]
            crb = crb_for(step, truth)
            label = step + (" (300 kg load off-centre)" if loaded else "")
            rows = {}
            for n in PAPER_EXPERIMENTS[step].free:
                err = np.array([r["estimate"][n] - getattr(truth, n) for r in conv])
                sig = np.array([r["std"][n] for r in conv])
                within = float(np.mean(np.abs(err) <= 3 * sig)) if len(conv) else float("nan")
                rows[n] = {"truth": getattr(truth, n), "mean_error": float(err.mean()),
                           "rms_error": float(np.sqrt(np.mean(err ** 2))), "mean_sigma": float(sig.mean()),
                           "crb": crb[n], "within_3_sigma": within, "converged": len(conv) / len(rs)}
                r_ = rows[n]
                sym = PAPER_EXPERIMENTS[step].symbol(n)
                print(f"| {label} | {sym} | {r_['truth']:.5g} | {r_['mean_error']:.2e} | {r_['rms_error']:.2e} | "
                      f"{r_['mean_sigma']:.2e} | {r_['crb']:.2e} | {r_['mean_sigma'] / r_['crb']:.3f} | "
                      f"{r_['rms_error'] / r_['crb']:.2f} | {100 * within:.0f} % | {100 * r_['converged']:.0f} % |")
            out["accuracy"][label] = rows
        # -- 2. global convergence
        devs = deviation_grid(1.0, args.sweep_points)
        print("\n## Global convergence of step 3\n")
        print("| true platform | method | fits | converged | converged and within 4 sigma | wall time |")
        print("|---|---|---|---|---|---|")
        for label, truth in (("unloaded", robot), ("300 kg at (0.3, -0.2) m", heavy)):
            for method, gs, nseeds, spread in (("pipeline", True, args.sweep_seeds, False),
                                               ("single TRF fit", False, args.plain_seeds, False),
                                               ("single TRF fit, guess directions over 360 deg", False,
                                                args.plain_seeds, True)):
                if nseeds <= 0:
                    continue
                t0 = time.perf_counter()
                res = run_sweep(truth, devs, range(nseeds), ex, base=robot, global_start=gs,
                                spread_directions=spread)
                wall = time.perf_counter() - t0
                pts = res["points"]
                conv = [p for p in pts if p["converged"]]
                good = [p for p in conv if all(abs(p["error_sigma"][n] or 0) <= 4 for n in p["error_sigma"])]
                print(f"| {label} | {method} | {len(pts)} | {100 * len(conv) / len(pts):.1f} % | "
                      f"{100 * len(good) / max(1, len(conv)):.1f} % | {wall:.0f} s |")
                key = f"{label} / {method}"
                out["sweeps"][key] = {"summary": res["summary"], "wall_time": wall,
                                      "within_4_sigma_of_converged": len(good) / max(1, len(conv))}
                if args.plot:
                    slug = (("unloaded" if truth is robot else "loaded") + ("" if gs else "_single_fit")
                            + ("_spread" if spread else ""))
                    out["sweeps"][key]["plots"] = plot_sweep(args.plot / slug, res)
    random_starts(out, args.random_truths, args.random_guesses)
    print(f"\ntotal {time.perf_counter() - t_start:.0f} s", file=sys.stderr)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
