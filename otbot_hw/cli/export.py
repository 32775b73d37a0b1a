"""``otbot export``: a project recording → a ROS 2 bag (rosbag2, MCAP storage, CDR)."""
from __future__ import annotations

import argparse
from pathlib import Path

from otbot_hw.cli import add_json_flag
from otbot_hw.cli.checks import CliError, not_an_input, writing


def register(sub) -> None:
    p = sub.add_parser(
        "export",
        help="write a recording as a ROS 2 bag (ros2 bag, Foxglove, PlotJuggler open it natively)",
        description="Write a recording as a rosbag2 folder (MCAP storage, CDR messages by rosbags, metadata.yaml) "
                    "with standard messages: /joint_states (position rad, velocity rad/s, effort N m = torque), "
                    "/imu (sensor_msgs/Imu in the platform frame, covariances from the noise model), /odom "
                    "(nav_msgs/Odometry from the estimate, with covariance), /truth, /reference, /events "
                    "(diagnostic_msgs/DiagnosticArray) where present, /tf (odom -> platform -> chassis). The bag is "
                    "written under a temporary name and renamed when complete (docs/recording-format.md §9).")
    p.add_argument("recording", type=Path, metavar="RUN.mcap", help="recording in the otbot format")
    p.add_argument("--ros2", type=Path, required=True, metavar="OUT",
                   help="the bag folder to write (an earlier bag there is replaced)")
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.recording import read_recording
    from otbot_hw.ros2.bag_export import check_output, export_recording

    check_output(args.ros2)
    not_an_input(args.ros2, "--ros2", {"recording": args.recording}, folder=True)
    rec = read_recording(args.recording)
    if len(rec) == 0:
        raise CliError(f"{args.recording}: no complete sample" + (" (the file was cut short: truncated)"
                                                                 if rec.truncated else "") + "; nothing to export")
    with writing("--ros2"):
        res = export_recording(rec, args.ros2)
    res = {"recording": str(args.recording), "truncated": bool(rec.truncated), **res}
    if not args.json:
        print(f"{args.recording}: {res['samples']} samples -> {res['path']} ({res['mcap']})"
              + (" (the recording was cut short: its complete samples)" if rec.truncated else ""))
        for tp, (ty, n) in res["topics"].items():
            print(f"  {tp}: {ty}, {n} messages")
        print(f"IMU covariances from {res['noise_source']}")
    return res
