"""Confusion study of ``otbot diagnose``: every catalog effect x magnitudes x seeds, plus negative controls.

For each case the simulator hides one effect (``sim/concealed.py``) in a fitting set (10 s
multisine on the floor + 4 s stand run, 100 Hz, paper noise) and a held-out set (10 s
tracking-like run); the diagnosis sees only commands, encoders and IMU. Recorded per case:
the named effect(s), the ambiguous groups, the magnitude error of the true effect's
parameters, the held-out fit before/after and the nominal fit's fitting-data fit % (the
concealment check). Writes ``docs/diagnose.md`` (section between the STUDY markers) and a
JSON file with every case.

    .venv/bin/python benchmarks/diagnose_confusion.py [--seeds 2] [--workers 2] [--quick]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def run_case(effect_name: str, magnitude_index: int, seed: int, scale: float = 1.0) -> dict:
    from otbot_hw.diagnose import catalog as cat
    from otbot_hw.diagnose.data import from_recording
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.params import nominal
    from otbot_hw.simulation.concealed import concealed_recording

    params = nominal()
    values = {} if effect_name == "none" else dict(cat.effect(effect_name).magnitudes[magnitude_index])
    # scale the effect's size (not the Stribeck speed, which is a shape parameter); limits (saturation,
    # traction) clip less of the 4 N m peaks
    limits = ("u_max", "u_max_r", "u_max_l", "u_max_p", "t_trac")
    values = {k: (v if k == "v_s" else (4.0 - (4.0 - v) * scale if k in limits else v * scale))
              for k, v in values.items()}
    fit = [from_recording(concealed_recording(params, values, "multisine", 10.0, seed=100 * seed + 1), "multisine"),
           from_recording(concealed_recording(params, values, "stand", 4.0, seed=100 * seed + 2), "stand")]
    held = [from_recording(concealed_recording(params, values, "tracking", 10.0, seed=100 * seed + 3), "tracking")]
    t0 = time.perf_counter()
    try:
        r = diagnose(fit, params, held)
    except Exception as exc:  # recorded, not hidden: shows up as 'error' in the table
        return {"true": effect_name, "magnitude": magnitude_index, "seed": seed, "error": repr(exc)}
    named = [e["name"] for e in r["effects"]]
    amb = [[c["name"] for c in g["candidates"]] for g in r["ambiguous"]]
    rel = None
    est = None
    src = None
    if effect_name != "none":
        if effect_name in named:
            src = next(e for e in r["effects"] if e["name"] == effect_name)["parameters"]
        else:
            for g in r["ambiguous"]:
                for c in g["candidates"]:
                    if c["name"] == effect_name:
                        src = c["parameters"]
        if src:
            est = {k: v["value"] for k, v in src.items()}
            size = max(abs(v) for v in values.values())  # a zero true value is judged against the effect's size
            rel = max(abs(est[k] - v) / (abs(v) if v != 0 else size) for k, v in values.items())
    hb, ha = r["fit_before"]["heldout"], r["fit_after"]["heldout"]
    return {"true": effect_name, "magnitude": magnitude_index, "seed": seed, "values": values, "named": named,
            "ambiguous": amb, "estimate": est, "max_rel_error": rel,
            "nominal_fit_percent": {c: v["fit_percent"] for c, v in r["fit_before"]["fitting"].items()},
            "heldout_before": {c: v["fit_percent"] for c, v in hb.items()},
            "heldout_after": {c: v["fit_percent"] for c, v in ha.items()},
            "elapsed_s": time.perf_counter() - t0}


def run_job(job: tuple) -> dict:
    """``run_case(effect, magnitude_index, seed, scale)`` for the executor (one picklable item)."""
    return run_case(*job)


def label(case: dict) -> str:
    if "error" in case:
        return "error"
    if case["named"]:
        return "+".join(case["named"])
    if case["ambiguous"]:
        return "ambiguous{" + ",".join(sorted(case["ambiguous"][0])) + "}"
    return "none"


def write_doc(cases: list[dict], path: Path, seconds: float, workers: int, scale: float = 1.0) -> None:
    from otbot_hw.diagnose.catalog import CATALOG

    names = [e.name for e in CATALOG] + ["none"]
    tag = "STUDY" if scale == 1.0 else f"STUDY_x{scale:g}"
    lines = [f"<!-- {tag}:BEGIN (written by benchmarks/diagnose_confusion.py) -->", "",
             *([f"**Detection limit: every effect at {scale:g} x its catalog magnitudes** "
                f"(saturation: {scale:g} x the clipped part of the 4 N m wheel peaks).", ""] if scale != 1.0 else []),
             f"{len(cases)} cases, {seconds / 60:.1f} min on {workers} worker process(es). Fitting set: 10 s multisine "
             "on the floor + 4 s stand run; held-out: 10 s tracking-like run; 100 Hz, paper noise (IMU 13.7e-3, "
             "encoder rates 0.01 rad/s). Magnitudes: the catalog `magnitudes` run (x the scale above); seeds "
             f"{sorted({c['seed'] for c in cases})}.", "",
             "### Confusion table (true effect -> what the diagnosis reported)", "",
             "| true effect | cases | named correctly | ... plus an extra effect | in an ambiguous group | named other | "
             "nothing found | error | magnitude within 20 % | reported (count) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for n in names:
        cs = [c for c in cases if c["true"] == n]
        if not cs:
            continue
        ok = sum(1 for c in cs if "error" not in c and n in c["named"])
        extra = sum(1 for c in cs if "error" not in c and n in c["named"] and len(c["named"]) > 1)
        amb = sum(1 for c in cs if "error" not in c and n not in c["named"] and any(n in g for g in c["ambiguous"]))
        err = sum(1 for c in cs if "error" in c)
        none = sum(1 for c in cs if "error" not in c and not c["named"] and not c["ambiguous"])
        other = len(cs) - ok - amb - err - none
        mag = sum(1 for c in cs if c.get("max_rel_error") is not None and c["max_rel_error"] <= 0.2)
        counts: dict[str, int] = {}
        for c in cs:
            counts[label(c)] = counts.get(label(c), 0) + 1
        rep = ", ".join(f"{k} ({v})" for k, v in sorted(counts.items(), key=lambda kv: -kv[1]))
        mag_txt = "n/a" if n == "none" else f"{mag}/{len(cs)}"
        lines.append(f"| {n} | {len(cs)} | {ok if n != 'none' else '-'} | {extra if n != 'none' else '-'} | "
                     f"{amb} | {other} | {none} | {err} | "
                     f"{mag_txt} | {rep} |")
    lines += ["", "### Concealment and held-out improvement (medians over cases)", "",
              "| true effect | nominal fit % on fitting data (min over channels) | held-out fit % before -> after "
              "(worst channel before) | median time (s) |", "|---|---|---|---|"]
    for n in names:
        cs = [c for c in cases if c["true"] == n and "error" not in c]
        if not cs:
            continue
        conc = np.median([min(c["nominal_fit_percent"].values()) for c in cs])
        worst = [min(c["heldout_before"], key=c["heldout_before"].get) for c in cs]
        hb = np.median([c["heldout_before"][w] for c, w in zip(cs, worst)])
        ha = np.median([c["heldout_after"][w] for c, w in zip(cs, worst)])
        tm = np.median([c["elapsed_s"] for c in cs])
        lines.append(f"| {n} | {conc:.1f} | {hb:.1f} -> {ha:.1f} | {tm:.0f} |")
    lines += ["", f"<!-- {tag}:END -->"]
    block = "\n".join(lines)
    text = path.read_text() if path.exists() else ""
    if f"<!-- {tag}:BEGIN" in text:
        a = text.index(f"<!-- {tag}:BEGIN")
        b = text.index(f"<!-- {tag}:END -->") + len(f"<!-- {tag}:END -->")
        text = text[:a] + block + text[b:]
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    path.write_text(text)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=2, help="noise/excitation seeds per effect and magnitude")
    ap.add_argument("--negatives", type=int, default=4, help="negative-control cases (no effect)")
    ap.add_argument("--workers", type=int, default=2, help="local worker processes")
    ap.add_argument("--scheduler", default=None, metavar="ADDRESS",
                    help="run the cases on a Dask distributed scheduler instead (tcp://host:8786)")
    ap.add_argument("--quick", action="store_true", help="first magnitude, one seed (smoke run)")
    ap.add_argument("--doc", type=Path, default=ROOT / "docs" / "diagnose.md")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "diagnose_confusion.json")
    ap.add_argument("--effects", default="", help="comma-separated subset of catalog effects")
    ap.add_argument("--scale", type=float, default=1.0,
                    help="multiply every effect size by this (e.g. 0.33 to probe detection limits); "
                         "written to its own section")
    ap.add_argument("--magnitudes", default="0,1", help="which catalog magnitudes (indices) to run")
    ap.add_argument("--from-json", type=Path, default=None,
                    help="rewrite the doc section from a saved case file instead of running")
    ap.add_argument("--seconds", type=float, default=0.0, help="with --from-json: the run's duration to report")
    args = ap.parse_args()
    from otbot_hw.diagnose.catalog import CATALOG

    if args.from_json:
        cases = json.loads(args.from_json.read_text())
        write_doc(cases, args.doc, args.seconds, args.workers, args.scale)
        return 0
    effects = [e.name for e in CATALOG if not args.effects or e.name in args.effects.split(",")]
    mags = (0,) if args.quick else tuple(int(m) for m in args.magnitudes.split(","))
    seeds = range(1 if args.quick else args.seeds)
    jobs = [(e, m, s) for e in effects for m in mags for s in seeds]
    jobs += [("none", 0, 50 + s) for s in range(1 if args.quick else args.negatives)]
    t0 = time.perf_counter()
    from otbot_hw.identification.executors import make_executor

    def report(done: int, total: int) -> None:
        print(f"[confusion] {done}/{total} cases ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)

    with make_executor(args.scheduler, args.workers) as ex:  # the executor the fleet and sweeps use
        print(f"[confusion] {len(jobs)} cases on {ex.describe()}", file=sys.stderr, flush=True)
        cases = ex.map(run_job, [(*j, args.scale) for j in jobs], progress=report)
    for c in cases:
        print(f"[confusion] true={c['true']} mag={c['magnitude']} seed={c['seed']} -> {label(c)} "
              f"rel.err={c.get('max_rel_error')}", file=sys.stderr)
    cases.sort(key=lambda c: (c["true"], c["magnitude"], c["seed"]))
    args.out.write_text(json.dumps(cases, indent=1, default=float))
    write_doc(cases, args.doc, time.perf_counter() - t0, args.workers, args.scale)
    print(json.dumps({"cases": len(cases), "seconds": time.perf_counter() - t0}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
