"""``otbot demo``: the main job against the built-in simulated robot.

Runs the paper's chassis experiment (tau = (6, -10, 6) N m for 3 s, 100 Hz
zero-order hold, IMU noise sigma = 13.73e-3), writes its recording and plots.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from otbot_hw.cli import add_json_flag, progress


def register(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="run the main job against the built-in simulated robot",
        description="Simulate the paper's chassis experiment (tau = 6, -10, 6 N m for 3 s at 100 Hz) "
                    "and write its MCAP recording and PNG plots into --out-dir.",
    )
    p.add_argument("--out-dir", type=Path, default=Path("otbot-demo"), help="output folder (default otbot-demo)")
    p.add_argument("--seed", type=int, default=0, help="sensor noise seed (default 0)")
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.cli.simulate import write_plots
    from otbot_hw.params import nominal
    from otbot_hw.recording import write_recording
    from otbot_hw.sensors import NoiseModel
    from sim.runs import simulated_recording

    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    params = nominal()
    quiet = args.json
    progress("[demo] chassis experiment: tau = (6, -10, 6) N m, 3 s, 100 Hz", not quiet)
    rec = simulated_recording(params, np.tile([6.0, -10.0, 6.0], (300, 1)), 0.01, NoiseModel.paper(),
                              seed=args.seed, extra_metadata={"experiment": "chassis (paper §4.3.2)"})
    path = out / "chassis.mcap"
    write_recording(path, rec)
    plots = write_plots(out / "chassis", rec, params, "Chassis experiment")
    result = {"chassis_experiment": {"recording": str(path), "plots": plots,
                                     "final_q": rec.truth_q[-1].tolist(), "final_qd": rec.truth_qd[-1].tolist()}}
    progress("[demo] identification: chassis parameters (step 2) from the recording", not quiet)
    from otbot_hw.identification.steps import demo_stage
    result["identification"] = demo_stage(rec, params, out, quiet)
    if not quiet:
        print(f"[demo] recording: {path}")
        for p in plots:
            print(f"[demo] plot: {p}")
        print("[demo] final q = " + ", ".join(f"{v:.4f}" for v in rec.truth_q[-1]))
    return result
