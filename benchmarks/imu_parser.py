"""IMU speed: VectorNav ASCII parser throughput and the driver's publish -> read round trip.

Usage: ``.venv/bin/python benchmarks/imu_parser.py [--sentences N] [--json]``

* parser: sentences/s of :class:`drivers.vectornav.SentenceParser` decoding a stream of
  $VNIMU (and $VNYMR) sentences fed in 4 KiB chunks (what a serial read returns), clean and
  with 1 % of sentences corrupted plus garbage bytes; best of 3 runs.
* round trip: the simulated IMU publishes one sentence on its pty and the driver's
  ``read()`` returns it (pyserial, select, parse, mounting rotation); p50 / p99 in us.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers import vectornav as vn  # noqa: E402


def make_stream(kind: str, n: int, corrupt_every: int | None, rng) -> bytes:
    out = bytearray()
    for k in range(n):
        s = vn.frame(vn.format_imu(kind, rng.normal(0, 3, 3), rng.normal(0, 1, 3)))
        if corrupt_every and k % corrupt_every == 0:
            s = s[:20] + b"#" + s[21:]  # bad checksum
            out += b"\x00\xff\x13"  # and some garbage
        out += s
    return bytes(out)


def parse_rate(stream: bytes, chunk: int = 4096, repeats: int = 3) -> tuple[float, vn.ParserStats]:
    best = float("inf")
    for _ in range(repeats):
        p = vn.SentenceParser()
        t0 = time.perf_counter()
        for i in range(0, len(stream), chunk):
            p.feed(stream[i:i + chunk])
        p.finish()
        best = min(best, time.perf_counter() - t0)
    return p.stats.good / best, p.stats


def round_trip(n: int) -> dict:
    from drivers.imu import VectorNavIMU
    from sim.imu import SimulatedIMU

    lat = []
    with SimulatedIMU(output="VNOFF") as sim:
        imu = VectorNavIMU(sim.port, 921600, timeout=1.0)
        imu.open()
        imu.configure("VNIMU", 100)
        for k in range(n):
            t0 = time.perf_counter()
            sim.publish([0.1, 0.2, 9.8], [0.0, 0.0, 0.01 * k])
            s = imu.read()
            lat.append(time.perf_counter() - t0)
            assert s is not None
        imu.close()
    us = np.array(lat) * 1e6
    return {"reads": n, "p50_us": float(np.percentile(us, 50)), "p99_us": float(np.percentile(us, 99))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sentences", type=int, default=50000, help="sentences per stream (default 50000)")
    ap.add_argument("--reads", type=int, default=2000, help="driver round trips (default 2000)")
    ap.add_argument("--json", action="store_true", help="one JSON object on stdout")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    rows = []
    for kind, corrupt, label in [("VNIMU", None, "VNIMU clean"), ("VNYMR", None, "VNYMR clean"),
                                 ("VNIMU", 100, "VNIMU, 1% bad checksum + garbage")]:
        print(f"parser: {label} ...", file=sys.stderr, flush=True)
        stream = make_stream(kind, args.sentences, corrupt, rng)
        rate, stats = parse_rate(stream)
        rows.append({"stream": label, "sentences": args.sentences, "bytes": len(stream),
                     "sentences_per_s": rate, "mbyte_per_s": rate * len(stream) / args.sentences / 1e6,
                     "bad_checksum": stats.bad_checksum, "garbage_bytes": stats.garbage_bytes})
    print("driver round trip over a pty ...", file=sys.stderr, flush=True)
    rt = round_trip(args.reads)
    result = {"parser": rows, "round_trip": rt}
    if args.json:
        print(json.dumps(result))
    else:
        print("| stream | sentences/s | MB/s |")
        print("|---|---|---|")
        for r in rows:
            print(f"| {r['stream']} | {r['sentences_per_s']:,.0f} | {r['mbyte_per_s']:.1f} |")
        print(f"\npublish -> read round trip over a pty: p50 {rt['p50_us']:.0f} us, p99 {rt['p99_us']:.0f} us "
              f"({rt['reads']} reads)")


if __name__ == "__main__":
    main()
