"""Discovery beyond the catalog on the independent robot (``benchmarks/independent_robot.py``): four laws the
catalog does not have, and clean runs for false discoveries.

Laws (each a fitting run of random piecewise-constant torques and a held-out run of random smooth torques,
10 s at 100 Hz, paper noise, the robot's own dynamics and effect forms):

* ``linear_drag``: a force -15 v N at the pivot (the catalog has only quadratic air drag);
* ``cogging``: -0.3 sin(4 phi_r) N m on the right wheel motor;
* ``pivot_dead_zone``: the pivot drive delivers nothing below 0.5 N m, u - 0.5 sgn(u) above;
* ``traction_limit``: wheel traction T x / sqrt(1 + x^2), x = sigma / (k T), k = 0.02 rad/(s N m), T = 3 N m
  (the catalog's tanh traction law with quasi-static slip does not fit this curve: "model inadequate").

A law counts as *discovered* when the diagnosis names it (the right kind on the right joint) with its main
parameter within 20 % after the simulation refit and the held-out re-simulation improves. Clean runs
(``--clean N`` seed pairs, no effect): a false discovery is any law named -- by the full diagnosis, and by
the discovery step (regression, then the simulation refit that drops what it takes back) run on the nominal
fit even when the model is adequate (the diagnosis would not run it); the regression's own picks are
counted too (``forced_regression_laws``).

    .venv/bin/python benchmarks/diagnose_discovery.py [--seeds 1] [--clean 10] [--workers 2] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import independent_robot as ir  # noqa: E402

#: label: (world, expected law kind, joint, main entry, true value)
LAWS = {
    "linear_drag": ({"lin_drag": 15.0}, "linear_drag", "platform", "c_lin", 15.0),
    "cogging": ({"cogging": (0.3, 4)}, "cogging", "r", "cog_r", 0.3),
    "pivot_dead_zone": ({"pivot_deadzone": 0.5}, "dead_zone", "p", "dz_p", 0.5),
    "traction_limit": ({"slip_k": 0.02, "slip_tmax": 3.0}, "soft_limit", "r", "ts_r", 3.0),
}
TOLERANCE = 0.2


def _record(folder: Path, label: str, world: dict, rep: int) -> list[Path]:
    paths = []
    for kind, seed in (("piecewise", 31 + 2 * rep), ("smooth", 32 + 2 * rep)):
        p = folder / f"{label}_{rep}_{kind}.mcap"
        if not p.exists():
            ir.record(p, ir.World(**world), kind, seed)
        paths.append(p)
    return paths


def run(label: str, rep: int, keep: Path | None) -> dict:
    """Record (or reuse in ``keep``) and diagnose one case; clean cases also run the discovery step alone."""
    from otbot_hw.diagnose.data import load
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.diagnose.discover import discover_laws
    from otbot_hw.diagnose.refit import refit
    from otbot_hw.diagnose.select import free_nominal
    from otbot_hw.model.effects import ExtendedModel
    from otbot_hw.params import nominal

    world = LAWS[label][0] if label in LAWS else {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(keep or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        fit_p, hold_p = _record(folder, label, world, rep)
        fit, hold = load([fit_p]), load([hold_p])
        t0 = time.process_time()
        r = diagnose(fit, nominal(), hold)
        cpu = time.process_time() - t0
        forced = None
        if label == "clean" and r["model_adequate"]:  # the discovery step as the diagnosis runs it, forced
            base = refit(fit, ExtendedModel.paper(nominal()), free_nominal(fit))
            forced = discover_laws(fit, hold, base, free_nominal(fit), nominal())[0]
    d = r.get("discovered") or {}
    laws = d.get("laws", [])
    out = {"case": label, "rep": rep, "adequate": r["model_adequate"],
           "laws": [{"law": lw["law"], "kind": lw["kind"], "joint": lw["joint"],
                     "refit": {k: v for k, v in (lw.get("refit") or {}).items()}} for lw in laws],
           "dropped": [lw["law"] for lw in d.get("dropped", [])],
           "closest": d.get("tried", [])[:3], "resimulation": d.get("resimulation"),
           "adequate_with_laws": d.get("adequate_with_laws"), "improves": d.get("improves"),
           "discovery_s": d.get("elapsed_s"), "discovery_cpu_s": d.get("cpu_s"), "regression_s": d.get("regression_s"),
           "diagnose_s": r["elapsed_s"], "diagnose_cpu_s": cpu,
           "named_effects": [e["name"] for e in r["effects"]]}
    if label in LAWS:
        _, kind, joint, main, truth = LAWS[label]
        hit = [lw for lw in laws if lw["kind"] == kind and lw["joint"] == joint]
        val = hit[0]["refit"][main] if hit else None
        out["estimate"] = val
        out["error"] = (val["value"] - truth) / truth if val else None
        out["discovered"] = bool(hit) and abs(out["error"]) <= TOLERANCE and bool(d.get("improves"))
    else:
        out["false_laws"] = len(laws) + len(r["effects"]) + len(r["ambiguous"])
        out["forced_laws"] = [lw["law"] for lw in (forced or {}).get("laws", [])]
        out["forced_regression_laws"] = out["forced_laws"] + [lw["law"] for lw in (forced or {}).get("dropped", [])]
    return out


def table(rows: list[dict]) -> list[str]:
    lines = ["| law (truth) | discovered (refit by simulation, value ± HAC std) | picked by the regression, dropped by the simulation | "
             "held-out re-simulation, RMS / noise before → after (w_r, w_l, w_p, a_x, a_y, g_z) | "
             "model adequate with the law | verdict | discovery / whole diagnosis (s) |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["case"] == "clean":
            continue
        laws = "; ".join(f"{lw['law']}: " + ", ".join(f"{k} = {v['value']:.4g}" + (f" ± {v['std']:.2g}" if v.get("std")
                                                                                   else "") for k, v in lw["refit"].items()
                                                    if not k.startswith("cogn"))
                         for lw in r["laws"]) or "none"
        if r["case"] in LAWS and not r["laws"]:
            laws += " (closest: " + ", ".join(f"{t['law']} {100 * t['heldout_gain']:+.0f} % held-out, p "
                                              f"{t['p_value']:.2g}" for t in r["closest"]) + ")"
        rs = r.get("resimulation")
        res = " / ".join(f"{v['before_noise_ratio']:.2g} → {v['after_noise_ratio']:.2g}"
                         for v in rs["channels"].values()) if rs else "-"
        verdict = "discovered" if r.get("discovered") else "inadequate, not named" if not r["laws"] else "wrong law"
        if r["adequate"]:
            verdict = "adequate (catalog: " + (", ".join(r["named_effects"]) or "nothing") + ")"
        lines.append(f"| {r['case']} #{r['rep']} ({LAWS[r['case']][3]} = {LAWS[r['case']][4]:g}) | {laws} | "
                     f"{', '.join(r['dropped']) or '-'} | {res} | {r['adequate_with_laws']} | {verdict} | "
                     f"{(r['discovery_s'] or 0):.1f} / {r['diagnose_s']:.1f} |")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=1, help="seed pairs per law (default 1)")
    ap.add_argument("--clean", type=int, default=10, help="clean seed pairs (default 10)")
    ap.add_argument("--laws", default=",".join(LAWS), help="comma-separated laws (default all four)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--recordings", type=Path, default=None, help="keep (and reuse) the recordings here")
    ap.add_argument("--json", action="store_true", help="print the results as JSON")
    args = ap.parse_args()
    jobs = [(lab, rep) for lab in args.laws.split(",") if lab for rep in range(args.seeds)]
    jobs += [("clean", rep) for rep in range(args.clean)]
    rows = []
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as ex:
        futs = {ex.submit(run, lab, rep, args.recordings): (lab, rep) for lab, rep in jobs}
        for f in as_completed(futs):
            try:
                rows.append(f.result())
            except Exception as exc:  # noqa: BLE001 - reported, the others go on
                rows.append({"case": futs[f][0], "rep": futs[f][1], "failed": repr(exc)})
            r = rows[-1]
            print(f"[discovery] {time.perf_counter() - t0:5.0f} s {r['case']} #{r['rep']}: "
                  + (r.get("failed") or f"laws {[lw['law'] for lw in r['laws']]} adequate {r['adequate']}"),
                  file=sys.stderr, flush=True)
    failed = [r for r in rows if "failed" in r]
    rows = sorted((r for r in rows if "failed" not in r), key=lambda r: (r["case"], r["rep"]))
    law_rows = [r for r in rows if r["case"] in LAWS]
    clean = [r for r in rows if r["case"] == "clean"]
    summary = {"laws_discovered": sorted({r["case"] for r in law_rows if r.get("discovered")}),
               "law_runs": len(law_rows), "law_runs_discovered": sum(bool(r.get("discovered")) for r in law_rows),
               "clean_runs": len(clean), "clean_false_findings": sum(r["false_laws"] > 0 for r in clean),
               "clean_forced_false_laws": sum(bool(r["forced_laws"]) for r in clean),
               "clean_forced_regression_picks": sum(bool(r["forced_regression_laws"]) for r in clean),
               "worst_diagnose_s": max((r["diagnose_s"] for r in rows), default=None),
               "worst_discovery_s": max((r["discovery_s"] or 0 for r in rows), default=None),
               "failed": failed}
    if args.json:
        print(json.dumps({"summary": summary, "runs": rows}, indent=1, default=float))
    else:
        print("\n".join(table(law_rows)))
        print(json.dumps(summary, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
