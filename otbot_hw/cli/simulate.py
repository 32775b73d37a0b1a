"""``otbot simulate``: open-loop simulation under constant torques, with recording and plots."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from otbot_hw.cli import CliError, add_json_flag, parse_vector, progress
from otbot_hw.cli.checks import (default_input, duration, output_file, output_folder, rate, rounding_notice,
                                 sample_count, seed, write_complete, writing)


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
    p.add_argument("--duration", type=duration, default=3.0, help="simulated time in s (default 3)")
    p.add_argument("--rate", type=rate, default=100.0,
                   help="sample and command rate in Hz (default 100)")
    p.add_argument("--fixture", choices=["floor", "stand", "locked"], default="floor",
                   help="floor (default), stand (chassis held, wheels free) or locked (wheels locked)")
    p.add_argument("--noise", choices=["paper", "none"], default="paper",
                   help="sensor noise: the paper's levels (default) or none")
    p.add_argument("--seed", type=seed, default=0, help="noise seed, an integer >= 0 (default 0)")
    p.add_argument("--params", type=Path, default=None,
                   help="parameter YAML (default config/otbot.yaml); a diagnosed model (otbot diagnose --out) with "
                        "an 'effects' section is simulated with those effects")
    p.add_argument("--out", type=Path, default=None, metavar="RUN.mcap",
                   help="write the recording (MCAP) here; its folder must exist")
    p.add_argument("--plot", type=Path, default=None, metavar="DIR",
                   help="write PNG plots into DIR (created if missing; its parent must exist)")
    add_json_flag(p)
    p.set_defaults(func=run)


#: Kept for callers that import it from here: the shared output-file check (``checks.output_file``).
check_output_folder = output_file


class stage_progress:
    """Progress lines ``[simulate] ...`` on stderr for a long run (more than one ``simulator.CHUNK`` of
    intervals) unless --json: ``say(stage)`` names a stage, ``say.chunk(done, total)`` counts its work
    (a line per tenth)."""

    def __init__(self, n: int, enabled: bool):
        from otbot_hw.simulation.simulator import CHUNK

        self.on = enabled and n > CHUNK
        self._shown = -1

    def __call__(self, stage: str) -> None:
        self._shown = -1
        progress(f"[simulate] {stage}", self.on)

    def chunk(self, done: int, total: int) -> None:
        tenth = 10 * done // max(total, 1)
        if tenth != self._shown:
            self._shown = tenth
            progress(f"[simulate]   {done}/{total} ({100 * done // max(total, 1)} %)", self.on)


def write_outputs(result: dict, rec, params, out: Path | None, plot: Path | None, title: str,
                  progress=None) -> None:
    """Write the recording and plots; file-system errors become CliError (exit 2). ``progress(done, n)``
    counts the samples written."""
    from otbot_hw.recording import write_recording

    with writing("output"):
        if out:  # an interrupted write leaves no truncated recording; a device is written as it is
            write_complete(out, lambda path: write_recording(path, rec, progress=progress))
            if out.is_file():
                result["recording"] = str(out)
        if plot:
            result["plots"] = write_plots(plot, rec, params, title)


def check_finite(rec, what: str) -> None:
    """CliError when a simulated state went non-finite (the integration diverged), or else a sensor reading
    (accelerations beyond the float range at a finite state)."""
    for part, arrays in (("the state", (rec.truth_q, rec.truth_qd)),
                         ("a sensor reading", (rec.joint_pos, rec.joint_vel, rec.imu_accel, rec.imu_gyro))):
        bad = ~np.isfinite(np.hstack(arrays)).all(axis=1)
        if bad.any():
            k = int(np.argmax(bad))
            raise CliError(f"the simulation diverged: {part} is not finite from t = {rec.t[k]:g} s (sample {k}); "
                           f"{what}")


def residuals(rec, params) -> tuple[float, float]:
    """Largest |J(q) q_dot| (the rolling constraints, ``kinematics.constraint_jacobian``) and largest
    holonomic residual (``kinematics.holonomic_constraint``) over the run, vectorized in blocks of
    samples (a Python loop over 10^7 samples took a minute)."""
    q0 = rec.truth_q[0]
    k = params.r / (2 * params.l2)
    l1, r = params.l1, params.r
    worst_j = worst_h = 0.0
    for a in range(0, len(rec), 1_000_000):
        q, v = rec.truth_q[a:a + 1_000_000], rec.truth_qd[a:a + 1_000_000]
        th = q[:, 2] - q[:, 5]
        s, c = np.sin(th), np.cos(th)
        j = np.abs(np.stack([v[:, 0] + l1 * s * v[:, 2] - 0.5 * r * c * (v[:, 3] + v[:, 4]) - l1 * s * v[:, 5],
                             v[:, 1] - l1 * c * v[:, 2] - 0.5 * r * s * (v[:, 3] + v[:, 4]) + l1 * c * v[:, 5],
                             v[:, 2] - k * v[:, 3] + k * v[:, 4] - v[:, 5]]))
        h = np.abs((q[:, 2] - k * q[:, 3] + k * q[:, 4] - q[:, 5]) - (q0[2] - k * q0[3] + k * q0[4] - q0[5]))
        worst_j, worst_h = max(worst_j, float(j.max())), max(worst_h, float(h.max()))
    return worst_j, worst_h


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.model.effects import ExtendedModel
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import extended_recording, simulated_recording

    torques = parse_vector(args.torques, 3, "--torques")
    n = sample_count(args.duration, args.rate)
    note = rounding_notice(args.duration, args.rate, n, "simulate")
    progress(note or "", note is not None)  # a duration that is not a whole number of periods: say so
    output_file(args.out, "--out", inputs={"parameter file": default_input(args.params, "otbot.yaml")})
    output_folder(args.plot, "--plot")
    model = ExtendedModel.load(args.params)
    params = model.params
    dt = 1.0 / args.rate
    noise = NoiseModel.paper() if args.noise == "paper" else NoiseModel()
    U = np.tile(torques, (n, 1))
    say = stage_progress(n, not args.json)
    # a diverged run's sensor readings overflow (numpy warning lines): check_finite says it in one line
    with np.errstate(over="ignore", invalid="ignore"):
        if model.active_effects():  # a diagnosed model: the paper's dynamics plus its effects
            say(f"integrating {n} intervals (extended model), then the sensor readings")
            rec = extended_recording(model, U, dt, noise, seed=args.seed, fixture=args.fixture, progress=say.chunk)
        else:
            say(f"integrating {n} intervals, then the sensor readings")
            rec = simulated_recording(params, U, dt, noise, seed=args.seed, fixture=args.fixture,
                                      progress=say.chunk)
    say("checking the constraints")
    check_finite(rec, f"--torques {args.torques} N m are too large for the model (or for --rate "
                      f"{args.rate:g} Hz); nothing was written")
    q, qd = rec.truth_q[-1], rec.truth_qd[-1]
    worst_j, worst_h = residuals(rec, params)
    result = {
        "t_final": float(rec.t[-1]),
        "samples": len(rec),
        "fixture": args.fixture,
        "torques": torques,
        "effects": model.active_effects(),
        "q": q.tolist(),
        "qd": qd.tolist(),
        "max_constraint_residual": worst_j,
        "max_holonomic_residual": worst_h,
    }
    if args.out:
        say(f"writing {args.out}")
    write_outputs(result, rec, params, args.out, args.plot, "Simulation", say.chunk if say.on else None)
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
