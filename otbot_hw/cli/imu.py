"""``otbot imu``: tools for the serial IMU (VectorNav ASCII protocol).

``otbot imu parse FILE`` decodes a captured byte stream (e.g. ``cat /dev/ttyUSB0 > FILE``):
every ``$VNIMU``/``$VNYMR`` record with its values, the other sentences (register replies,
device errors) and the counts of what was rejected.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from otbot_hw.cli import CliError, add_json_flag


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
    parse.add_argument("--limit", type=int, default=None, metavar="N",
                       help="print/report only the first N records (counts still cover the whole file)")
    add_json_flag(parse)
    parse.set_defaults(func=run_parse)


def run_parse(args: argparse.Namespace) -> dict:
    from drivers.vectornav import ImuRecord, parse_bytes

    path: Path = args.file
    if args.limit is not None and args.limit < 0:
        raise CliError(f"--limit must be >= 0, got {args.limit}")
    try:
        data = path.read_bytes()
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
