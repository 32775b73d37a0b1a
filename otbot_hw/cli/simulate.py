"""``otbot simulate``: open-loop simulation under constant torques, with recording and plots."""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from otbot_hw.cli import CliError, add_json_flag, parse_vector, positive_float


def register(sub) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate the robot under constant motor torques (zero-order hold)",
        description="Simulate Otbot from rest under constant torques held by a zero-order hold. "
                    "Torques in N m (tau_r, tau_l, tau_p), duration in s, rate in Hz. The final "
                    "state q = (x, y [m], alpha, phi_r, phi_l, phi_p [rad]) and its rate are reported.",
    )
    p.add_argument("--torques", default="6,-10,6",
                   help="tau_r,tau_l,tau_p in N m, held constant (default: 6,-10,6); a leading minus "
                        "is fine: --torques -6,10,6")
    p.add_argument("--duration", type=float, default=3.0, help="simulated time in s (default 3)")
    p.add_argument("--rate", type=positive_float("--rate"), default=100.0,
                   help="sample and command rate in Hz (default 100)")
    p.add_argument("--fixture", choices=["floor", "stand", "locked"], default="floor",
                   help="floor (default), stand (chassis held, wheels free) or locked (wheels locked)")
    p.add_argument("--noise", choices=["paper", "none"], default="paper",
                   help="sensor noise: the paper's levels (default) or none")
    p.add_argument("--seed", type=seed_int, default=0, help="noise seed, an integer >= 0 (default 0)")
    p.add_argument("--params", type=Path, default=None,
                   help="parameter YAML (default config/otbot.yaml); a diagnosed model (otbot diagnose --out) with "
                        "an 'effects' section is simulated with those effects")
    p.add_argument("--out", type=Path, default=None, help="write the recording (MCAP) here")
    p.add_argument("--plot", type=Path, default=None, metavar="DIR", help="write PNG plots into DIR")
    add_json_flag(p)
    p.set_defaults(func=run)
    # argparse takes "-6,10,6" for an option; let values that start like a negative number be values
    if hasattr(p, "_negative_number_matcher"):
        p._negative_number_matcher = re.compile(r"^-\.?\d[0-9.eE+-]*(,.*)?$")


#: Longest run the command accepts (samples); 10^7 samples of 12 states are about 1 GB.
MAX_SAMPLES = 10_000_000


def seed_int(text: str) -> int:
    """argparse type: a noise seed, an integer >= 0."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--seed must be an integer >= 0, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"--seed must be an integer >= 0, got {text!r}")
    return v


def check_duration(duration: float, rate: float) -> int:
    """Number of ZOH intervals for ``duration`` s at ``rate`` Hz; CliError when not positive/finite."""
    if not np.isfinite(duration) or duration <= 0:
        raise CliError(f"--duration must be a finite number of seconds > 0, got {duration}")
    n = int(round(duration * rate))
    if n < 1:
        raise CliError(f"--duration {duration} s at --rate {rate} Hz gives no sample interval")
    if n > MAX_SAMPLES:
        raise CliError(f"--duration {duration} s at --rate {rate} Hz gives {n} samples; at most {MAX_SAMPLES}")
    return n


def check_output_folder(path: Path | None, option: str) -> None:
    """CliError unless the folder that will receive ``path`` exists (checked before simulating)."""
    if path is not None and not path.parent.resolve().is_dir():
        raise CliError(f"{option} {path}: folder {path.parent} does not exist")


def write_outputs(result: dict, rec, params, out: Path | None, plot: Path | None, title: str) -> None:
    """Write the recording and plots, turning file-system errors into CliError (exit 2)."""
    from otbot_hw.recording import write_recording

    try:
        if out:
            write_recording(out, rec)
            result["recording"] = str(out)
        if plot:
            result["plots"] = write_plots(plot, rec, params, title)
    except OSError as exc:
        raise CliError(f"cannot write output: {exc.strerror}: {exc.filename}") from None


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.model.kinematics import constraint_jacobian, holonomic_constraint
    from otbot_hw.model.effects import ExtendedModel
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import extended_recording, simulated_recording

    torques = parse_vector(args.torques, 3, "--torques")
    n = check_duration(args.duration, args.rate)
    check_output_folder(args.out, "--out")
    model = ExtendedModel.load(args.params)
    params = model.params
    dt = 1.0 / args.rate
    noise = NoiseModel.paper() if args.noise == "paper" else NoiseModel()
    U = np.tile(torques, (n, 1))
    if model.active_effects():  # a diagnosed model: the paper's dynamics plus its effects
        rec = extended_recording(model, U, dt, noise, seed=args.seed, fixture=args.fixture)
    else:
        rec = simulated_recording(params, U, dt, noise, seed=args.seed, fixture=args.fixture)
    q, qd = rec.truth_q[-1], rec.truth_qd[-1]
    result = {
        "t_final": float(rec.t[-1]),
        "samples": len(rec),
        "fixture": args.fixture,
        "torques": torques,
        "effects": model.active_effects(),
        "q": q.tolist(),
        "qd": qd.tolist(),
        "max_constraint_residual": float(max(np.abs(constraint_jacobian(a, params) @ b).max()
                                             for a, b in zip(rec.truth_q, rec.truth_qd))),
        "max_holonomic_residual": float(max(abs(holonomic_constraint(a, rec.truth_q[0], params))
                                            for a in rec.truth_q)),
    }
    write_outputs(result, rec, params, args.out, args.plot, "Simulation")
    if not args.json:
        print(f"simulated {result['t_final']:.3f} s ({result['samples']} samples, fixture {args.fixture})")
        print("final q  = " + ", ".join(f"{v:.6g}" for v in q) + "  (x, y m; alpha, phi_r, phi_l, phi_p rad)")
        print("final qd = " + ", ".join(f"{v:.6g}" for v in qd))
        for key in ("recording", "plots"):
            if key in result:
                print(f"{key}: {result[key]}")
    return result


def write_plots(folder: Path, rec, params, title: str) -> list[str]:
    """XY path with the robot drawn, states over time and sensor readings (PNGs)."""
    from otbot_hw.plots import plot_series, plot_states, plot_xy_path

    folder.mkdir(parents=True, exist_ok=True)
    x = np.hstack([rec.truth_q, rec.truth_qd])
    out = [plot_xy_path(folder / "xy_path.png", rec.truth_q, params, title=f"{title}: pivot path"),
           plot_states(folder / "states.png", rec.t, x, title=f"{title}: state")]
    if rec.imu_accel is not None:
        out.append(plot_series(folder / "imu.png", rec.t, {
            "a_x''": (rec.imu_accel[:, 0], "m/s^2"), "a_y''": (rec.imu_accel[:, 1], "m/s^2"),
            "omega_z": (rec.imu_gyro[:, 2], "rad/s")}, title=f"{title}: IMU (platform frame)"))
    return [str(p) for p in out]
