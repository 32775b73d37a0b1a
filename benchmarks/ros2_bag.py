"""ROS 2 bags: the cost of writing a sample as a bag (the daemon's ``daemon.recording.format: ros2``)
next to the project's JSON recording, and the speed of ``otbot export --ros2`` / ``otbot import``.

    python benchmarks/ros2_bag.py [--samples N]

Prints one table (µs per sample; samples per second); the numbers go to docs/recording-format.md §9.
"""
from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from otbot_hw.recording import (TOPIC_COMMAND, TOPIC_ESTIMATE, TOPIC_IMU, TOPIC_JOINTS, TOPIC_REFERENCE,
                                RecordingWriter, read_recording, write_recording)
from otbot_hw.ros2.bag_export import export_recording
from otbot_hw.ros2.bag_import import import_bag
from otbot_hw.ros2.writer import BagWriter

LOOP_TOPICS = (TOPIC_JOINTS, TOPIC_IMU, TOPIC_ESTIMATE, TOPIC_REFERENCE)  # what the daemon's loop records


def sample(k: int, rate: float) -> dict:
    t = k / rate
    s = np.sin(0.01 * k)
    return {TOPIC_COMMAND: {"t": t, "torque": [s, -s, 0.5 * s]},
            TOPIC_JOINTS: {"t": t, "position": [k * 1e-3, -k * 1e-3, s], "velocity": [0.1, -0.1, s]},
            TOPIC_IMU: {"t": t, "accel": [0.01 * s, 0.02, 9.80665], "gyro": [0.0, 0.0, 0.01 * s]},
            TOPIC_ESTIMATE: {"t": t, "pose": [k * 1e-4, 0.0, 0.1 + s], "twist": [0.1, 0.0, s], "std": [0.01] * 6},
            TOPIC_REFERENCE: {"t": t, "p": [k * 1e-4, 0.0, 0.1], "pd": [0.1, 0.0, 0.0], "pdd": [0.0] * 3}}


def per_sample(make, n: int) -> float:
    msgs = [sample(k, 1000.0) for k in range(n)]
    w = make()
    t0 = time.perf_counter()
    for m in msgs:
        w.write_sample(m)
    w.close()
    return (time.perf_counter() - t0) / n * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=5000)
    n = ap.parse_args().samples
    d = Path(tempfile.mkdtemp())
    try:
        rows = [("loop sample -> project recording (JSON MCAP)", per_sample(
                    lambda: RecordingWriter(d / "a.mcap", {}, LOOP_TOPICS, flush_every=100), n)),
                ("loop sample -> ROS 2 bag (BagWriter, 6 messages)", per_sample(
                    lambda: BagWriter(d / "b", {}, LOOP_TOPICS, flush_every=100), n))]
        rec = read_recording(d / "a.mcap")
        t0 = time.perf_counter()
        export_recording(rec, d / "exp")
        rows.append(("otbot export --ros2 (recording -> bag)", (time.perf_counter() - t0) / n * 1e6))
        t0 = time.perf_counter()
        res = import_bag(d / "exp")
        rows.append(("otbot import (bag -> recording, shared stamps)", (time.perf_counter() - t0) / n * 1e6))
        write_recording(d / "c.mcap", res.recording)
        print(f"{n} samples of joints, IMU, estimate, reference (1 kHz loop)")
        print(f"{'what':<52} {'µs/sample':>10} {'samples/s':>10}")
        for name, us in rows:
            print(f"{name:<52} {us:>10.1f} {1e6 / us:>10.0f}")
    finally:
        shutil.rmtree(d)


if __name__ == "__main__":
    main()
