"""``otbot demo``: the main job against the built-in simulated robot.

Runs the paper's chassis experiment (tau = (6, -10, 6) N m for 3 s, 100 Hz
zero-order hold, IMU noise sigma = ND sqrt(SR) = 13.7e-3), writes its recording and plots,
identifies the chassis from it, runs the same experiment through the CANopen drivers, then tracks
the paper's corridor with the computed-torque controller over the simulated CAN bus, fed by the
pose EKF (recording and plots in ``corridor/``).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from otbot_hw.cli import CliError, add_json_flag, progress
from otbot_hw.cli.simulate import seed_int


def register(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="run the main job against the built-in simulated robot",
        description="Simulate the paper's chassis experiment (tau = 6, -10, 6 N m for 3 s at 100 Hz), write its "
                    "MCAP recording and PNG plots into --out-dir, identify the chassis from it, run the same "
                    "experiment through the CANopen drivers on virtual CAN, and track the corridor over the "
                    "simulated bus with EKF feedback (tracking errors in mm and rad, estimation errors = estimate "
                    "- truth in mm and rad).",
    )
    p.add_argument("--out-dir", type=Path, default=Path("otbot-demo"), help="output folder (default otbot-demo)")
    p.add_argument("--seed", type=seed_int, default=0, help="sensor noise seed, an integer >= 0 (default 0)")
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
    result["corridor"] = _corridor(out, params, quiet, args.seed)
    return result


def _corridor(out: Path, params, quiet: bool, seed: int = 0) -> dict:
    """The paper's corridor tracked over the simulated CAN bus by the loop runner, fed by the pose EKF
    on the encoders and IMU (by the simulator's true state, with a printed note, where the EKF is not
    installed); recording and plots in ``corridor/``."""
    from drivers.config import load_robot_config
    from otbot_hw.runtime.backends import BusSimBackend
    from otbot_hw.runtime.feedback import FeedbackUnavailable, load_ekf
    from otbot_hw.runtime.supervisor import SafetyConfig
    from otbot_hw.runtime.tracking import run_scenario
    from otbot_hw.sensors import NoiseModel

    cfg = load_robot_config()
    feedback = "ekf"
    note = None
    try:
        load_ekf()
    except FeedbackUnavailable as exc:
        feedback = "truth"
        note = f"{exc}: the controller is fed the simulator's true state instead"
        progress(f"[demo] note: {note}", True)
    progress(f"[demo] corridor: computed-torque tracking over the simulated CAN bus at {cfg.bus.control_rate:g} Hz, "
             f"feedback {feedback}, 5 x 3 m at 0.6 m/s", not quiet)
    folder = out / "corridor"
    folder.mkdir(parents=True, exist_ok=True)
    res = run_scenario("corridor", params, cfg.limits, robustness=False, plot_dir=folder,
                       progress=None if quiet else (lambda m: progress(f"[demo] {m}")),
                       backend=BusSimBackend(cfg, NoiseModel.paper(), seed), feedback=feedback,
                       safety=SafetyConfig.load(), path=folder / "corridor.mcap",
                       metadata={"command": "otbot demo", "noise": NoiseModel.paper().to_dict(), "seed": seed})
    keep = ("max_abs_error", "rms_error", "estimation_error", "peak_torque", "events", "saturation", "plots",
            "wall_time_s", "feedback", "bus", "backend", "loop", "recording", "completed", "fault")
    res = {k: res[k] for k in keep if k in res}
    if note:
        res["note"] = note
    if not res["completed"]:
        raise RuntimeError(f"corridor stopped by fault: {res['fault']}")
    if not quiet:
        e = res["max_abs_error"]
        print(f"[demo] corridor over the bus, feedback {feedback}: tracking error of the true pose, max |e_x| "
              f"{e['x'] * 1e3:.1f} mm, max |e_y| {e['y'] * 1e3:.1f} mm, max |e_alpha| {e['alpha']:.1e} rad")
        ee = res.get("estimation_error")
        if feedback == "truth":
            print("[demo] estimation error: none to report (the controller was fed the true state)")
        elif ee is not None:
            m, r = ee["max"], ee["rms"]
            print(f"[demo] estimation error (estimate - truth): max |x| {m['x'] * 1e3:.2f} mm, max |y| "
                  f"{m['y'] * 1e3:.2f} mm, max |alpha| {m['alpha']:.1e} rad; rms x {r['x'] * 1e3:.2f} mm, "
                  f"y {r['y'] * 1e3:.2f} mm, alpha {r['alpha']:.1e} rad")
        print("[demo] corridor settle times after start, corners and stop: "
              + ", ".join(f"{ev['settle_time_s']:.2f}" if ev["settle_time_s"] is not None else "-"
                          for ev in res["events"]) + " s")
        print(f"[demo] corridor recording: {res['recording']}")
        for p in res["plots"]:
            print(f"[demo] plot: {p}")
    return res
