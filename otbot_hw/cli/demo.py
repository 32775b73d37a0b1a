"""``otbot demo``: the main job against the built-in simulated robot.

Runs the paper's chassis experiment (tau = (6, -10, 6) N m for 3 s, 100 Hz
zero-order hold, IMU noise sigma = ND sqrt(SR) = 13.7e-3), writes its recording and plots, then
tracks the paper's narrow corridor with the computed-torque controller (plots in
``corridor/``).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from otbot_hw.cli import CliError, add_json_flag, progress
from otbot_hw.cli.checks import output_folder, seed


def register(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="run the main job against the built-in simulated robot",
        description="Simulate the paper's chassis experiment (tau = 6, -10, 6 N m for 3 s at 100 Hz) "
                    "and write its MCAP recording and PNG plots into --out-dir.",
    )
    p.add_argument("--out-dir", type=Path, default=Path("otbot-demo"), help="output folder (default otbot-demo)")
    p.add_argument("--seed", type=seed, default=0, help="sensor noise seed, an integer >= 0 (default 0)")
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.cli.simulate import write_plots
    from otbot_hw.params import nominal
    from otbot_hw.recording import write_recording
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    out = args.out_dir
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"--out-dir {out}: cannot create folder: {exc.strerror}") from None
    params = nominal()
    quiet = args.json
    progress("[demo] chassis experiment: tau = (6, -10, 6) N m, 3 s, 100 Hz", not quiet)
    rec = simulated_recording(params, np.tile([6.0, -10.0, 6.0], (300, 1)), 0.01, NoiseModel.paper(),
                              seed=args.seed, extra_metadata={"experiment": "chassis (paper §4.3.2)"})
    path = out / "chassis.mcap"
    try:
        write_recording(path, rec)
        plots = write_plots(out / "chassis", rec, params, "Chassis experiment")
    except OSError as exc:
        raise CliError(f"cannot write output: {exc.strerror}: {exc.filename}") from None
    result = {"chassis_experiment": {"recording": str(path), "plots": plots,
                                     "final_q": rec.truth_q[-1].tolist(), "final_qd": rec.truth_qd[-1].tolist()}}
    if not quiet:
        print(f"[demo] recording: {path}")
        for p in plots:
            print(f"[demo] plot: {p}")
        print("[demo] final q = " + ", ".join(f"{v:.4f}" for v in rec.truth_q[-1]))
    progress("[demo] identification: chassis parameters (step 2) from the recording", not quiet)
    from otbot_hw.identification.steps import demo_stage
    result["identification"] = demo_stage(rec, params, out, quiet)
    from otbot_hw.cli.run import bus_demo
    result["bus_run"] = bus_demo(out, args.seed, quiet, reference=rec)
    result["corridor"] = _corridor(out, params, quiet)
    return result


def _corridor(out: Path, params, quiet: bool) -> dict:
    """The paper's corridor with the computed-torque controller (closed loop, 1 kHz)."""
    from otbot_hw.control.scenarios import demo_corridor
    from otbot_hw.motors import load_motor_limits

    progress("[demo] corridor: computed-torque tracking, 5 x 3 m at 0.6 m/s, 1 kHz", not quiet)
    res = demo_corridor(out / "corridor", params, load_motor_limits(),
                        progress=None if quiet else (lambda m: progress(f"[demo] {m}")))
    if not quiet:
        e = res["max_abs_error"]
        print(f"[demo] corridor: max |e| x {e['x'] * 1e3:.1f} mm, y {e['y'] * 1e3:.1f} mm, alpha {e['alpha']:.1e} rad; "
              "settle " + ", ".join(f"{ev['settle_time_s']:.2f}" if ev["settle_time_s"] is not None else "-"
                                    for ev in res["events"]) + " s")
        for p in res["plots"]:
            print(f"[demo] plot: {p}")
    return res
