"""Time ``diagnose`` on one 10 s, 100 Hz recording (target <= 60 s on 2 cores).

Cases: a hidden Coulomb wheel friction (found -> nested fits + refit) and a negative
control (no effect), each a 10 s multisine floor recording with a 10 s held-out
tracking run. The numba compile (cached after the first run) is timed separately.
Writes the table under ``## Diagnose`` in docs/performance.md.

    .venv/bin/python benchmarks/diagnose.py [--repeats 2]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--doc", type=Path, default=ROOT / "docs" / "performance.md")
    args = ap.parse_args()
    from otbot_hw.diagnose.data import from_recording
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.params import nominal
    from otbot_hw.simulation.concealed import concealed_recording

    P = nominal()
    import subprocess
    import tempfile

    code = ("import time; t = time.perf_counter()\n"
            "from otbot_hw.params import nominal\nfrom otbot_hw.diagnose.data import from_recording\n"
            "from otbot_hw.diagnose.diagnosis import diagnose\nfrom otbot_hw.simulation.concealed import concealed_recording\n"
            "P = nominal(); d = [from_recording(concealed_recording(P, {}, 'multisine', 1.0, seed=0), 'w')]\n"
            "diagnose(d, P); print(time.perf_counter() - t)")
    with tempfile.TemporaryDirectory() as cache:
        cold = float(subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                                    env={**os.environ, "NUMBA_CACHE_DIR": cache}, check=True).stdout.split()[-1])
    t0 = time.perf_counter()
    warm = [from_recording(concealed_recording(P, {}, "multisine", 1.0, seed=0), "warm")]
    diagnose(warm, P)
    warmup = time.perf_counter() - t0
    rows = []
    for label, values in (("Coulomb wheel friction hidden (c_w = 0.3 N m)", {"c_w": 0.3}),
                          ("negative control (no effect)", {})):
        times, verdict = [], ""
        for rep in range(args.repeats):
            fit = [from_recording(concealed_recording(P, values, "multisine", 10.0, seed=rep + 1), "fit")]
            held = [from_recording(concealed_recording(P, values, "tracking", 10.0, seed=rep + 40), "held")]
            t = time.perf_counter()
            r = diagnose(fit, P, held)
            times.append(time.perf_counter() - t)
            verdict = r["verdict"]
            print(f"[bench] {label}: {times[-1]:.1f} s -- {verdict}", file=sys.stderr, flush=True)
        rows.append((label, min(times), max(times), verdict))
    cpu = f"{os.cpu_count()} CPU(s), {platform.processor() or platform.machine()}, Python {platform.python_version()}"
    load = os.getloadavg()[0]
    lines = ["## Diagnose", "", "Reproduce: `.venv/bin/python benchmarks/diagnose.py --repeats 3` (rewrites this section).", "",
             "`benchmarks/diagnose.py`: `diagnose()` on one 10 s, 100 Hz floor recording (1001 samples, multisine "
             "torques) with one 10 s held-out recording; nominal fit, locate, screening, nested fits, refit and "
             f"before/after statistics, no plots. Machine: {cpu}; load average {load:.1f} at the end (other jobs "
             "share the machine). Target: <= 60 s on 2 cores.", "",
             "| case | fastest (s) | slowest (s) | verdict |", "|---|---|---|---|"]
    lines += [f"| {a} | {b:.1f} | {c:.1f} | {d} |" for a, b, c, d in rows]
    lines += ["", f"First call in a fresh process with the numba cache in place: {warmup:.1f} s; with an empty "
              f"cache (fresh checkout: compiling the extended model and residual kernels): {cold:.1f} s.", ""]
    block = "\n".join(lines)
    text = args.doc.read_text() if args.doc.exists() else "# Performance\n\n"
    if "## Diagnose" in text:
        a = text.index("## Diagnose")
        b = text.find("\n## ", a + 5)
        text = text[:a] + block + (text[b + 1:] if b >= 0 else "")
    else:
        text = text.rstrip("\n") + "\n\n" + block
    args.doc.write_text(text)
    print(json.dumps({"rows": [{"case": a, "fastest_s": b, "slowest_s": c} for a, b, c, _ in rows],
                      "warmup_s": warmup, "cold_start_s": cold}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
