"""The pose EKF in the loop: tracking and estimation measured on every simulated back end (issue 11).

Each run is ``otbot_hw.runtime.tracking.track``: the computed-torque controller through the loop runner,
fed by the EKF (``EkfFeedback``, the ``estimator:`` section of config/robot.yaml) or by the simulator's
truth, on

* ``direct 1 kHz``: ``DirectSimRobot`` with the configured sensors (encoder counts, 100 Hz IMU, drive
  torque resolution, motor limits) and the paper's noise, loop at 1 kHz (the IMU reading held over ten
  loop samples);
* ``direct 100 Hz``: the same at the bus rate;
* ``bus sim 100 Hz``: the CANopen drivers over virtual CAN to the simulated plant (``BusSimBackend``).

Scenarios: corridor, corridor-smooth, figure8 (its pivot forces). Plants: ``nominal``; ``bursts``: the
extended model's wheel slip k_slip = 0.05 rad/(s N m) switched on for 0.3 s at the times of
benchmarks/estimation_accuracy.py (``sim.effect_schedule``); ``bursts fixes``: the same with a simulated
motion capture feeding the EKF a pose fix (sigma 2 mm, 2 mrad) every second (``sim.mocap``). Each seed
draws the sensor noise and where the encoders' count boundaries sit: the robot starts at a random
fraction of a count on every joint (a real robot's encoders are not zeroed on its start pose; at
exactly zero the pivot's reading error starts at its worst, half a count).

Per run: largest tracking errors of the true pose (x, y mm; alpha mrad), estimation errors (estimate -
truth), settle time per event judged on the true errors (the issue's criterion: position and velocity
error norms below 2 % of the event's peak) and on the errors the controller is fed (estimate -
reference), the EKF's gate counts, NEES of pose + twist (6 dof) from the filter's covariance, and wall
time. Extras: ``--sweep`` the unmodelled-alpha_dd random walk against a plant with unmodelled pivot
friction and torque-gain errors; ``--pivot-counts`` the direct 1 kHz corridor with a finer pivot encoder.

    nice -n 10 python benchmarks/estimation_loop.py [--seeds 20 | --seed-list 4,15] [--backends ...]
        [--scenarios ...] [--plants ...]
        [--sweep SEEDS] [--pivot SEEDS] [--workers 1] [--json] > loop.json
    python benchmarks/estimation_loop.py --markdown loop*.json [--plot DIR] [--save MERGED.json]
                                          # tables (runs merged), plots, the merged result
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from otbot_hw.estimation import EstimatorConfig  # noqa: E402
from otbot_hw.estimation.consistency import average_bounds, nees, pose_twist_error  # noqa: E402
from otbot_hw.runtime.feedback import EkfFeedback  # noqa: E402

BACKENDS = ("direct 1 kHz", "direct 100 Hz", "bus sim 100 Hz")
SCENARIOS = ("corridor", "corridor-smooth", "figure8")
PLANTS = ("nominal", "bursts", "bursts fixes")
BURST_K = 0.05          # rad/(s N m)
BURST_S = 0.3           # s
BURSTS = {"corridor": (4.9, 7.5, 9.9, 14.9, 22.0), "corridor-smooth": (4.9, 7.5, 9.9, 14.9, 22.0),
          "figure8": (3.0, 7.0, 11.0, 15.0)}
FIX_HZ = 1.0
FIX_STD = (0.002, 0.002, 0.002)
#: the plant of the robustness sweep: unmodelled pivot Coulomb friction, wheel friction, torque-gain errors
UNMODELLED = {"c_p": 0.5, "k_p": 0.05, "c_r": 0.3, "c_l": 0.3, "k_r": 0.05, "k_l": -0.05}
ENCODER_COUNTS = (40960, 40960, 16384)


class RecordingEkf(EkfFeedback):
    """``EkfFeedback`` that also keeps, per sample, the covariance of pose + twist and the NIS of each
    update kind (for NEES/NIS against the truth)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.cov, self.nis = [], []

    def _record(self, est, snapshot):
        self.cov.append(np.array(est.cov[:6, :6]))
        self.nis.append(dict(est.nis))
        return super()._record(est, snapshot)


def make_backend(name: str, seed: int, pivot_counts: int | None = None):
    from drivers.config import load_robot_config
    from otbot_hw.runtime.backends import BusSimBackend, DirectBackend
    from otbot_hw.sensors import NoiseModel

    cfg = load_robot_config()
    if name.startswith("direct"):
        be = DirectBackend.from_config(cfg, 1000.0 if "1 kHz" in name else 100.0, NoiseModel.paper(), seed)
        if pivot_counts:
            be = dataclasses.replace(be, encoder_counts=(be.encoder_counts[0], be.encoder_counts[1], pivot_counts))
        return be
    return BusSimBackend(cfg, NoiseModel.paper(), seed)


def start_state(spec, seed: int, counts=ENCODER_COUNTS) -> np.ndarray:
    """The scenario's start with every joint at a random fraction of its encoder count (seeded)."""
    from otbot_hw.simulation.simulator import rest_state

    x0 = spec.x0.copy() if spec.x0 is not None else rest_state(spec.reference.sample(np.zeros(1))[0][0])
    rng = np.random.default_rng(50_000 + seed)
    x0[3:6] += rng.uniform(0, 1, 3) * 2 * np.pi / np.asarray(counts, dtype=float)
    return x0


def one_run(backend: str, scenario: str, plant: str, feedback: str, seed: int, config: dict | None = None,
            plant_effects: dict | None = None, pivot_counts: int | None = None) -> dict:
    """One loop run; returns its metrics (no arrays but the estimation-error trace for plots)."""
    from otbot_hw.control.gains import gains_from_tstab
    from otbot_hw.control.metrics import event_summary
    from otbot_hw.control.scenarios import build_spec, summarize
    from otbot_hw.model.effects import ExtendedModel, effect_vector
    from otbot_hw.motors import load_motor_limits
    from otbot_hw.params import nominal
    from otbot_hw.runtime.supervisor import SafetyConfig
    from otbot_hw.runtime.tracking import track
    from sim.effect_schedule import EffectSchedule, with_schedule
    from sim.mocap import MotionCapture

    params, limits = nominal(), load_motor_limits()
    spec = build_spec(scenario, params, limits)
    counts = ENCODER_COUNTS if pivot_counts is None else (*ENCODER_COUNTS[:2], pivot_counts)
    spec = dataclasses.replace(spec, x0=start_state(spec, seed, counts))
    be = make_backend(backend, seed, pivot_counts)
    plant_model = None
    if plant_effects:
        plant_model = ExtendedModel(params, effect_vector(plant_effects))
    if plant.startswith("bursts"):
        plant_model = ExtendedModel(params, effect_vector({**(plant_effects or {}), "k_slip": BURST_K}))
        be = with_schedule(be, EffectSchedule.bursts("k_slip", BURST_K, BURSTS[scenario], BURST_S))
    fixes = MotionCapture(FIX_HZ, FIX_STD, seed=20_000 + seed) if plant == "bursts fixes" else None
    fb = feedback
    if feedback == "ekf":
        cfg = EstimatorConfig.load().replace(**(config or {}))
        if pivot_counts:
            cfg = cfg.replace(pivot_angle_sigma=2 * np.pi / pivot_counts / np.sqrt(12))
        fb = RecordingEkf(params, be.period, spec.x0[:3], cfg, fixes=fixes)
    t0 = time.perf_counter()
    run = track(spec, params, limits, gains_from_tstab(3.0), backend=be, feedback=fb, plant=plant_model,
                safety=SafetyConfig.load())
    wall = time.perf_counter() - t0
    out = {"backend": backend, "scenario": scenario, "plant": plant, "feedback": feedback, "seed": seed,
           "completed": bool(run.completed), "fault": str(run.loop.fault) if run.loop.fault else None,
           "wall_s": wall, "config": config or {}, "plant_effects": plant_effects or {},
           "pivot_counts": pivot_counts}
    if len(run.t) < 2:
        return out
    s = summarize(spec, run, limits, params)
    out["track_max"] = {k: s["max_abs_error"][k] for k in ("x", "y", "alpha")}
    out["track_rms"] = {k: s["rms_error"][k] for k in ("x", "y", "alpha")}
    out["settle"] = [e["settle_time_s"] for e in s["events"]]
    out["events"] = [e["kind"] for e in s["events"]]
    if feedback == "ekf":
        e = run.est_pose - run.x[:, :3]
        out["est_max"] = {k: float(np.abs(e[:, i]).max()) for i, k in enumerate(("x", "y", "alpha"))}
        out["est_rms"] = {k: float(np.sqrt(np.mean(e[:, i] ** 2))) for i, k in enumerate(("x", "y", "alpha"))}
        pos = np.hypot(e[:, 0], e[:, 1])
        out["est_pos_max"], out["est_pos_final"] = float(pos.max()), float(pos[-1])
        out["gates"] = run.gates
        fed = event_summary(run.t, run.est_pose - run.p_ref, run.est_twist - run.pd_ref, spec.events)
        out["settle_fed"] = [ev["settle_time_s"] for ev in fed]
        # NEES over the loop's samples from the reference start on (the recording holds every sample)
        n = len(run.t)
        cov = np.asarray(fb.cov)[-n:]
        err = pose_twist_error(run.est_pose, run.est_twist, run.x[:, :3], run.x[:, 6:9])
        ne = nees(err, cov)
        out["nees_mean"] = float(ne[10:].mean())
        nis = fb.nis[-n:]
        out["nis_mean"] = {k: float(np.nanmean([d[k] for d in nis])) for k in ("encoders", "heading", "gyro")
                           if np.isfinite([d[k] for d in nis]).any()}
        if plant.startswith("bursts"):
            steps = []
            for tb in BURSTS[scenario]:
                before = pos[np.searchsorted(run.t, tb - 0.05)]
                after = pos[min(len(pos) - 1, np.searchsorted(run.t, tb + BURST_S + 0.5))]
                steps.append(float(after - before))
            out["burst_steps"] = steps
            k = max(1, len(run.t) // 600)
            out["trace"] = {"t": run.t[::k].tolist(), "pos_err": pos[::k].tolist()}
    return out


def _job(args):
    """One run; a back end that could not be set up (e.g. an SDO timeout on a machine too loaded for the
    simulated bus) is recorded as such, not the study lost."""
    try:
        return one_run(*args[:5], **args[5])
    except Exception as exc:  # noqa: BLE001 -- reported in the result, never silently
        return {"backend": args[0], "scenario": args[1], "plant": args[2], "feedback": args[3], "seed": args[4],
                "completed": False, "fault": f"setup failed: {type(exc).__name__}: {exc}", "wall_s": 0.0,
                "config": args[5].get("config") or {}, "plant_effects": args[5].get("plant_effects") or {},
                "pivot_counts": args[5].get("pivot_counts")}


def jobs_main(seeds: int, truth_seeds: int, backends, scenarios, plants, seed_list=None) -> list:
    """The main runs; ``seed_list``: these EKF seeds instead of 0 .. seeds - 1 (one seed looked at alone)."""
    jobs = []
    for be in backends:
        for sc in scenarios:
            for pl in plants:
                if pl != "nominal" and (sc == "corridor-smooth" or be == "direct 100 Hz"):
                    continue  # bursts: corridor and figure-8 on the 1 kHz and the bus back ends
                fbs = ("truth", "ekf") if pl == "nominal" else ("ekf",)
                for fb in fbs:
                    for seed in (range(truth_seeds) if fb == "truth" else seed_list or range(seeds)):
                        jobs.append((be, sc, pl, fb, seed, {}))
    return jobs


def jobs_sweep(seeds: int, walks=(0.03, 0.1, 0.3)) -> list:
    jobs = []
    for w in walks:
        for effects in ({}, UNMODELLED):
            for seed in range(seeds):
                jobs.append(("bus sim 100 Hz", "corridor", "nominal", "ekf", seed,
                             {"config": {"angular_disturbance_walk": w}, "plant_effects": effects or None}))
    for effects in ({}, UNMODELLED):
        for seed in range(min(seeds, 2)):
            jobs.append(("bus sim 100 Hz", "corridor", "nominal", "truth", seed, {"plant_effects": effects or None}))
    return jobs


def jobs_pivot(seeds: int, counts=(16384, 65536, 262144)) -> list:
    jobs = []
    for c in counts:
        for fb in ("truth", "ekf"):
            for seed in range(seeds if fb == "ekf" else 1):
                jobs.append(("direct 1 kHz", "corridor", "nominal", fb, seed, {"pivot_counts": c}))
    return jobs


def run_jobs(jobs, workers: int, tag: str) -> list:
    out = []
    start = time.perf_counter()
    if workers > 1:
        from multiprocessing import get_context

        with get_context("spawn").Pool(workers) as pool:
            for i, r in enumerate(pool.imap_unordered(_job, jobs)):
                out.append(r)
                print(f"[{time.perf_counter() - start:6.0f} s] {tag} {i + 1}/{len(jobs)}", file=sys.stderr, flush=True)
    else:
        for i, j in enumerate(jobs):
            out.append(_job(j))
            print(f"[{time.perf_counter() - start:6.0f} s] {tag} {i + 1}/{len(jobs)}: {j[:5]} "
                  f"{out[-1].get('wall_s', 0):.1f} s", file=sys.stderr, flush=True)
    return out


# ---------------------------------------------------------------------------------------------- summary
def _stat(rows, key, sub=None, f=np.mean):
    vals = [r[key][sub] if sub else r[key] for r in rows if key in r and (sub is None or r[key].get(sub) is not None)]
    return float(f(vals)) if vals else None


def summarize(runs: list) -> list:
    """One row per (backend, scenario, plant, feedback, config): means over seeds (max over seeds where said)."""
    groups = {}
    for r in runs:
        key = (r["backend"], r["scenario"], r["plant"], r["feedback"], json.dumps(r["config"], sort_keys=True),
               json.dumps(r["plant_effects"], sort_keys=True), r["pivot_counts"])
        groups.setdefault(key, []).append(r)
    rows = []
    for key, rs in groups.items():
        ok = [r for r in rs if "track_max" in r]
        row = {"backend": key[0], "scenario": key[1], "plant": key[2], "feedback": key[3], "config": json.loads(key[4]),
               "plant_effects": json.loads(key[5]), "pivot_counts": key[6], "seeds": len(rs),
               "completed": sum(r["completed"] for r in rs), "faults": [r["fault"] for r in rs if r["fault"]],
               "wall_s": _stat(rs, "wall_s")}
        if ok:
            for k in ("x", "y", "alpha"):
                row[f"track_max_{k}"] = _stat(ok, "track_max", k)
                row[f"track_max_{k}_worst"] = _stat(ok, "track_max", k, np.max)
            ev = np.array([[np.nan if s is None else s for s in r["settle"]] for r in ok], dtype=float)
            if ev.size:
                row["events"] = ok[0]["events"]
                row["settle_mean"] = [None if np.all(np.isnan(c)) else float(np.nanmean(c)) for c in ev.T]
                row["settle_worst"] = [None if np.any(np.isnan(c)) else float(np.max(c)) for c in ev.T]
                row["not_settled"] = [int(np.sum(np.isnan(c))) for c in ev.T]
        ekf = [r for r in ok if "est_max" in r]
        if ekf:
            for k in ("x", "y", "alpha"):
                row[f"est_max_{k}"] = _stat(ekf, "est_max", k)
                row[f"est_rms_{k}"] = _stat(ekf, "est_rms", k)
            row["est_pos_max"] = _stat(ekf, "est_pos_max")
            row["est_pos_max_worst"] = _stat(ekf, "est_pos_max", f=np.max)
            row["est_pos_final"] = _stat(ekf, "est_pos_final")
            row["nees_mean"] = _stat(ekf, "nees_mean")
            row["nees_bounds"] = list(average_bounds(6, len(ekf)))
            row["rejected"] = {k: float(np.mean([r["gates"]["rejected"][k] for r in ekf])) for k in ekf[0]["gates"]["rejected"]}
            row["fixes"] = float(np.mean([r["gates"]["updates"]["fix"] for r in ekf]))
            fed = np.array([[np.nan if s is None else s for s in r["settle_fed"]] for r in ekf], dtype=float)
            if fed.size:
                row["settle_fed_mean"] = [None if np.all(np.isnan(c)) else float(np.nanmean(c)) for c in fed.T]
                row["settle_fed_not_settled"] = [int(np.sum(np.isnan(c))) for c in fed.T]
            if "burst_steps" in ekf[0]:
                row["burst_steps_mm"] = [1e3 * float(np.mean(c)) for c in np.array([r["burst_steps"] for r in ekf]).T]
        rows.append(row)
    return rows


def attach_ratios(rows: list) -> None:
    """Tracking error of each EKF row over the truth row of the same back end, scenario and plant effects."""
    truth = {(r["backend"], r["scenario"], json.dumps(r["plant_effects"]), r["pivot_counts"]): r
             for r in rows if r["feedback"] == "truth" and r["plant"] == "nominal"}
    for r in rows:
        t = truth.get((r["backend"], r["scenario"], json.dumps(r["plant_effects"]), r["pivot_counts"]))
        if r["feedback"] == "ekf" and t is not None and "track_max_x" in r:
            r["ratio"] = {k: r[f"track_max_{k}"] / t[f"track_max_{k}"] for k in ("x", "y", "alpha")
                          if t.get(f"track_max_{k}")}


def plots(folder: Path, runs: list) -> list:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    files = []
    cases = sorted({(r["backend"], r["scenario"]) for r in runs if "trace" in r})
    for be, sc in cases:
        fig, ax = plt.subplots(figsize=(9, 3.6))
        for pl, color in (("bursts", "C3"), ("bursts fixes", "C0")):
            rs = [r for r in runs if r["backend"] == be and r["scenario"] == sc and r["plant"] == pl and "trace" in r]
            for i, r in enumerate(rs[:5]):
                ax.plot(r["trace"]["t"], 1e3 * np.asarray(r["trace"]["pos_err"]), color=color, lw=0.8, alpha=0.7,
                        label=f"{pl} ({len(rs[:5])} seeds)" if i == 0 else None)
        for tb in BURSTS[sc]:
            ax.axvspan(tb, tb + BURST_S, color="k", alpha=0.12)
        ax.set_xlabel("t (s)")
        ax.set_ylabel("position error (mm)")
        ax.set_title(f"{sc} on {be}, EKF in the loop: estimate - truth with slip bursts (grey), with and without "
                     f"a {FIX_HZ:g} Hz pose fix", fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        p = folder / f"loop_bursts_{sc}_{be.split()[0]}_{be.split()[-2]}.png".replace(" ", "_")
        fig.tight_layout()
        fig.savefig(p, dpi=100)
        plt.close(fig)
        files.append(str(p))
    return files


# ---------------------------------------------------------------------------------------------- markdown
def _mm(v):
    return "-" if v is None else f"{1e3 * v:.2f}"


def _settle(row, key="settle_mean", ns="not_settled"):
    if "events" not in row or not row["events"]:
        return "n/a"
    out = []
    for m, n in zip(row[key], row[ns]):
        out.append(("-" if m is None else f"{m:.2f}") + (f" ({n} not)" if n else ""))
    return ", ".join(out)


def markdown(result: dict) -> str:
    rows = result["rows"]
    main = [r for r in rows if not r["config"] and not r["plant_effects"] and r["pivot_counts"] is None]
    out = ["Tracking through the loop runner; mean over the seeds of each run's maximum (truth feedback, which "
           "sensor noise does not reach, on fewer seeds). Tracking errors are of the true pose against the "
           "reference (x, y in mm, alpha in mrad), ratio = EKF / truth on the same back end; estimation error = "
           "estimate - truth (max); NEES of pose + twist (6 dof) with the two-sided 95 % bounds of that many runs' "
           "average; settle: mean over seeds per event (s; '(n not)': seeds that did not settle within the "
           "event's window).", "",
           "| back end | scenario | feedback | seeds | track x | track y | track alpha | ratio x, y, alpha | est x | "
           "est y | est alpha | NEES (bounds) | settle per event (s) | rejected per run |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted((r for r in main if r["plant"] == "nominal"),
                    key=lambda r: (BACKENDS.index(r["backend"]), SCENARIOS.index(r["scenario"]), r["feedback"] != "truth")):
        ratio = ", ".join(f"{r['ratio'][k]:.2f}" for k in ("x", "y", "alpha")) if "ratio" in r else "-"
        nees_s = f"{r['nees_mean']:.2f} ({r['nees_bounds'][0]:.2f}-{r['nees_bounds'][1]:.2f})" if "nees_mean" in r else "-"
        rej = ", ".join(f"{k} {v:.3g}" for k, v in r.get("rejected", {}).items() if v) or ("none" if "rejected" in r else "-")
        out.append(f"| {r['backend']} | {r['scenario']} | {r['feedback']} | {r['seeds']} | {_mm(r.get('track_max_x'))} | "
                   f"{_mm(r.get('track_max_y'))} | {_mm(r.get('track_max_alpha'))} | {ratio} | "
                   f"{_mm(r.get('est_max_x'))} | {_mm(r.get('est_max_y'))} | {_mm(r.get('est_max_alpha'))} | {nees_s} | "
                   f"{_settle(r)} | {rej} |")
    fed = [r for r in main if r["plant"] == "nominal" and r["feedback"] == "ekf" and r.get("settle_fed_mean")]
    if fed:
        out += ["", "Settle times of the same EKF runs judged on the errors the controller is fed (estimate - "
                    "reference) instead of the true errors:", "", "| back end | scenario | settle per event (s) |",
                "|---|---|---|"]
        for r in sorted(fed, key=lambda r: (BACKENDS.index(r["backend"]), SCENARIOS.index(r["scenario"]))):
            out.append(f"| {r['backend']} | {r['scenario']} | {_settle(r, 'settle_fed_mean', 'settle_fed_not_settled')} |")
    bursts = [r for r in main if r["plant"] != "nominal"]
    if bursts:
        out += ["", f"Slip bursts in the plant (k_slip {BURST_K} rad/(s N m) for {BURST_S} s at each burst time), EKF "
                    f"feedback, with and without a {FIX_HZ:g} Hz motion-capture fix (sigma {FIX_STD[0] * 1e3:g} mm, "
                    f"{FIX_STD[2] * 1e3:g} mrad); mean over seeds:", "",
                "| back end | scenario | plant | seeds | est position max (mm) | worst seed | final | growth per burst (mm) | "
                "track x, y (mm), alpha (mrad) | rejected per run | fixes accepted | completed |",
                "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in sorted(bursts, key=lambda r: (BACKENDS.index(r["backend"]), SCENARIOS.index(r["scenario"]), r["plant"])):
            rej = ", ".join(f"{k} {v:.3g}" for k, v in r.get("rejected", {}).items() if v) or "none"
            steps = ", ".join(f"{v:+.2f}" for v in r.get("burst_steps_mm", []))
            out.append(f"| {r['backend']} | {r['scenario']} | {r['plant']} | {r['seeds']} | {_mm(r.get('est_pos_max'))} | "
                       f"{_mm(r.get('est_pos_max_worst'))} | {_mm(r.get('est_pos_final'))} | {steps} | "
                       f"{_mm(r.get('track_max_x'))}, {_mm(r.get('track_max_y'))}, {_mm(r.get('track_max_alpha'))} | "
                       f"{rej} | {r.get('fixes', 0):g} | {r['completed']}/{r['seeds']} |")
    sweep = [r for r in rows if r["config"] or (r["plant_effects"] and r["pivot_counts"] is None)]
    if sweep:
        out += ["", "The unmodelled-alpha_dd random walk (`angular_disturbance_walk`) on the bus corridor, nominal "
                    f"plant and a plant with torques the model does not know ({', '.join(f'{k} {v:g}' for k, v in UNMODELLED.items())}); "
                    "mean over seeds:", "",
                "| walk (rad/s^2/sqrt(s)) | plant | feedback | track alpha (mrad) | ratio alpha | est position max (mm) | "
                "est alpha max (mrad) | NEES | rejected per run | completed |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r in sorted(sweep, key=lambda r: (r["config"].get("angular_disturbance_walk", 0), bool(r["plant_effects"]),
                                              r["feedback"])):
            rej = ", ".join(f"{k} {v:.3g}" for k, v in r.get("rejected", {}).items() if v) or "none"
            w = r["config"].get("angular_disturbance_walk", "-")
            ratio = f"{r['ratio']['alpha']:.2f}" if "ratio" in r else "-"
            nees_s = f"{r['nees_mean']:.1f}" if "nees_mean" in r else "-"
            out.append(f"| {w} | {'unmodelled torques' if r['plant_effects'] else 'nominal'} | {r['feedback']} | "
                       f"{_mm(r.get('track_max_alpha'))} | {ratio} | {_mm(r.get('est_pos_max'))} | "
                       f"{_mm(r.get('est_max_alpha'))} | {nees_s} | {rej if r['feedback'] == 'ekf' else '-'} | "
                       f"{r['completed']}/{r['seeds']} |")
    piv = [r for r in rows if r["pivot_counts"] is not None]
    if piv:
        out += ["", "Direct 1 kHz corridor with finer pivot encoders (counts per revolution; the EKF's pivot sigma "
                    "follows):", "", "| pivot counts | feedback | track alpha (mrad) | ratio x, y, alpha | est alpha max "
                                     "(mrad) | est position max (mm) |", "|---|---|---|---|---|---|"]
        for r in sorted(piv, key=lambda r: (r["pivot_counts"], r["feedback"] != "truth")):
            ratio = ", ".join(f"{r['ratio'][k]:.2f}" for k in ("x", "y", "alpha")) if "ratio" in r else "-"
            out.append(f"| {r['pivot_counts']} | {r['feedback']} | {_mm(r.get('track_max_alpha'))} | {ratio} | "
                       f"{_mm(r.get('est_max_alpha'))} | {_mm(r.get('est_pos_max'))} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=20, help="seeds of every EKF case (default 20)")
    ap.add_argument("--truth-seeds", type=int, default=3, help="seeds of every truth-feedback case (default 3)")
    ap.add_argument("--seed-list", default=None, metavar="N,N,...",
                    help="only these EKF seeds (e.g. 4: one seed looked at alone; replaces --seeds)")
    ap.add_argument("--backends", default=",".join(BACKENDS))
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    ap.add_argument("--plants", default=",".join(PLANTS))
    ap.add_argument("--sweep", type=int, default=0, metavar="SEEDS", help="the disturbance-walk sweep with SEEDS seeds")
    ap.add_argument("--pivot", type=int, default=0, metavar="SEEDS", help="the finer-pivot-encoder rows with SEEDS seeds")
    ap.add_argument("--no-main", action="store_true", help="only the --sweep / --pivot extras")
    ap.add_argument("--workers", type=int, default=1, help="processes (default 1; the machine is shared)")
    ap.add_argument("--plot", type=Path, default=None, metavar="DIR", help="write the slip-burst plots into DIR")
    ap.add_argument("--save", type=Path, default=None, metavar="MERGED.json",
                    help="with --markdown: write the summary rows of the merged runs (what the tables print)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--markdown", type=Path, nargs="+", default=None, metavar="RESULT.json",
                    help="print the tables of one or more saved --json results (their runs merged; with --plot, "
                         "the plots too)")
    args = ap.parse_args(argv)
    if args.markdown:
        data = [json.loads(f.read_text()) for f in args.markdown]
        runs = [r for d in data for r in d.get("runs", [])]
        if runs:
            rows = summarize(runs)
            attach_ratios(rows)
        else:  # a saved summary (--save)
            rows = [r for d in data for r in d["rows"]]
        if args.plot:
            print("\n".join(plots(args.plot, runs)), file=sys.stderr)
        if args.save:
            args.save.write_text(json.dumps({"rows": rows}))
        print(markdown({"rows": rows}))
        return 0
    seed_list = None
    if args.seed_list is not None:
        try:
            seed_list = [int(v) for v in args.seed_list.split(",")]
        except ValueError:
            ap.error(f"--seed-list: comma-separated whole numbers, got {args.seed_list!r}")
        if any(v < 0 for v in seed_list):
            ap.error(f"--seed-list: seeds are >= 0, got {args.seed_list!r}")
    jobs = []
    if not args.no_main:
        jobs += jobs_main(args.seeds, args.truth_seeds, args.backends.split(","), args.scenarios.split(","),
                          args.plants.split(","), seed_list)
    if args.sweep:
        jobs += jobs_sweep(args.sweep)
    if args.pivot:
        jobs += jobs_pivot(args.pivot)
    runs = run_jobs(jobs, args.workers, "loop")
    rows = summarize(runs)
    attach_ratios(rows)
    result = {"seeds": args.seeds, "truth_seeds": args.truth_seeds, "config": EstimatorConfig.load().to_dict(),
              "rows": rows, "runs": runs}
    if args.plot:
        result["plots"] = plots(args.plot, runs)
    if args.json:
        print(json.dumps(result))
    else:
        print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
