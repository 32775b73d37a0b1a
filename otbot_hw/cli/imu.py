"""``otbot imu``: tools for the serial IMU (VectorNav ASCII protocol).

``otbot imu parse FILE`` decodes a captured byte stream (e.g. ``cat /dev/ttyUSB0 > FILE``):
every ``$VNIMU``/``$VNYMR`` record with its values, the other sentences (register replies,
device errors) and the counts of what was rejected.

``otbot imu read`` configures the IMU from ``config/robot.yaml`` (section ``imu``) and reads
it for a while: sample rate and the mean/spread of the platform-frame readings -- at rest
the accelerometer mean should be (0, 0, +9.81) m/s^2 when the mounting rotation is right.
``--sim`` runs the same against the simulated IMU on a pseudo-terminal.
"""
from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import numpy as np

from otbot_hw.cli import CliError, add_json_flag, progress
from otbot_hw.cli.checks import count, duration, seed


def register(sub) -> None:
    p = sub.add_parser("imu", help="serial IMU tools (VectorNav ASCII protocol)",
                       description="Serial IMU tools for the VectorNav ASCII protocol.")
    imu_sub = p.add_subparsers(dest="imu_command", metavar="ACTION")
    imu_sub.required = True
    parse = imu_sub.add_parser(
        "parse",
        help="decode a captured VectorNav byte stream",
        description="Decode a captured VectorNav ASCII byte stream: $VNIMU / $VNYMR records in the "
                    "sensor frame (accel m/s^2, gyro rad/s, mag Gauss, temperature deg C, pressure kPa, "
                    "yaw/pitch/roll deg), other sentences, and error counts (bad checksums, truncated "
                    "sentences, malformed sentences, garbage bytes). Records carry their index and the "
                    "byte offset of their '$' in the file.",
    )
    parse.add_argument("file", type=Path, metavar="FILE", help="captured bytes (binary file)")
    parse.add_argument("--limit", type=count(0), default=None, metavar="N",
                       help="print/report only the first N records (counts still cover the whole file)")
    add_json_flag(parse)
    parse.set_defaults(func=run_parse)

    read = imu_sub.add_parser(
        "read",
        help="configure the IMU from the config and read it live",
        description="Open the IMU's serial port, configure its output (type and rate, registers 6 and 7) "
                    "from the 'imu' section of the hardware config, read samples for --duration s and report "
                    "the rate (Hz) and the mean and standard deviation of the specific force (m/s^2) and "
                    "angular rate (rad/s) in the platform frame B'' (x, y horizontal, z up). At rest the "
                    "specific force should be about (0, 0, +9.81) m/s^2. Exit 2: bad config or port; "
                    "exit 1: the device does not answer or stops sending.",
    )
    read.add_argument("--config", type=Path, default=None, help="hardware config YAML (default config/robot.yaml)")
    read.add_argument("--port", default=None, help="serial port (default: imu.port from the config)")
    read.add_argument("--duration", type=duration, default=1.0,
                      help="how long to read, s (default 1)")
    read.add_argument("--sim", action="store_true",
                      help="read a simulated IMU at rest (gravity + the paper's noise) on a pseudo-terminal")
    read.add_argument("--seed", type=seed, default=0, help="noise seed for --sim, an integer >= 0 (default 0)")
    add_json_flag(read)
    read.set_defaults(func=run_read)


def run_parse(args: argparse.Namespace) -> dict:
    from drivers.vectornav import ImuRecord, parse_bytes
    from otbot_hw.input_files import read_bytes

    path: Path = args.file
    try:
        data = read_bytes(path)
    except IsADirectoryError:
        raise CliError(f"{path}: is a directory, expected a captured byte stream") from None
    except OSError as exc:
        raise CliError(f"{path}: cannot read: {exc.strerror or exc}") from None
    items, stats = parse_bytes(data)
    records, others = [], []
    for item in items:
        if isinstance(item, ImuRecord):
            d = item.to_dict()
            d = {"index": len(records), "offset": d.pop("offset"), "type": d.pop("kind"), **d}
            records.append(d)
        else:
            others.append({"offset": item.offset, "type": item.header, "fields": list(item.fields),
                           "checked": item.checked})
    errors = {k: stats.to_dict()[k] for k in ("bad_checksum", "truncated", "malformed", "garbage_bytes",
                                              "device_errors")}
    shown = records if args.limit is None else records[: args.limit]
    result = {
        "file": str(path),
        "bytes": len(data),
        "sentences": stats.good,
        "record_count": len(records),
        "records": shown,
        "other_sentences": others,
        "unchecked": stats.unchecked,
        "errors": errors,
        "units": {"accel": "m/s^2", "gyro": "rad/s", "mag": "Gauss", "temperature": "deg C",
                  "pressure": "kPa", "ypr": "deg", "frame": "sensor"},
    }
    if not args.json:
        print(f"{path}: {len(data)} bytes, {stats.good} sentences, {len(records)} IMU records (sensor frame)")
        for r in shown:
            acc = " ".join(f"{v:+8.3f}" for v in r["accel"])
            gyr = " ".join(f"{v:+10.6f}" for v in r["gyro"])
            print(f"  #{r['index']:<5d} @{r['offset']:<8d} {r['type']}  accel [m/s^2] {acc}   gyro [rad/s] {gyr}")
        if len(shown) < len(records):
            print(f"  ... {len(records) - len(shown)} more records")
        for o in others:
            print(f"  @{o['offset']:<8d} {o['type']} {','.join(o['fields'])}")
        print("errors: " + ", ".join(f"{k} {v}" for k, v in errors.items()))
    return result


def _rest_publisher(sim, stop: threading.Event, seed: int, sigma: float, gravity: float) -> None:
    """Publish the platform at rest (B'': specific force (0, 0, +g), no rotation) with white
    noise of ``sigma`` on every channel, at the simulator's configured rate, in real time."""
    rng = np.random.default_rng(seed)
    t_next = time.monotonic()
    while not stop.is_set():
        now = time.monotonic()
        if sim.output is None:  # output off until the driver configures it
            t_next = now + 0.001
        else:
            sim.publish_platform(np.array([0.0, 0.0, gravity]) + rng.normal(0, sigma, 3), rng.normal(0, sigma, 3))
            t_next += 1.0 / sim.rate_hz
            if t_next < now - 1.0 / sim.rate_hz:  # more than a period late: no catch-up burst
                t_next = now
        stop.wait(max(0.0, t_next - time.monotonic()))


def run_read(args: argparse.Namespace) -> dict:
    from drivers.imu import ImuFault, VectorNavIMU
    from drivers.imu_config import load_imu_config

    cfg = load_imu_config(args.config)
    sim = stop = thread = None
    if args.sim:
        from otbot_hw.sensors import GRAVITY, imu_sigma
        from sim.imu import SimulatedIMU

        sim = SimulatedIMU(output="VNOFF", mounting=cfg.mounting)
        stop = threading.Event()
        thread = threading.Thread(target=_rest_publisher, args=(sim, stop, args.seed, imu_sigma(), GRAVITY),
                                  daemon=True)
        thread.start()
    port = args.port or (sim.port if sim else cfg.port)
    imu = VectorNavIMU.from_config(cfg, port=port)
    samples = []
    try:
        try:
            imu.open()
        except ImuFault as exc:
            raise CliError(str(exc)) from None
        try:
            imu.configure(cfg.output, cfg.rate_hz)
            progress(f"{port}: {cfg.output} at {cfg.rate_hz} Hz, reading {args.duration:g} s", not args.json)
            t0 = time.monotonic()
            records0 = imu.stats.records
            next_report = t0 + 1.0
            while time.monotonic() - t0 < args.duration:
                s = imu.read()
                if s is not None:
                    samples.append(s)
                if time.monotonic() >= next_report:
                    progress(f"  {len(samples)} samples", True)
                    next_report += 1.0
            elapsed = time.monotonic() - t0
            sentences = imu.stats.records - records0
        except ImuFault as exc:
            print(f"otbot imu read: error: {exc}", file=sys.stderr)
            raise SystemExit(1) from None
    finally:
        imu.close()
        if sim is not None:
            stop.set()
            thread.join(timeout=2.0)
            sim.close()
    acc = np.array([s.accel for s in samples]).reshape(-1, 3)
    gyr = np.array([s.gyro for s in samples]).reshape(-1, 3)
    stats = imu.stats
    result = {
        "port": port,
        "simulated": bool(args.sim),
        "output": cfg.output,
        "configured_rate_hz": cfg.rate_hz,
        "samples": len(samples),
        "sentences": sentences,
        "rate_hz": sentences / elapsed if elapsed > 0 else 0.0,
        "accel_mean": acc.mean(axis=0).tolist() if len(acc) else None,
        "accel_std": acc.std(axis=0).tolist() if len(acc) else None,
        "gyro_mean": gyr.mean(axis=0).tolist() if len(gyr) else None,
        "gyro_std": gyr.std(axis=0).tolist() if len(gyr) else None,
        "frame": "platform B'' (z up)",
        "units": {"accel": "m/s^2", "gyro": "rad/s", "rate": "Hz"},
        "errors": {k: getattr(stats, k) for k in ("bad_checksum", "truncated", "malformed", "garbage_bytes")},
    }
    if not args.json:
        print(f"{port}: {sentences} IMU sentences in {elapsed:.2f} s ({result['rate_hz']:.1f} Hz, configured "
              f"{cfg.rate_hz} Hz); {len(samples)} samples read (a read returns the newest only)")
        if len(acc):
            print("accel mean [m/s^2] " + " ".join(f"{v:+.4f}" for v in result["accel_mean"])
                  + "   std " + " ".join(f"{v:.4f}" for v in result["accel_std"]))
            print("gyro  mean [rad/s] " + " ".join(f"{v:+.5f}" for v in result["gyro_mean"])
                  + "   std " + " ".join(f"{v:.5f}" for v in result["gyro_std"]))
        print("errors: " + ", ".join(f"{k} {v}" for k, v in result["errors"].items()))
    return result
