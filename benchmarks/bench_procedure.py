"""The whole bench procedure through the simulated bus on robots whose every parameter differs from the file.

Run: ``nice -n 10 .venv/bin/python benchmarks/bench_procedure.py [--seeds 50] [--variants default,paper,paper-wide]
[--no-track] [--out-dir DIR] [--json out.json]``

For each seed a robot is drawn by ``identification.study.every_parameter_robot`` (issue 21: every mass,
inertia and friction +-30 %, the unloaded platform's included, every centre of mass moved up to 5 cm,
a 0-300 kg load within 0.2 m of the pivot with its own inertia 0-5 kg m^2) and the procedure runs as a
user runs it: ``otbot bench --bus sim --yes --json --sim-params ROBOT.yaml --sim-load KG@X,Y,I --seed S``
(in this process, through ``otbot_hw.cli.main``): the CANopen drivers over the virtual bus to the
simulated plant in lockstep, the simulated operator changing fixture and load and weighing the
unloaded platform, the checks, the supervised runs with the brake, the identification with gates
and redo, the diagnosis. The start parameters are the file's (config/otbot.yaml): the robot is
unknown. Variants:

* ``default``: no option (designed excitation, default limits, diagnosis): the main row;
* ``paper``: ``--excitation paper``, default limits: how often the paper's torques leave them;
* ``paper-wide``: the paper's torques with every speed limit and the free area widened 1.5x (a
  config copy), without the diagnosis: the sigma the paper's excitation gives, for the comparison.

After a passed ``default`` procedure (unless ``--no-track``) the corridor is tracked on the loaded
robot (``otbot track corridor --sim``) with the identified ``params.yaml`` and with the true
parameters; the ratio of their RMS position errors is the tracking row (target <= 1.1).

Tables (docs/identification.md, section *The bench procedure*): outcomes per variant; for each
parameter and identified combination the fraction of robots whose final estimate is within 3 reported
sigma (target >= 95 %), the RMS of error / sigma, the mean sigma; tracking; the procedure's wall and CPU
time (target <= 30 s CPU). Trials are written to ``--json`` after each robot (a study cut short keeps
what it ran).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from otbot_hw.identification.uncertainty import SESSION_PARAMS  # noqa: E402

VARIANTS = {
    "default": [],
    "paper": ["--excitation", "paper"],
    "paper-wide": ["--excitation", "paper", "--no-diagnose"],
}
#: what the coverage table lists beyond SESSION_PARAMS: the unloaded platform and the identified combinations
EXTRA = ("m_p0", "x_F0", "y_F0", "m_c+m_p0", "m_p-m_p0")
WIDEN = 1.5


def wide_config(folder: Path) -> Path:
    """A copy of config/robot.yaml with the experiment's speed limits and free area widened WIDEN times
    (EDS paths made absolute, so the copy works from another folder)."""
    import yaml

    data = yaml.safe_load((ROOT / "config" / "robot.yaml").read_text())
    for sec in ("drives", "pivot_encoder"):
        data[sec]["eds"] = str(ROOT / "config" / data[sec]["eds"])
    for k in ("wheel_speed", "pivot_speed", "platform_speed", "travel_radius"):
        data["experiment_limits"][k]["value"] *= WIDEN
    for k in ("max_wheel_rate", "max_pivot_rate"):
        data["safety"][k]["value"] *= WIDEN
    path = folder / "robot-wide.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _cli(argv: list[str]) -> tuple[int, dict, str]:
    from otbot_hw.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(argv)
        except SystemExit as exc:
            rc = exc.code
    text = out.getvalue().strip()
    try:
        res = json.loads(text.splitlines()[-1]) if text else {}
    except ValueError:
        res = {}
    return rc or 0, res, err.getvalue()


def _track(params: Path, plant: Path, seed: int) -> dict:
    """The corridor tracked on ``plant`` with the controller's ``params``: RMS position error (m, up to a
    stop), whether it completed, the fault, whether the feasibility check found the corridor feasible."""
    rc, res, _ = _cli(["track", "corridor", "--sim", "--params", str(params), "--plant-params", str(plant),
                       "--seed", str(seed), "--json"])
    rms = res.get("rms_error")
    return {"rms": float(np.hypot(rms["x"], rms["y"])) if rms else None, "completed": rc == 0,
            "fault": (res.get("fault") or {}).get("kind"), "feasible": (res.get("feasibility") or {}).get("feasible")}


def track_pair(session: Path, plant: Path, seed: int) -> dict:
    return {"identified": _track(session / "params.yaml", plant, seed), "true": _track(plant, plant, seed)}


def track_only(folder: Path, seeds: range, out: Path) -> list[dict]:
    """Tracking for the sessions a ``--no-track`` study left in ``folder`` (``default-S/params.yaml``)."""
    from otbot_hw.identification.study import every_parameter_robot

    rows = []
    for seed in seeds:
        session = folder / f"default-{seed}"
        if not (session / "params.yaml").is_file():
            continue
        unloaded, loaded, load = every_parameter_robot(seed)
        plant = folder / f"robot-{seed}-loaded.yaml"
        (loaded if load["mass"] >= 0.5 else unloaded).save(plant, header=f"every_parameter_robot({seed}), loaded")
        row = {"seed": seed, "load": load, "track": track_pair(session, plant, seed)}
        rows.append(row)
        tr = row["track"]
        print(f"[track] seed {seed}: load {load['mass']:.0f} kg, identified {tr['identified']}, true {tr['true']}",
              flush=True)
        out.write_text(json.dumps({"default": rows}, indent=1, default=float))
    return rows


def run_one(seed: int, variant: str, folder: Path, extra: list[str], track: bool = False) -> dict:
    """One procedure; returns the parsed JSON (or the failure) with the truth and the exit code."""
    from otbot_hw.identification.study import every_parameter_robot

    unloaded, loaded, load = every_parameter_robot(seed)
    robot = folder / f"robot-{seed}.yaml"
    unloaded.save(robot, header=f"every_parameter_robot({seed})")
    session = folder / f"{variant}-{seed}"
    argv = ["bench", "--bus", "sim", "--yes", "--json", "--session", str(session), "--sim-params", str(robot),
            *(["--sim-load", f"{load['mass']!r}@{load['x']!r},{load['y']!r},{load['inertia']!r}"]
              if load["mass"] >= 0.5 else []),
            "--seed", str(seed), *VARIANTS[variant], *extra]
    t0, c0 = time.perf_counter(), time.process_time()
    rc, res, err = _cli(argv)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    res.update(seed=seed, variant=variant, rc=rc, wall=wall, cpu=cpu, load=load,
               stderr_tail=err.strip().splitlines()[-1:] if rc else [])
    if track and rc == 0:
        plant = folder / f"robot-{seed}-loaded.yaml"
        (loaded if load["mass"] >= 0.5 else unloaded).save(plant, header=f"every_parameter_robot({seed}), loaded")
        res["track"] = track_pair(session, plant, seed)
    return res


def honesty_table(trials: list[dict]) -> str:
    ok = [t for t in trials if t["rc"] == 0]
    lines = ["| parameter | truth range | within 3 sigma | RMS of error / sigma | largest abs(error) / sigma | mean sigma |",
             "|---|---|---|---|---|---|"]
    for n in SESSION_PARAMS + EXTRA:
        z = np.array([t["error_sigma"][n] for t in ok if (t.get("error_sigma") or {}).get(n) is not None])
        tr = np.array([t["truth"][n] for t in ok if n in (t.get("truth") or {})])
        s = np.array([_entry(t, n)["std"] for t in ok if _entry(t, n) is not None])
        if not len(z):
            continue
        lines.append(f"| {n} | {tr.min():.4g} .. {tr.max():.4g} | {100 * np.mean(np.abs(z) <= 3):.0f} % | "
                     f"{np.sqrt(np.mean(z ** 2)):.2f} | {np.max(np.abs(z)):.2f} | {s.mean():.3g} |")
    return "\n".join(lines)


def _entry(t: dict, n: str) -> dict | None:
    for key in ("parameters", "unloaded_platform", "combinations"):
        if n in (t.get(key) or {}):
            return t[key][n]
    return None


def track_table(trials: list[dict]) -> str:
    """Identified against true parameters on the corridor: the RMS ratio where both completed, and the
    robots whose corridor the true parameters cannot track either (torque-limited)."""
    tr = [t["track"] for t in trials if t.get("track")]
    both = [x for x in tr if x["identified"]["completed"] and x["true"]["completed"]]
    if not tr:
        return "(no tracking runs)"
    r = np.array([x["identified"]["rms"] / x["true"]["rms"] for x in both]) if both else np.array([np.nan])
    ident = np.array([x["identified"]["rms"] for x in both] or [np.nan])
    true = np.array([x["true"]["rms"] for x in both] or [np.nan])
    only_true = sum(x["true"]["completed"] and not x["identified"]["completed"] for x in tr)
    only_ident = sum(x["identified"]["completed"] and not x["true"]["completed"] for x in tr)
    neither = sum(not x["true"]["completed"] and not x["identified"]["completed"] for x in tr)
    return ("| robots | both completed | RMS position error, identified: mean | true: mean | ratio: median | "
            "ratio: max | ratio <= 1.1 | neither completed | only the true one | only the identified one |\n"
            "|---|---|---|---|---|---|---|---|---|---|\n"
            f"| {len(tr)} | {len(both)} | {1000 * ident.mean():.2f} mm | {1000 * true.mean():.2f} mm | "
            f"{np.median(r):.4f} | {r.max():.4f} | {100 * np.mean(r <= 1.1):.0f} % | {neither} | {only_true} | "
            f"{only_ident} |")


def outcome_table(sets: dict[str, list[dict]]) -> str:
    lines = ["| variant | robots | passed | stopped by a limit or fault (exit 1) | refused (exit 2) | redo runs | "
             "reasons |", "|---|---|---|---|---|---|---|"]
    for v, ts in sets.items():
        stopped = [t for t in ts if t["rc"] == 1]
        refused = [t for t in ts if t["rc"] == 2]
        redo = sum(max(0, d["attempts"] - 1) for t in ts if t["rc"] == 0 for d in t["steps"].values())
        why = {}
        for t in stopped + refused:
            text = (t.get("reason") or " ".join(t["stderr_tail"]))
            key = next((k for k in ("joint_rate", "platform_speed", "travel", "limits", "fixture", "at_rest",
                                    "saturation", "identif") if k in text), text[:60])
            why[key] = why.get(key, 0) + 1
        lines.append(f"| {v} | {len(ts)} | {sum(t['rc'] == 0 and t['passed'] for t in ts)} | {len(stopped)} | "
                     f"{len(refused)} | {redo} | {', '.join(f'{k}: {c}' for k, c in why.items()) or '-'} |")
    return "\n".join(lines)


def sigma_table(designed: list[dict], paper: list[dict]) -> str:
    both = sorted({t["seed"] for t in designed if t["rc"] == 0} & {t["seed"] for t in paper if t["rc"] == 0})
    d = {t["seed"]: t for t in designed}
    p = {t["seed"]: t for t in paper}
    lines = [f"| parameter | paper: mean sigma | designed: mean sigma | sigma ratio designed / paper | "
             f"(both on the same {len(both)} robots) |", "|---|---|---|---|---|"]
    for n in SESSION_PARAMS:
        sp = np.array([p[s]["parameters"][n]["std"] for s in both])
        sd = np.array([d[s]["parameters"][n]["std"] for s in both])
        if len(both):
            lines.append(f"| {n} | {sp.mean():.3g} | {sd.mean():.3g} | {sd.mean() / sp.mean():.2f} | |")
    return "\n".join(lines)


def time_table(sets: dict[str, list[dict]]) -> str:
    lines = ["| variant | procedure wall time: mean | max | CPU time: mean | max | of which: bus runs (wall) | "
             "identification | diagnosis | robot time |", "|---|---|---|---|---|---|---|---|---|"]
    for v, ts in sets.items():
        ok = [t for t in ts if t["rc"] == 0]
        if not ok:
            continue
        w = np.array([t["wall"] for t in ok])
        c = np.array([t["cpu"] for t in ok])
        tm = {k: np.mean([t["timing"][k] for t in ok]) for k in ("runs_wall_time", "identification_wall_time",
                                                                   "diagnosis_wall_time", "robot_time")}
        lines.append(f"| {v} | {w.mean():.1f} s | {w.max():.1f} s | {c.mean():.1f} s | {c.max():.1f} s | "
                     f"{tm['runs_wall_time']:.1f} s | {tm['identification_wall_time']:.1f} s | "
                     f"{tm['diagnosis_wall_time']:.1f} s | {tm['robot_time']:.1f} s |")
    return "\n".join(lines)


def scale_table(sets: dict[str, list[dict]]) -> str:
    """How often the designed torques were scaled to the robot (the ``robot_limits`` check's value)."""
    lines = ["| variant | step | robots with the check | scaled down | smallest scale | mean scale |",
             "|---|---|---|---|---|---|"]
    for v, ts in sets.items():
        for step in ("chassis", "platform"):
            k = [c["value"] for t in ts for c in (((t.get("steps") or {}).get(step) or {}).get("checks") or [])
                 if c["name"] == "robot_limits" and c.get("value") is not None]
            if k:
                k = np.array(k)
                lines.append(f"| {v} | {step} | {len(k)} | {int(np.sum(k < 1.0))} | {k.min():.3f} | {k.mean():.3f} |")
    return "\n".join(lines)


def print_tables(sets: dict[str, list[dict]]) -> None:
    print("## Outcomes\n")
    print(outcome_table(sets))
    print("\n## Designed torques fitted to the robot (robot_limits)\n")
    print(scale_table(sets))
    for v, ts in sets.items():
        print(f"\n## Honest uncertainty through the bus: {v}\n")
        print(honesty_table(ts))
    if "default" in sets and "paper-wide" in sets:
        print("\n## Designed against the paper's excitation, measured through the bus\n")
        print(sigma_table(sets["default"], sets["paper-wide"]))
    if "default" in sets:
        print("\n## Tracking the corridor with the identified parameters\n")
        print(track_table(sets["default"]))
    print("\n## Time per procedure\n")
    print(time_table(sets))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=50, help="robots per variant (default 50)")
    ap.add_argument("--first-seed", type=int, default=0, help="first seed (default 0)")
    ap.add_argument("--variants", default="default", help="comma-separated, of " + ", ".join(VARIANTS)
                    + " (default: default)")
    ap.add_argument("--no-track", action="store_true", help="skip the corridor tracking comparison")
    ap.add_argument("--track-only", type=Path, default=None, metavar="DIR",
                    help="only the tracking comparison, for the sessions a --no-track study kept in DIR (--out-dir)")
    ap.add_argument("--out-dir", type=Path, default=None, help="keep the sessions here (default a temporary folder)")
    ap.add_argument("--json", type=Path, default=None, help="write every trial to this JSON file")
    ap.add_argument("--tables", type=Path, nargs="+", default=None, metavar="JSON",
                    help="print the tables of earlier runs' --json files (merged) instead of running")
    args = ap.parse_args(argv)
    if args.tables:
        sets = {}
        for f in args.tables:
            for v, ts in json.loads(f.read_text()).items():
                sets.setdefault(v, []).extend(ts)
        print_tables(sets)
        return 0
    if args.track_only:
        rows = track_only(args.track_only, range(args.first_seed, args.first_seed + args.seeds),
                          args.json or args.track_only / "track.json")
        print(track_table(rows))
        return 0
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    tmp = None
    if args.out_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench-procedure-")
        folder = Path(tmp.name)
    else:
        folder = args.out_dir
        folder.mkdir(parents=True, exist_ok=True)
    extra = {"paper-wide": ["--config", str(wide_config(folder))]}
    sets: dict[str, list[dict]] = {}
    t0 = time.perf_counter()
    for v in variants:
        sets[v] = []
        for s in range(args.first_seed, args.first_seed + args.seeds):
            r = run_one(s, v, folder, extra.get(v, []), track=v == "default" and not args.no_track)
            sets[v].append(r)
            if args.json:
                args.json.write_text(json.dumps(sets, indent=1, default=float))
            es = r.get("error_sigma") or {}
            worst = max((abs(x) for x in es.values() if x is not None), default=float("nan"))
            tr = r.get("track") or {}
            print(f"[{v}] seed {s}: exit {r['rc']}, {r['wall']:.1f} s, {r['cpu']:.1f} s CPU, largest |error|/sigma "
                  f"{worst:.2f}" + (f", tracking {tr['identified']} / {tr['true']}" if tr else "")
                  + (f" ({r.get('reason') or ' '.join(r['stderr_tail'])})"[:200] if r["rc"] else ""), flush=True)
    print(f"\n{sum(len(t) for t in sets.values())} procedures in {time.perf_counter() - t0:.0f} s\n")
    print_tables(sets)
    if args.json:
        args.json.write_text(json.dumps(sets, indent=1, default=float))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
