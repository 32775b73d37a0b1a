"""Wall time and CPU of the family study's slowest diagnoses, rerun one at a time (issue 20 item 6: "every
diagnosis <= 10 s" is what a user waits for; the study's own timings come from two workers on a shared machine).

Takes the rows of ``--jsonl`` (``benchmarks/diagnose_independent.py --families``) made by the code in this
checkout (its ``code_hash()``), the ``--count`` slowest by diagnosis CPU, and diagnoses each again through
``diagnose_independent.run_case`` after one untimed warm-up run (numba's kernels loaded), printing wall time, CPU
and the load average before and after. Run it on an idle machine.

    .venv/bin/python benchmarks/diagnose_slowest.py --count 6 [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def slowest(rows: list[dict], version: str, count: int) -> list[dict]:
    """The ``count`` rows of code ``version`` with the largest diagnosis CPU (magic traction curve only)."""
    mine = [r for r in rows if r.get("hash") == version and r.get("traction_curve", "magic") == "magic"]
    return sorted(mine, key=lambda r: -r["diagnose_cpu_s"])[:count]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jsonl", type=Path, default=ROOT / "docs" / "diagnose_families.jsonl",
                    help="the family study's rows (default docs/diagnose_families.jsonl)")
    ap.add_argument("--count", type=int, default=6, help="how many of the slowest rows to rerun (default 6)")
    ap.add_argument("--json", action="store_true", help="one JSON list instead of lines")
    args = ap.parse_args()
    if args.count < 1:
        ap.error(f"--count must be at least 1, got {args.count}")
    try:
        rows = [json.loads(line) for line in args.jsonl.read_text().splitlines() if line.strip()]
    except (OSError, ValueError) as e:
        print(f"diagnose_slowest: error: {args.jsonl}: {e}", file=sys.stderr)
        return 2
    import diagnose_independent as di

    version = di.code_hash()
    chosen = slowest(rows, version, args.count)
    if not chosen:
        print(f"diagnose_slowest: error: {args.jsonl} has no rows of this code version ({version}): run the family "
              "study first", file=sys.stderr)
        return 2
    di.run_case("none", 0)  # warm-up: numba's kernels loaded, not timed
    out = []
    for r in chosen:
        load0 = os.getloadavg()[0]
        got = di.run_case(di.magnitude_case(r["case"], r["magnitude"]), r["rep"], None, di.DURATION, r["family"],
                          fisher=True)  # scored as the study scores
        row = {"case": r["case"], "magnitude": r["magnitude"], "rep": r["rep"], "family": r["family"],
               "study_cpu_s": round(r["diagnose_cpu_s"], 2), "wall_s": round(got["diagnose_s"], 2),
               "cpu_s": round(got["diagnose_cpu_s"], 2), "right": got["right"],
               "load": [round(load0, 2), round(os.getloadavg()[0], 2)]}
        out.append(row)
        if not args.json:
            print(f"{r['family']} {r['case']} x{r['magnitude']:g} #{r['rep']}: wall {row['wall_s']:.1f} s, CPU "
                  f"{row['cpu_s']:.1f} s (study {row['study_cpu_s']:.1f} s), {'right' if row['right'] else 'wrong'}, "
                  f"load {row['load'][0]:.1f} -> {row['load'][1]:.1f}", flush=True)
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
