"""Accuracy and consistency of the pose EKF on simulated runs with ground truth (issue 11, item 4).

The runs: the corridor and the figure-8 (``otbot_hw.control.scenarios``) tracked in closed loop on the
simulator's true state at the bus rate (100 Hz), then replayed under the same torques on the extended
model (``simulate_extended``) with the effect under study -- constant wheel slip (k_slip), slip bursts
(k_slip switched on for short spans), a gyro bias (b_gz) -- and read through the extended model's
sensor outputs (``sensor_model.sensor_outputs``) with the paper's noise (``NoiseModel.paper()``) and the
configured encoders' quantization (wheels 4096 x 10 counts per revolution, pivot 16384; count boundaries at
a random offset from the joints' zero, drawn per seed). Slip leaves the
body's motion unchanged (the contact transmits the force), so one closed-loop run serves every variant.

For each seed (noise and a draw of the initial pose from the filter's prior) every estimator runs on
the same recording: the EKF with IMU prediction, the EKF with dynamic-model prediction, IMU-only dead
reckoning (the paper's approach) and wheel odometry alone. Reported: position and heading error (max
and rms over the run, mean over seeds), average NEES (pose + twist, 6 dof) and encoder NIS (4 dof)
against their two-sided 95 % chi-square bounds for the seed count, gate rejections; the standstill
drift over 60 s; with slip bursts, the error with and without absolute pose fixes.

    python benchmarks/estimation_accuracy.py [--seeds 20] [--plot docs/img/estimation] [--json]
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from otbot_hw.estimation import EstimatorConfig, run_recording  # noqa: E402
from otbot_hw.estimation.consistency import average_bounds, nees, pose_twist_error  # noqa: E402
from otbot_hw.estimation.dead_reckoning import imu_dead_reckoning, wheel_odometry  # noqa: E402
from otbot_hw.estimation.ekf import INITIAL_POSE_STD  # noqa: E402
from otbot_hw.model import effects as fx  # noqa: E402
from otbot_hw.model import sensor_model  # noqa: E402
from otbot_hw.model.angles import wrap_angle  # noqa: E402
from otbot_hw.params import OtbotParams, nominal  # noqa: E402
from otbot_hw.recording import Recording  # noqa: E402
from otbot_hw.sensors import NoiseModel  # noqa: E402
from otbot_hw.simulation.simulator import simulate_extended  # noqa: E402

RATE_HZ = 100.0
#: Counts per joint revolution of the simulated bus's encoders (config/robot.yaml): wheels 4096 x 10, pivot 16384.
ENCODER_COUNTS = (40960, 40960, 16384)
SLIP_K = 0.005          # rad/(s N m), constant slip of the "slip" variant
BURST_K = 0.05          # rad/(s N m) during a burst
BURST_S = 0.3           # s, burst length
GYRO_BIAS = 0.02        # rad/s, the "gyro bias" variant (about 1.1 deg/s)
FIX_EVERY_S = 1.0       # s between absolute pose fixes
FIX_STD = (0.002, 0.002, 0.002)  # m, m, rad
BURSTS = {"corridor": (4.9, 7.5, 9.9, 14.9, 22.0), "figure8": (3.0, 7.0, 11.0, 15.0)}
VARIANTS = ("nominal", "slip", "gyro_bias", "bursts", "bursts_fixes")
ESTIMATORS = ("ekf_imu", "ekf_model", "imu_dead_reckoning", "wheel_odometry")


@functools.lru_cache(maxsize=None)
def closed_loop(name: str, rate_hz: float = RATE_HZ):
    """(U (N, 3) N m, F (N, 2) N, x0 (12,), dt) of scenario ``name`` tracked on the true state."""
    from otbot_hw.control.gains import gains_from_tstab
    from otbot_hw.control.scenarios import build_spec
    from otbot_hw.runtime.tracking import track
    from otbot_hw.motors import load_motor_limits

    params = nominal()
    limits = load_motor_limits()
    spec = build_spec(name, params, limits)
    run = track(spec, params, limits, gains_from_tstab(), rate_hz=rate_hz)
    return run.u, run.f, run.x[0].copy(), 1.0 / rate_hz


def quantize(phi: np.ndarray, counts=ENCODER_COUNTS, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Joint angles floored to whole encoder counts (as the drives and the pivot encoder report them);
    ``offset`` (rad, one per joint): where the encoder's count boundaries sit relative to the joint's zero."""
    step = 2 * np.pi / np.asarray(counts, dtype=float)
    off = np.asarray(offset, dtype=float)
    return np.floor((phi + off) / step + 1e-9) * step - off


def sensed_recording(params: OtbotParams, U: np.ndarray, F: np.ndarray, x0: np.ndarray, dt: float,
                     schedule: list[tuple[float, dict]], noise: NoiseModel, seed: int,
                     counts=ENCODER_COUNTS) -> Recording:
    """Replay torques U (N, 3) and pivot forces F (N, 2) on the extended model whose effects change over
    time: ``schedule`` [(t_start s, {effect: value})] (the first entry starts at 0), sensors from the
    extended model's outputs plus white noise (seeded) and encoder quantization."""
    n = len(U)
    starts = [int(round(t0 / dt)) for t0, _ in schedule] + [n]
    if starts[0] != 0:
        raise ValueError("the effect schedule must start at t = 0")
    X = np.empty((n + 1, 12))
    sens = {k: np.empty((n + 1, 3)) for k in ("joint_pos", "joint_vel", "imu_accel", "imu_gyro")}
    x, tau, slip = x0, np.zeros(3), np.zeros(2)
    for (a, b), (_, values) in zip(zip(starts[:-1], starts[1:]), schedule):
        if b <= a:
            continue
        eff = fx.effect_vector(values)
        traj = simulate_extended(params, eff, U[a:b], dt, x0=x, tau0=tau, forces=F[a:b])
        s = sensor_model.sensor_outputs(traj, params, eff)
        s["joint_pos"][:, :2] += slip
        X[a:b + 1] = traj.x
        for key in sens:
            sens[key][a:b + 1] = s[key]
        x, tau, slip = traj.x[-1], traj.tau[-1], slip + traj.slip[-1]
    rng = np.random.default_rng(seed)
    m = n + 1
    acc = sens["imu_accel"] + noise.accel * rng.standard_normal((m, 3))
    gyro = sens["imu_gyro"] + noise.gyro * rng.standard_normal((m, 3))
    offset = rng.uniform(0, 2 * np.pi / np.asarray(counts, dtype=float))  # the start is not on a count boundary
    pos = quantize(sens["joint_pos"] + noise.enc_angle * rng.standard_normal((m, 3)), counts, offset)
    vel = sens["joint_vel"] + noise.enc_rate * rng.standard_normal((m, 3))
    meta = {"source": "simulation", "sample_period": dt, "fixture": "floor", "params": params.to_dict(),
            "noise": noise.to_dict(), "seed": seed, "initial_state": x0.tolist(),
            "effects_schedule": [[t0, dict(v)] for t0, v in schedule], "encoder_counts": list(counts)}
    return Recording(t=np.arange(m) * dt, torque=np.vstack([U, U[-1:]]), joint_pos=pos, joint_vel=vel,
                     imu_accel=acc, imu_gyro=gyro, truth_q=X[:, :6].copy(), truth_qd=X[:, 6:].copy(),
                     truth_force=np.vstack([F, F[-1:]]), metadata=meta)


def schedule_for(scenario: str, variant: str) -> list[tuple[float, dict]]:
    """The effect schedule of a variant."""
    if variant == "nominal":
        return [(0.0, {})]
    if variant == "slip":
        return [(0.0, {"k_slip": SLIP_K})]
    if variant == "gyro_bias":
        return [(0.0, {"b_gz": GYRO_BIAS})]
    if variant in ("bursts", "bursts_fixes"):
        out = [(0.0, {})]
        for t0 in BURSTS[scenario]:
            out += [(t0, {"k_slip": BURST_K}), (t0 + BURST_S, {})]
        return out
    raise ValueError(f"unknown variant {variant!r}")


def run_once(scenario: str, variant: str, seed: int, params: OtbotParams, config: EstimatorConfig,
             estimators=ESTIMATORS) -> dict:
    """Every estimator on one recording; returns per-estimator metrics and the arrays for plots."""
    U, F, x0, dt = closed_loop(scenario)
    rec = sensed_recording(params, U, F, x0, dt, schedule_for(scenario, variant), NoiseModel.paper(), seed)
    rng = np.random.default_rng(10_000 + seed)
    tp, tt = rec.truth_q[:, :3], rec.truth_qd[:, :3]
    pose0 = tp[0] + np.asarray(INITIAL_POSE_STD) * rng.standard_normal(3)  # a draw from the prior
    fixes = {}
    if variant == "bursts_fixes":
        every = int(round(FIX_EVERY_S / dt))
        cov = np.diag(np.square(FIX_STD))
        for k in range(every, len(rec), every):
            fixes[k] = (tp[k] + np.asarray(FIX_STD) * rng.standard_normal(3), cov)
    out = {"t": rec.t, "truth": tp}
    for name in estimators:
        t0 = time.perf_counter()
        entry: dict = {}
        if name.startswith("ekf"):
            cfg = dataclasses.replace(config, prediction=name.split("_")[1])
            run = run_recording(rec, params, cfg, initial_pose=pose0, fixes=fixes)
            pose, twist = run.pose, run.twist
            err = pose_twist_error(pose, twist, tp, tt)
            # NIS of the accepted updates (a rejected one is an outlier by design: counted apart)
            nis_acc = np.where(run.nis["encoders"] <= run.gate["encoders"], run.nis["encoders"], np.nan)
            nis_h = np.where(run.nis["heading"] <= run.gate["heading"], run.nis["heading"], np.nan)
            entry.update(nees=nees(err, run.cov[:, :6, :6]), nis=nis_acc, nis_heading=nis_h,
                         rejected=run.rejected,
                         updates=run.updates, gyro_bias=run.gyro_bias, std=run.std)
        elif name == "imu_dead_reckoning":
            pose, twist = imu_dead_reckoning(rec, tp[0], tt[0])
        else:
            pose = wheel_odometry(rec, params, tp[0])
        entry["seconds"] = time.perf_counter() - t0
        e = pose - tp
        e[:, 2] = wrap_angle(e[:, 2])
        entry["pos_err"] = np.hypot(e[:, 0], e[:, 1])
        entry["alpha_err"] = np.abs(e[:, 2])
        entry["pose"] = pose
        out[name] = entry
    return out


def summarize(runs: list[dict], estimators=ESTIMATORS) -> dict:
    """Mean over seeds of each estimator's max/rms position and heading error; NEES/NIS averages."""
    res = {}
    for name in estimators:
        rows = [r[name] for r in runs]
        d = {"pos_max_mm": 1e3 * float(np.mean([r["pos_err"].max() for r in rows])),
             "pos_rms_mm": 1e3 * float(np.mean([np.sqrt(np.mean(r["pos_err"] ** 2)) for r in rows])),
             "alpha_max_mrad": 1e3 * float(np.mean([r["alpha_err"].max() for r in rows])),
             "alpha_rms_mrad": 1e3 * float(np.mean([np.sqrt(np.mean(r["alpha_err"] ** 2)) for r in rows])),
             "pos_max_worst_mm": 1e3 * float(max(r["pos_err"].max() for r in rows)),
             "seconds_per_run": float(np.mean([r["seconds"] for r in rows]))}
        if "nees" in rows[0]:
            N = len(rows)
            anees = np.mean([r["nees"] for r in rows], axis=0)
            anis = np.nanmean([r["nis"] for r in rows], axis=0)
            lo6, hi6 = average_bounds(6, N)
            lo3, hi3 = average_bounds(3, N)
            anis_h = np.nanmean([r["nis_heading"] for r in rows], axis=0)
            lo1, hi1 = average_bounds(1, N)
            d.update(nees_mean=float(anees.mean()), nees_bounds=[lo6, hi6],
                     nees_inside=float(np.mean((anees >= lo6) & (anees <= hi6))),
                     nis_mean=float(np.nanmean(anis)), nis_bounds=[lo3, hi3],
                     nis_inside=float(np.nanmean((anis >= lo3) & (anis <= hi3))),
                     nis_heading_mean=float(np.nanmean(anis_h)), nis_heading_bounds=[lo1, hi1],
                     nis_heading_inside=float(np.nanmean((anis_h >= lo1) & (anis_h <= hi1))),
                     rejected={k: float(np.mean([r["rejected"][k] for r in rows])) for k in rows[0]["rejected"]},
                     gyro_bias_final=float(np.mean([r["gyro_bias"][-1] for r in rows])))
        res[name] = d
    return res


def standstill_drift(params: OtbotParams, config: EstimatorConfig, seeds: int, duration: float = 60.0) -> dict:
    """The robot at rest for ``duration`` s (zero torque): how far each estimate wanders (mean over seeds)."""
    n = int(round(duration * RATE_HZ))
    U, F = np.zeros((n, 3)), np.zeros((n, 2))
    out = {}
    for variant, sched in (("nominal", [(0.0, {})]), ("gyro_bias", [(0.0, {"b_gz": GYRO_BIAS})])):
        rows = {k: [] for k in ESTIMATORS}
        for seed in range(seeds):
            rec = sensed_recording(params, U, F, np.zeros(12), 1 / RATE_HZ, sched, NoiseModel.paper(), seed)
            tp = rec.truth_q[:, :3]
            for name in ESTIMATORS:
                if name.startswith("ekf"):
                    run = run_recording(rec, params, dataclasses.replace(config, prediction=name.split("_")[1]),
                                        record_innovations=False)
                    pose = run.pose
                    rows[name].append((pose, run.standstill.mean()))
                elif name == "imu_dead_reckoning":
                    rows[name].append((imu_dead_reckoning(rec, tp[0])[0], None))
                else:
                    rows[name].append((wheel_odometry(rec, params, tp[0]), None))
        res = {}
        for name, vals in rows.items():
            d = [np.hypot(*(p[-1, :2] - p[0, :2])) for p, _ in vals]
            a = [abs(p[-1, 2] - p[0, 2]) for p, _ in vals]
            res[name] = {"drift_mm": 1e3 * float(np.mean(d)), "drift_max_mm": 1e3 * float(np.max(d)),
                         "alpha_drift_mrad": 1e3 * float(np.mean(a))}
            if vals[0][1] is not None:
                res[name]["standstill_fraction"] = float(np.mean([s for _, s in vals]))
        out[variant] = res
    return out


def model_noise_sweep(params: OtbotParams, config: EstimatorConfig, seeds: int,
                      densities=(0.05, 0.2, 0.5, 2.0)) -> list[dict]:
    """The dynamic-model prediction under several acceleration-noise densities ((m/s^2)/sqrt(Hz), the
    same for rad/s^2): no single value both follows the figure-8's unmodelled pivot forces and rejects
    slip bursts."""
    rows = []
    for q in densities:
        cfg = dataclasses.replace(config, model_accel_density=q, model_angular_density=q)
        for scenario in ("corridor", "figure8"):
            for variant in ("nominal", "bursts"):
                runs = [run_once(scenario, variant, s, params, cfg, estimators=("ekf_model",)) for s in range(seeds)]
                d = summarize(runs, estimators=("ekf_model",))["ekf_model"]
                rows.append({"density": q, "case": f"{scenario}/{variant}", "pos_max_mm": d["pos_max_mm"],
                             "alpha_max_mrad": d["alpha_max_mrad"], "nees_mean": d["nees_mean"],
                             "rejected": d["rejected"]})
    return rows


def held_imu(params: OtbotParams, config: EstimatorConfig, seeds: int) -> dict:
    """The corridor with a 1 kHz loop and a 100 Hz IMU (each reading held for ten samples, as a loop
    faster than its IMU records it): the EKF against the same at 100 Hz."""
    U, F, x0, dt = closed_loop("corridor", 1000.0)
    out = []
    for seed in range(seeds):
        rec = sensed_recording(params, U, F, x0, dt, [(0.0, {})], NoiseModel.paper(), seed)
        held = (np.arange(len(rec)) // 10) * 10
        rec.imu_accel, rec.imu_gyro = rec.imu_accel[held], rec.imu_gyro[held]
        t0 = time.perf_counter()
        run = run_recording(rec, params, config, record_innovations=False)
        wall = time.perf_counter() - t0
        tp, tt = rec.truth_q[:, :3], rec.truth_qd[:, :3]
        err = pose_twist_error(run.pose, run.twist, tp, tt)
        out.append({"pos_max_mm": 1e3 * float(np.hypot(err[:, 0], err[:, 1]).max()),
                    "alpha_max_mrad": 1e3 * float(np.abs(err[:, 2]).max()),
                    "nees_mean": float(nees(err, run.cov[:, :6, :6]).mean()), "seconds": wall,
                    "rejected": sum(run.rejected.values())})
    return {k: float(np.mean([o[k] for o in out])) for k in out[0]}


def plots(folder: Path, examples: dict, sums: dict) -> list[str]:
    """Error over time per estimator (one seed) and the averaged NEES/NIS against their bounds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    files = []
    for (scenario, variant), ex in examples.items():
        fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        for name in ESTIMATORS:
            axes[0].semilogy(ex["t"], 1e3 * np.maximum(ex[name]["pos_err"], 1e-6), label=name)
            axes[1].semilogy(ex["t"], 1e3 * np.maximum(ex[name]["alpha_err"], 1e-6), label=name)
        axes[0].set_ylabel("position error (mm)")
        axes[1].set_ylabel("|alpha error| (mrad)")
        axes[1].set_xlabel("t (s)")
        axes[0].legend(fontsize=8)
        axes[0].set_title(f"{scenario}, {variant}: estimate - truth (seed 0)")
        for ax in axes:
            ax.grid(True, which="both", alpha=0.3)
        p = folder / f"error_{scenario}_{variant}.png"
        fig.tight_layout()
        fig.savefig(p, dpi=100)
        plt.close(fig)
        files.append(str(p))
    for key, (scenario, variant, runs) in sums.items():
        fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        t = runs[0]["t"]
        N = len(runs)
        for ax, what, dof in ((axes[0], "nees", 6), (axes[1], "nis", 3)):
            lo, hi = average_bounds(dof, N)
            for name in ("ekf_imu", "ekf_model"):
                avg = np.nanmean([r[name][what] for r in runs], axis=0)
                ax.semilogy(t, avg, label=f"{name}: mean {np.nanmean(avg):.2f}", lw=0.8)
            ax.axhline(lo, color="k", ls="--", lw=0.8)
            ax.axhline(hi, color="k", ls="--", lw=0.8, label=f"95 % bounds over {N} seeds")
            ax.set_ylabel(f"average {what.upper()} ({dof} dof)")
            ax.legend(fontsize=8)
            ax.grid(True, which="both", alpha=0.3)
        axes[0].set_title(f"{scenario}, {variant}: consistency over {N} seeds")
        axes[1].set_xlabel("t (s)")
        p = folder / f"consistency_{scenario}_{variant}.png"
        fig.tight_layout()
        fig.savefig(p, dpi=100)
        plt.close(fig)
        files.append(str(p))
    return files


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=20, help="noise seeds per scenario and variant (default 20)")
    ap.add_argument("--scenarios", default="corridor,figure8")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--plot", type=Path, default=None, metavar="DIR", help="write PNG plots into DIR")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--markdown", type=Path, default=None, metavar="RESULT.json",
                    help="print the docs/estimation.md tables of a saved --json result and exit")
    args = ap.parse_args(argv)
    if args.markdown:
        print(markdown(json.loads(args.markdown.read_text())))
        return 0
    params = nominal()
    config = EstimatorConfig.load()  # the estimator section of config/robot.yaml
    result = {"seeds": args.seeds, "rate_hz": RATE_HZ, "config": config.to_dict(), "cases": {}}
    examples, sums = {}, {}
    start = time.perf_counter()
    for scenario in args.scenarios.split(","):
        for variant in args.variants.split(","):
            runs = []
            for seed in range(args.seeds):
                runs.append(run_once(scenario, variant, seed, params, config))
            print(f"[{time.perf_counter() - start:6.0f} s] {scenario} {variant}: {args.seeds} seeds", file=sys.stderr)
            result["cases"][f"{scenario}/{variant}"] = summarize(runs)
            examples[(scenario, variant)] = runs[0]
            if variant in ("nominal", "bursts", "gyro_bias"):
                sums[(scenario, variant)] = (scenario, variant, runs)
    result["standstill"] = standstill_drift(params, config, args.seeds)
    print(f"[{time.perf_counter() - start:6.0f} s] standstill", file=sys.stderr)
    few = min(args.seeds, 5)
    result["model_noise_sweep"] = model_noise_sweep(params, config, few)
    print(f"[{time.perf_counter() - start:6.0f} s] model noise sweep ({few} seeds)", file=sys.stderr)
    result["held_imu"] = {"seeds": few, **held_imu(params, config, few)}
    print(f"[{time.perf_counter() - start:6.0f} s] 1 kHz loop, 100 Hz IMU ({few} seeds)", file=sys.stderr)
    if args.plot:
        result["plots"] = plots(args.plot, examples, sums)
    if args.json:
        print(json.dumps(result))
    else:
        print_tables(result)
    return 0


def print_tables(result: dict) -> None:
    print(f"{result['seeds']} seeds, {result['rate_hz']:g} Hz; mean over seeds of the per-run max / rms")
    print(f"{'case':28s} {'estimator':20s} {'pos max':>9s} {'pos rms':>9s} {'alpha max':>10s} {'alpha rms':>10s}"
          f" {'NEES':>6s} {'in':>5s} {'NIS':>6s} {'in':>5s}  rejected")
    for case, sums in result["cases"].items():
        for name, d in sums.items():
            extra = ""
            if "nees_mean" in d:
                extra = (f" {d['nees_mean']:6.2f} {d['nees_inside']:5.2f} {d['nis_mean']:6.2f} {d['nis_inside']:5.2f}  "
                         + ", ".join(f"{k} {v:g}" for k, v in d["rejected"].items() if v))
            print(f"{case:28s} {name:20s} {d['pos_max_mm']:7.2f}mm {d['pos_rms_mm']:7.2f}mm "
                  f"{d['alpha_max_mrad']:7.3f}mrad {d['alpha_rms_mrad']:7.3f}mrad{extra}")
    print("dynamic-model prediction, acceleration-noise density sweep:")
    for r in result["model_noise_sweep"]:
        print(f"  q = {r['density']:5.2f} {r['case']:18s} {r['pos_max_mm']:9.2f} mm {r['alpha_max_mrad']:8.3f} mrad "
              f"NEES {r['nees_mean']:9.2f}")
    h = result["held_imu"]
    print(f"corridor, 1 kHz loop with a 100 Hz IMU ({h['seeds']} seeds): pos max {h['pos_max_mm']:.2f} mm, "
          f"alpha max {h['alpha_max_mrad']:.3f} mrad, NEES {h['nees_mean']:.2f}, {h['seconds']:.2f} s per run")
    print("standstill 60 s: drift of the final pose from the start (mean over seeds)")
    for variant, res in result["standstill"].items():
        for name, d in res.items():
            print(f"  {variant:10s} {name:20s} {d['drift_mm']:10.3f} mm  {d['alpha_drift_mrad']:8.3f} mrad")


NAMES = {"ekf_imu": "EKF, IMU prediction", "ekf_model": "EKF, model prediction",
         "imu_dead_reckoning": "IMU dead reckoning (paper)", "wheel_odometry": "wheel odometry"}


def markdown(result: dict) -> str:
    """The tables of docs/estimation.md from a --json result."""
    n = result["seeds"]
    out = [f"Pose error, mean over {n} seeds of each run's maximum and rms (position: distance in mm; "
           f"heading: |alpha error| in mrad):", "",
           "| scenario | plant | estimator | position max | position rms | heading max | heading rms |",
           "|---|---|---|---|---|---|---|"]
    for case, sums in result["cases"].items():
        scenario, variant = case.split("/")
        for name, d in sums.items():
            out.append(f"| {scenario} | {variant.replace('_', ' ')} | {NAMES[name]} | {d['pos_max_mm']:.2f} | "
                       f"{d['pos_rms_mm']:.2f} | {d['alpha_max_mrad']:.3f} | {d['alpha_rms_mrad']:.3f} |")
    out += ["", f"Consistency over {n} seeds: time average of the seed-averaged NEES (pose + twist, 6 dof) and of "
                f"the accepted updates' NIS (joint rates, 3 dof; wheel heading, 1 dof), the two-sided 95 % "
                f"chi-square bounds of a {n}-run average, the fraction of samples whose average lies inside, and "
                f"the mean number of gate rejections per run:", "",
            "| scenario | plant | prediction | NEES (bounds) | inside | NIS rates (bounds) | inside | NIS heading (bounds) "
            "| rejected per run |", "|---|---|---|---|---|---|---|---|---|"]
    for case, sums in result["cases"].items():
        scenario, variant = case.split("/")
        for name in ("ekf_imu", "ekf_model"):
            d = sums[name]
            rej = ", ".join(f"{k} {v:g}" for k, v in d["rejected"].items() if v) or "none"
            out.append(f"| {scenario} | {variant.replace('_', ' ')} | {name[4:]} | {d['nees_mean']:.2f} "
                       f"({d['nees_bounds'][0]:.2f}-{d['nees_bounds'][1]:.2f}) | {d['nees_inside']:.2f} | "
                       f"{d['nis_mean']:.2f} ({d['nis_bounds'][0]:.2f}-{d['nis_bounds'][1]:.2f}) | {d['nis_inside']:.2f} | "
                       f"{d['nis_heading_mean']:.2f} ({d['nis_heading_bounds'][0]:.2f}-{d['nis_heading_bounds'][1]:.2f}) | "
                       f"{rej} |")
    out += ["", "Standstill, 60 s at rest (zero torque): distance of the final pose from the start, mean (max) over "
                f"{n} seeds:", "", "| gyro | estimator | position drift (mm) | heading drift (mrad) |", "|---|---|---|---|"]
    for variant, res in result["standstill"].items():
        for name, d in res.items():
            out.append(f"| {variant.replace('_', ' ')} | {NAMES[name]} | {d['drift_mm']:.3f} ({d['drift_max_mm']:.3f}) | "
                       f"{d['alpha_drift_mrad']:.3f} |")
    sw = result["model_noise_sweep"]
    out += ["", f"Model prediction under other acceleration-noise densities ({min(n, 5)} seeds; the default is 0.5):",
            "", "| density ((m/s^2)/sqrt(Hz)) | case | position max (mm) | heading max (mrad) | NEES |",
            "|---|---|---|---|---|"]
    for r in sw:
        out.append(f"| {r['density']:g} | {r['case']} | {r['pos_max_mm']:.2f} | {r['alpha_max_mrad']:.3f} | "
                   f"{r['nees_mean']:.2f} |")
    h = result["held_imu"]
    out += ["", f"Corridor with a 1 kHz loop and a 100 Hz IMU (each reading held for ten samples; {h['seeds']} seeds): "
                f"position max {h['pos_max_mm']:.2f} mm, heading max {h['alpha_max_mrad']:.3f} mrad, NEES "
                f"{h['nees_mean']:.2f} (6 dof), {h['seconds']:.2f} s of EKF per 30 s run."]
    return "\n".join(out)


if __name__ == "__main__":
    sys.exit(main())
