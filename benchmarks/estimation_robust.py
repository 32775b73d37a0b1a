"""The pose EKF on robots that differ from the parameter file it is given (issue 11, a model that is wrong).

The robots are the identification benchmark's (``otbot_hw.identification.study.perturbed_robot``: masses,
inertias, frictions +-20 %, centre of mass moved, an unknown platform load of 20-300 kg off the pivot).
Each is simulated (``simulate_extended`` through the paper's sensor model and the configured encoders,
``benchmarks/estimation_accuracy.sensed_recording``) under two open-loop torque programmes, and its
recording is estimated with the NOMINAL parameters (config/robot.yaml), as ``otbot estimate`` and the
loop do on a robot nobody identified:

* ``step``: the bench's platform floor run -- the paper's excitation (6, -10, 6) N m for 1 s -- then the
  torque reversed at half its size for 1.5 s (the torque step the bench's brake makes);
* ``corridor``: the corridor's torques and pivot forces (tracked on the nominal robot) replayed.

Reported per configuration: heading and position error (max over the run; mean and worst over the
robots), the average NEES (pose + twist, 6 dof), gate rejections per run, and how many runs diverged
(heading error above 0.1 rad).

    python benchmarks/estimation_robust.py [--robots 20] [--config default,no-adaptation] [--json]

The EKF of another checkout (e.g. main before the adaptation): ``PYTHONPATH=<checkout> python
benchmarks/estimation_robust.py --config default`` (the script's own directory comes after PYTHONPATH).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.append(str(ROOT))  # after PYTHONPATH: PYTHONPATH=<another checkout> measures that checkout's EKF

from otbot_hw.estimation import EstimatorConfig, run_recording  # noqa: E402  (before estimation_accuracy)
from estimation_accuracy import closed_loop, sensed_recording  # noqa: E402
from otbot_hw.estimation.consistency import nees, pose_twist_error  # noqa: E402
from otbot_hw.identification.study import perturbed_robot  # noqa: E402
from otbot_hw.params import nominal  # noqa: E402
from otbot_hw.sensors import NoiseModel  # noqa: E402

RATE_HZ = 100.0
STEP_TORQUE = (6.0, -10.0, 6.0)   # N m, the paper's floor excitation (chassis and platform steps)
STEP_S, REVERSE_S = 1.0, 1.5      # s of the excitation and of the reversed torque after it
DIVERGED = 0.1                    # rad: a heading error above this is a diverged filter
PROGRAMMES = ("step", "corridor")


def programme(name: str):
    """(U (N, 3) N m, F (N, 2) N, x0 (12,), dt s) of a torque programme."""
    if name == "corridor":
        return closed_loop("corridor", RATE_HZ)
    dt = 1.0 / RATE_HZ
    n1, n2 = int(round(STEP_S / dt)), int(round(REVERSE_S / dt))
    u = np.asarray(STEP_TORQUE)
    U = np.vstack([np.tile(u, (n1, 1)), np.tile(-0.5 * u, (n2, 1))])
    return U, np.zeros((len(U), 2)), np.zeros(12), dt


def run_one(name: str, seed: int, config: EstimatorConfig) -> dict:
    _, robot, load = perturbed_robot(seed)
    U, F, x0, dt = programme(name)
    rec = sensed_recording(robot, U, F, x0, dt, [(0.0, {})], NoiseModel.paper(), 1000 + seed)
    t0 = time.perf_counter()
    run = run_recording(rec, nominal(), config, record_innovations=False)
    err = pose_twist_error(run.pose, run.twist, rec.truth_q[:, :3], rec.truth_qd[:, :3])
    return {"programme": name, "seed": seed, "load_kg": load["mass"],
            "alpha_max": float(np.abs(err[:, 2]).max()), "pos_max": float(np.hypot(err[:, 0], err[:, 1]).max()),
            "nees": float(nees(err, run.cov[:, :6, :6]).mean()),
            "rejected": {k: v for k, v in run.rejected.items()}, "seconds": time.perf_counter() - t0}


def summarize(runs: list[dict]) -> dict:
    out = {}
    for name in PROGRAMMES:
        rs = [r for r in runs if r["programme"] == name]
        if not rs:
            continue
        kinds = sorted({k for r in rs for k in r["rejected"]})
        out[name] = {
            "robots": len(rs),
            "alpha_max_mean": float(np.mean([r["alpha_max"] for r in rs])),
            "alpha_max_worst": float(np.max([r["alpha_max"] for r in rs])),
            "pos_max_mean": float(np.mean([r["pos_max"] for r in rs])),
            "pos_max_worst": float(np.max([r["pos_max"] for r in rs])),
            "nees_median": float(np.median([r["nees"] for r in rs])),
            "nees_worst": float(np.max([r["nees"] for r in rs])),
            "rejected_per_run": {k: float(np.mean([r["rejected"].get(k, 0) for r in rs])) for k in kinds
                                 if any(r["rejected"].get(k, 0) for r in rs)},
            "diverged": int(sum(r["alpha_max"] > DIVERGED for r in rs)),
        }
    return out


CONFIGS = {
    "default": {},
    # without the adaptation of the unmodelled-alpha_dd walk (the gyro still re-anchors alpha_dot)
    "no-adaptation": {"walk_adaptation_window": 0.0},
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=20, help="perturbed robots (seeds 0..N-1)")
    ap.add_argument("--config", default="default,no-adaptation", help=f"comma list of {', '.join(CONFIGS)}")
    ap.add_argument("--programmes", default=",".join(PROGRAMMES))
    ap.add_argument("--label", default="", help="prefix of the EKF column (e.g. main)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    result = {"robots": args.robots, "configs": {}}
    t0 = time.perf_counter()
    for cname in args.config.split(","):
        cfg = EstimatorConfig().replace(**CONFIGS[cname])
        runs = []
        for name in args.programmes.split(","):
            for seed in range(args.robots):
                runs.append(run_one(name, seed, cfg))
                print(f"[{time.perf_counter() - t0:7.0f} s] {cname} {name} robot {seed}: heading max "
                      f"{runs[-1]['alpha_max']:.4f} rad, NEES {runs[-1]['nees']:.1f}", file=sys.stderr)
        result["configs"][args.label + cname] = {"summary": summarize(runs), "runs": runs}
    if args.json:
        print(json.dumps(result))
    else:
        print_table(result)
    return 0


def print_table(result: dict) -> None:
    print("| EKF | programme | robots | heading max mean (mrad) | worst (mrad) | position max mean (mm) | worst (mm) "
          "| NEES median | worst | rejected per run | diverged |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for cname, c in result["configs"].items():
        for name, s in c["summary"].items():
            rej = ", ".join(f"{k} {v:.3g}" for k, v in s["rejected_per_run"].items()) or "-"
            print(f"| {cname} | {name} | {s['robots']} | {1e3 * s['alpha_max_mean']:.2f} | {1e3 * s['alpha_max_worst']:.2f} "
                  f"| {1e3 * s['pos_max_mean']:.2f} | {1e3 * s['pos_max_worst']:.2f} | {s['nees_median']:.1f} "
                  f"| {s['nees_worst']:.1f} | {rej} | {s['diverged']}/{s['robots']} |")


if __name__ == "__main__":
    sys.exit(main())
