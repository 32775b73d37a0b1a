"""CPU per recording sample: ``RecordingWriter.write_sample`` on the daemon's sample shape (command,
joints, IMU, truth, estimate, reference: six JSON messages per sample, events registered), into a
file in a temporary folder, flushed every 10 samples as the loop's writer is. Times the checkout in the current folder.

    python benchmarks/recording_sample.py [--samples 20000] [--repeat 5] [--profile]

Prints the CPU time per sample (µs, best and median of ``--repeat`` runs); ``--profile`` prints a
cProfile table of one run instead. Numbers in docs/performance.md ("Daemon loop", fourth pass).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.getcwd())  # the checkout in the current folder (before/after comparisons)
from otbot_hw.recording import (TOPIC_COMMAND, TOPIC_ESTIMATE, TOPIC_EVENTS, TOPIC_IMU, TOPIC_JOINTS,
                                TOPIC_REFERENCE, TOPIC_TRUTH, RecordingWriter)

TOPICS = [TOPIC_JOINTS, TOPIC_EVENTS, TOPIC_IMU, TOPIC_TRUTH, TOPIC_ESTIMATE, TOPIC_REFERENCE]


def sample(k: int, rng: np.random.Generator, period: float = 1 / 800) -> dict:
    """One sample as ``LoopRecording._record`` builds it (lists of Python floats)."""
    t = k * period
    v = rng.standard_normal(40)
    return {TOPIC_COMMAND: {"t": t, "torque": v[0:3].tolist()},
            TOPIC_JOINTS: {"t": t, "position": v[3:6].tolist(), "velocity": v[6:9].tolist()},
            TOPIC_IMU: {"t": t, "accel": v[9:12].tolist(), "gyro": v[12:15].tolist()},
            TOPIC_TRUTH: {"t": t, "q": v[15:21].tolist(), "qd": v[21:27].tolist(), "force": v[27:29].tolist()},
            TOPIC_ESTIMATE: {"t": t, "pose": v[29:32].tolist(), "twist": v[32:35].tolist(),
                             "std": (np.abs(v[34:40])).tolist(), "gyro_bias": float(v[0] * 1e-3)},
            TOPIC_REFERENCE: {"t": t, "p": v[0:3].tolist(), "pd": v[3:6].tolist(), "pdd": v[6:9].tolist()}}


def run(n: int, folder: Path) -> float:
    """CPU seconds per sample writing ``n`` samples (samples built beforehand)."""
    rng = np.random.default_rng(0)
    samples = [sample(k, rng) for k in range(n)]
    with RecordingWriter(folder / "bench.mcap", {"program": "bench"}, topics=TOPICS) as w:
        c0 = time.process_time()
        for s in samples:
            w.write_sample(s)
        c1 = time.process_time()
    return (c1 - c0) / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--profile", action="store_true")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        if a.profile:
            import cProfile
            import pstats
            pr = cProfile.Profile()
            pr.enable()
            run(a.samples, Path(d))
            pr.disable()
            pstats.Stats(pr).sort_stats("tottime").print_stats(20)
            return
        per = [run(a.samples, Path(d)) * 1e6 for _ in range(a.repeat)]
    print(f"write_sample CPU per sample: best {min(per):.1f} us, median {statistics.median(per):.1f} us "
          f"({a.samples} samples x {a.repeat})")


if __name__ == "__main__":
    main()
