"""``otbot import``: a ROS 2 bag (rosbag2 folder or .mcap, CDR) → a project recording."""
from __future__ import annotations

import argparse
from pathlib import Path

from otbot_hw.cli import add_json_flag
from otbot_hw.cli.checks import MAX_SAMPLES, CliError, duration, non_negative, output_file, rate, write_complete, writing


def register(sub) -> None:
    p = sub.add_parser(
        "import",
        help="read a ROS 2 bag (joint_states, imu) into a recording that diagnose/estimate/identify accept",
        description="Read a ROS 2 bag (rosbag2 folder with metadata.yaml, MCAP or SQLite storage, or a single "
                    ".mcap file; CDR messages, read by rosbags) into a recording in the project's format. "
                    "Default mapping (no --map): /joint_states (sensor_msgs/JointState) with joints right_wheel, "
                    "left_wheel, pivot (position rad, velocity rad/s, effort N m = the torque command) and /imu "
                    "(sensor_msgs/Imu) in the platform frame with REP-103 axes (x forward, y left, z up; linear "
                    "acceleration including gravity). Topics at other rates or with jittery stamps are brought "
                    "to one grid (--rate Hz, default the joint-state rate) by linear interpolation, the torque by "
                    "zero-order hold; the method and its estimated error are reported. A gap, a clock jump, "
                    "another robot's joints or a missing torque refuse the import (exit 2); a missing IMU or an "
                    "unwrapped encoder is a notice (docs/recording-format.md §9).")
    p.add_argument("bag", type=Path, metavar="BAG", help="rosbag2 folder or .mcap file")
    p.add_argument("--out", type=Path, required=True, metavar="RUN.mcap", help="the recording to write")
    p.add_argument("--map", type=Path, default=None, metavar="MAP.yaml",
                   help="which topic and field is which channel (layout: config/ros2_map.yaml)")
    p.add_argument("--rate", type=rate, default=None, metavar="HZ",
                   help="sample rate of the recording (Hz; default the joint-state rate)")
    p.add_argument("--start", type=non_negative, default=None, metavar="S",
                   help="import from S seconds after the first joint state")
    p.add_argument("--end", type=duration, default=None, metavar="S",
                   help="import up to S seconds after the first joint state")
    p.add_argument("--allow-truncated", action="store_true",
                   help="import a bag whose MCAP was cut short (recorder killed) up to the cut")
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.recording import write_recording
    from otbot_hw.ros2.bag_import import import_bag
    from otbot_hw.ros2.mapping import load_map

    output_file(args.out, "--out", inputs={"bag": args.bag, "map file": args.map})
    bag_map = load_map(args.map)
    res = import_bag(args.bag, bag_map, rate=args.rate, start=args.start, end=args.end,
                     allow_truncated=args.allow_truncated, max_samples=MAX_SAMPLES)
    with writing("--out"):  # beside, renamed when complete; a device (/dev/null) written as it is
        write_complete(args.out, lambda path: write_recording(path, res.recording))
    report = {**res.report, "out": str(args.out)}
    if not args.json:
        print_summary(report)
    return report


def print_summary(r: dict) -> None:
    print(f"{r['bag']}: {r['samples']} samples over {r['duration_s']:.3f} s at {r['rate_hz']:g} Hz -> {r['out']} "
          f"({', '.join(r['channels'])})")
    for tp, info in r["topics"].items():
        extra = f", {info['rate_hz']:.1f} Hz, jitter {1e3 * info['jitter_s']:.3f} ms" if "rate_hz" in info else ""
        print(f"  {tp}: {info['type']}, {info['messages']} messages{extra}")
    print(f"conversion: {r['conversion']}")
    rs = r["resampling"]
    print(f"resampling: {rs['method']}")
    for name, e in rs.get("error", {}).items():
        print(f"  {name}: interpolation error rms {e['rms']:.3g}, max {e['max']:.3g} {e['unit']} "
              "(each sample predicted from its neighbours; sensor noise included)")
    for n in r["notices"]:
        print(f"notice: {n}")
