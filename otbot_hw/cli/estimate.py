"""``otbot estimate``: run the pose EKF over a recording, write it as /otbot/estimate, compare with truth."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from otbot_hw.cli import CliError, add_json_flag
from otbot_hw.cli.checks import complete_samples, default_input, output_file, write_failure


def register(sub) -> None:
    p = sub.add_parser(
        "estimate",
        help="run the pose EKF over a recording (encoders + IMU) and compare it with the truth",
        description="Run the pose EKF (otbot_hw.estimation, docs/estimation.md) over an MCAP recording: the "
                    "wheel and pivot encoders (rad, rad/s) and the IMU (m/s^2, rad/s in the platform frame), "
                    "one step per sample. Reports the estimate's final pose x, y (m), alpha (rad), the gate "
                    "counts per update kind and, when the recording holds the truth, the estimation errors "
                    "(max, rms) of x, y (m) and alpha (rad). Without an IMU the dynamic model under the "
                    "recorded torques drives the prediction; without encoders the command refuses (exit 2).",
    )
    p.add_argument("recording", type=Path, metavar="RUN.mcap", help="recording in the otbot format")
    p.add_argument("--out", type=Path, default=None, metavar="EST.mcap",
                   help="write a copy of the recording with the estimate on /otbot/estimate")
    p.add_argument("--plot", type=Path, default=None, metavar="DIR",
                   help="write PNGs into DIR: path, innovations with their gates, errors against the truth")
    p.add_argument("--params", type=Path, default=None, metavar="P.yaml",
                   help="robot parameters (default config/otbot.yaml; a diagnosed model's effects are ignored)")
    p.add_argument("--config", type=Path, default=None, metavar="ROBOT.yaml",
                   help="estimator noise and gates: the 'estimator' section of this file (default config/robot.yaml)")
    p.add_argument("--prediction", choices=["imu", "model"], default=None,
                   help="what drives the prediction (default: the configuration's, imu)")
    add_json_flag(p)
    p.set_defaults(func=run)


def error_summary(rec, run) -> dict:
    """{'max': {x, y, alpha}, 'rms': {...}} of estimate - truth (m, m, rad; alpha wrapped)."""
    from otbot_hw.estimation.errors import estimation_error

    return estimation_error(run.pose, rec.truth_q[:, :3])


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.estimation import EstimatorConfig, EstimatorFault, run_recording
    from otbot_hw.estimation.replay import initial_state, with_estimate
    from otbot_hw.model.effects import ExtendedModel
    from otbot_hw.recording import read_recording, write_recording

    output_file(args.out, "--out", inputs={"recording": args.recording, "parameter file":
                                           default_input(args.params, "otbot.yaml"),
                                           "configuration file": default_input(args.config, "robot.yaml")})
    rec = read_recording(args.recording)
    truncated = complete_samples(args.recording, rec, "estimate", "estimate", "estimating on")
    params = ExtendedModel.load(args.params).params
    config = EstimatorConfig.load(args.config)
    if args.prediction:
        config = config.replace(prediction=args.prediction)
    try:
        est = run_recording(rec, params, config)
    except EstimatorFault as exc:
        raise CliError(f"{args.recording}: {exc}") from None
    _, _, source = initial_state(rec)
    nis_mean = {}
    for kind, v in est.nis.items():
        ok = v[np.isfinite(v) & (v <= est.gate[kind])]
        if len(ok):
            nis_mean[kind] = float(ok.mean())
    result = {
        "recording": str(args.recording),
        "truncated": truncated,
        "samples": len(rec),
        "duration_s": float(rec.t[-1] - rec.t[0]),
        "prediction": est.prediction,
        "initial_pose_source": source,
        "updates": est.updates,
        "rejected": est.rejected,
        "nis_mean": nis_mean,
        "gate": est.gate,
        "final": {"pose": est.pose[-1].tolist(), "twist": est.twist[-1].tolist(), "std": est.std[-1].tolist(),
                  "gyro_bias": float(est.gyro_bias[-1])},
        "standstill_fraction": float(est.standstill.mean()),
        "notes": est.notes,
    }
    if rec.truth_q is not None:
        result["estimation_error"] = error_summary(rec, est)
    if args.out:
        try:
            write_recording(args.out, with_estimate(rec, est, config))
        except OSError as exc:
            raise write_failure(exc, args.out) from None
        result["out"] = str(args.out)
    try:
        if args.plot:
            from otbot_hw.estimation.dead_reckoning import wheel_odometry
            from otbot_hw.estimation.plots import plot_errors, plot_innovations, plot_path

            args.plot.mkdir(parents=True, exist_ok=True)
            odo = wheel_odometry(rec, params, est.pose[0])
            files = [plot_path(args.plot / "path.png", rec, est, odo),
                     plot_innovations(args.plot / "innovations.png", est)]
            if rec.truth_q is not None:
                files.append(plot_errors(args.plot / "errors.png", rec, est))
            result["plots"] = [str(f) for f in files]
    except OSError as exc:
        raise write_failure(exc, args.plot) from None
    if not args.json:
        print_summary(result)
    return result


def print_summary(r: dict) -> None:
    x, y, a = r["final"]["pose"]
    sx, sy, sa = r["final"]["std"][:3]
    print(f"{r['samples']} samples over {r['duration_s']:.3f} s, prediction from the {r['prediction']}, "
          f"start pose from the {r['initial_pose_source']}")
    for note in r["notes"]:
        print(f"note: {note}")
    print(f"final pose: x = {x:.4f} m (std {1e3 * sx:.2f} mm), y = {y:.4f} m (std {1e3 * sy:.2f} mm), "
          f"alpha = {a:.5f} rad (std {1e3 * sa:.3f} mrad); gyro bias {r['final']['gyro_bias']:.2e} rad/s")
    used = [k for k in r["updates"] if r["updates"][k] or r["rejected"][k]]
    print("updates accepted / rejected by the gate: "
          + ", ".join(f"{k} {r['updates'][k]} / {r['rejected'][k]}" for k in used))
    if "estimation_error" in r:
        from otbot_hw.estimation.errors import describe_estimation_error

        print(describe_estimation_error(r["estimation_error"]))
    for key in ("out", "plots"):
        if key in r:
            print(f"{key}: {r[key]}")
