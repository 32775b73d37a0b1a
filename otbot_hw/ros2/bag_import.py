"""A ROS 2 bag as a project recording (``otbot import BAG --out RUN.mcap``).

Parts: ``bag_open`` opens the bag and decodes its messages, ``bag_series`` reads the mapped topics
into time series (joint states split over messages merged), ``bag_time`` checks their stamps and
unwraps the encoders; this module puts them on one grid and writes the metadata.

Conversion (docs/recording-format.md §9): joint angles and rates keep their values times the
map's sign (REP-103 wheels turning about +y and the pivot about +z have the project's signs);
the effort (N m) is the torque command; the IMU message's vectors are rotated into B'' by the
map's rpy (identity by default: a REP-103 body frame x forward, y left, z up is B''), and its
linear acceleration *with* gravity (+g up at rest, as ROS reports it) is the project's specific
force; ``gravity: removed`` adds +g on z. Angles of quaternions (odom, reference) are unwrapped.
The payload estimate (``/payload``, ``messages.payload``) becomes ``/otbot/payload``.

Time: the messages' header stamps (``time: receive``: the bag's log times). When every mapped
topic shares the joint stamps on a uniform grid, the samples are those stamps, values unchanged.
Otherwise one grid at ``rate`` Hz (default the joint-state rate) spans the time every required
topic covers; positions, rates, IMU and optional channels are interpolated linearly in time, the
torque is held (zero-order hold: the latest command at or before the grid time, a quarter period
of stamp jitter allowed), and the interpolation error is estimated by predicting every source
sample from its two neighbours (rms, max per channel: an upper bound, sensor noise included).

Refused (``BagError``, exit 2) where the result would be wrong: another robot's joints, no torque
(effort) channel, a topic with no messages, a mapped topic or field missing, a non-CDR topic, a
clock jump (header stamps going back, or jumping while the receive times do not), a gap (no
sample of a required topic for more than two grid periods: import the part before or after it
with ``start``/``end``), a wrapped encoder that cannot be unwrapped. Said as a notice where the
result is merely less: no IMU, dropped single messages, unwrapped encoder wraps, rates derived
from angles, trimmed ends.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from otbot_hw.recording import FORMAT_NAME, Recording, source_metadata
from otbot_hw.ros2 import BagError
from otbot_hw.ros2 import messages as M
from otbot_hw.ros2.bag_open import Connection, Types, open_bag
from otbot_hw.ros2.bag_series import Series, Source, read_imu, read_joints, read_optional, read_torque, require
from otbot_hw.ros2.bag_time import check_clock, check_gaps, loo_error, nominal_rate, uniform, unwrap_joints
from otbot_hw.ros2.mapping import BagMap


@dataclass
class ImportResult:
    recording: Recording
    report: dict[str, Any]


#: Largest --start/--end (s): an int64 nanosecond stamp spans 9.2e9 s.
MAX_OFFSET = 9e9


def import_bag(path: str | Path, bag_map: BagMap | None = None, rate: float | None = None,
               start: float | None = None, end: float | None = None, allow_truncated: bool = False,
               max_samples: int | None = None) -> ImportResult:
    """Read the bag at ``path`` into a project ``Recording`` (see the module doc). ``rate``: grid
    rate (Hz; default the joint-state rate); ``start``/``end``: the part to import (s after the
    first joint state, at most ``MAX_OFFSET`` s); ``max_samples``: the most samples the grid may have
    (BagError before anything is allocated). Returns the recording and a report (method, errors, notices)."""
    for name, value in (("--start", start), ("--end", end)):
        if value is not None and not (math.isfinite(value) and 0 <= value <= MAX_OFFSET):
            raise BagError(f"{name} {value:g} s: at most {MAX_OFFSET:g} s after the first joint state (the "
                           "nanosecond time stamps' range)")
    bm = bag_map or BagMap()
    bag = open_bag(path, allow_truncated)
    notices: list[str] = []
    if bag.truncated:
        notices.append("the bag's MCAP was cut short (no footer): imported its complete messages up to the cut")
    use_header = bm.time == "header"
    jc = require(bag, bm.joints_topic, "joints", (M.JOINT_STATE,))
    tc = require(bag, bm.torque_topic, "torque")
    imu_c = None
    if bm.imu_topic:
        if bm.imu_topic in bag.connections or bm.imu_topic in bm.explicit:
            imu_c = require(bag, bm.imu_topic, "IMU", (M.IMU,))
        else:
            notices.append(f"no IMU: the bag has no {bm.imu_topic} (the recording has no /otbot/imu: `estimate` "
                           "predicts with the model, `diagnose` fits the encoders only)")
    optional: dict[str, Connection] = {}
    for key, types in (("odom", (M.ODOMETRY,)), ("truth", (M.JOINT_STATE,)), ("reference", (M.MULTI_DOF,)),
                       ("events", (M.DIAGNOSTIC_ARRAY,)), ("payload", (M.PAYLOAD,))):
        tp = getattr(bm, f"{key}_topic")
        if tp and (tp in bag.connections or tp in bm.explicit):
            c = bag.connections.get(tp)
            if tp in bm.explicit or (c is not None and c.msgtype in types and c.count):
                optional[key] = require(bag, tp, key, types)
    extra_topics = {}
    for sub, ty in (("/truth/force", M.WRENCH), ("/odom/gyro_bias", M.VECTOR3)):
        base = bm.truth_topic if sub.startswith("/truth") else bm.odom_topic
        name = None if base is None else base + sub[sub.rindex("/"):]
        if name and name in bag.connections and bag.connections[name].msgtype == ty and bag.connections[name].count:
            extra_topics[sub] = name
    types = Types(bag.connections)
    wanted = {c.topic for c in (jc, tc, imu_c, *optional.values()) if c is not None} | set(extra_topics.values())
    raw: dict[str, list] = {tp: [] for tp in wanted}
    for tp, ns, data in bag.messages(wanted):
        raw[tp].append((ns, data))

    src = Source(bag, types, bm, raw, notices)
    jr = read_joints(src, jc, tc)
    joints, vel_from_angles, no_joints = jr.series, jr.vel_from_angles, jr.no_joints
    names = bm.joint_names
    torque = read_torque(src, tc, jr)
    imu = read_imu(src, imu_c)
    opt, events_raw = read_optional(src, optional, extra_topics)

    # --- time checks -----------------------------------------------------------------------------
    required = [joints] + ([torque] if torque.topic != joints.topic else []) + ([imu] if imu is not None else [])
    if use_header and np.all(joints.stamps == 0):
        raise BagError(f"{joints.topic}: every header stamp is zero; use `time: receive` in the map to take the "
                       "bag's receive times")
    for s in required + list(opt.values()):
        check_clock(s, use_header)
    origin_custom = bool(bag.custom.get("format") == FORMAT_NAME or bag.custom.get("format_version"))
    t_first = int(joints.stamps[0])
    lo = t_first + (int(round(start * 1e9)) if start is not None else 0)
    hi = (t_first + int(round(end * 1e9))) if end is not None else None
    if hi is not None and hi <= lo:
        raise BagError(f"--end {end} s is not after --start {start or 0} s")

    js_step = float(np.median(np.diff(joints.stamps))) if len(joints.stamps) > 1 else math.nan
    if not len(joints.stamps) > 1:
        raise BagError(f"{joints.topic}: {len(joints.stamps)} message(s); at least 2 are needed")
    every = required + list(opt.values())
    common = min(len(s.stamps) for s in every)  # a bag cut mid-sample ends one topic early
    shared = (rate is None or abs(rate * js_step * 1e-9 - 1) < 1e-9) and uniform(joints.stamps) and all(
        np.array_equal(s.stamps[:common], joints.stamps[:common]) and len(s.stamps) - common <= 1 for s in every)
    if shared:
        grid = joints.stamps[:common]
        grid = grid[(grid >= lo) & ((grid <= hi) if hi is not None else True)]
        period_ns = float(np.median(np.diff(joints.stamps)))
        method = {"method": "none: every topic shares the joint-state stamps on a uniform grid; values as recorded"}
        rate_hz = 1e9 / period_ns
    else:
        rate_hz = float(rate) if rate is not None else nominal_rate(js_step)
        period_ns = 1e9 / rate_hz
        span_ns = min(int(s.stamps[-1]) for s in required) - max(int(s.stamps[0]) for s in required)
        if not math.isfinite(period_ns):  # 1/rate of a denormal rate
            raise BagError(f"--rate {rate_hz:g} Hz: the sample period 1/rate is not a finite number of seconds; "
                           f"fewer than 2 samples in the {span_ns * 1e-9:.6g} s the required topics share")
        if max_samples is not None and span_ns / period_ns + 1 > max_samples:
            k = span_ns / period_ns + 1
            raise BagError(f"--rate {rate_hz:g} Hz over the bag's {span_ns * 1e-9:.6g} s gives "
                           f"{int(k) if k < 1e15 else format(k, '.3g')} samples; at most {max_samples}")
        half = period_ns / 2
        first = max(int(s.stamps[0]) for s in required) - half  # a topic's edge value serves half a period
        g1 = int(min(int(s.stamps[-1]) for s in required) + half)
        cand = joints.stamps[(joints.stamps >= max(first, lo))]  # the grid keeps the joint states' phase
        if not len(cand):
            raise BagError(f"{path}: no joint state after every required topic has begun")
        g0 = int(cand[0])
        trimmed = []
        if g0 > t_first + period_ns and start is None:
            trimmed.append(f"start by {(g0 - t_first) * 1e-9:.3f} s (until every required topic has begun)")
        if g1 < int(joints.stamps[-1]) - period_ns and end is None:
            trimmed.append(f"end by {(int(joints.stamps[-1]) - g1) * 1e-9:.3f} s (where a required topic ends)")
        if hi is not None:
            g1 = min(g1, hi)
        n = int(math.floor((g1 - g0) / period_ns + 1e-9)) + 1
        if n < 2:
            raise BagError(f"{path}: the required topics ({', '.join(s.topic for s in required)}) overlap for less "
                           "than two samples")
        grid = g0 + np.round(np.arange(n) * period_ns).astype(np.int64)
        if trimmed:
            notices.append("trimmed the " + " and the ".join(trimmed))
        if len(torque.stamps) > 1:
            cmd_period = float(np.median(np.diff(torque.stamps)))
            changes = np.any(np.diff(torque.values["torque"], axis=0) != 0, axis=1)
            if cmd_period < 0.9 * period_ns and changes.mean() > 0.5 * cmd_period / period_ns:
                notices.append(f"the torque commands come at {1e9 / cmd_period:.4g} Hz and change faster than the "
                               f"{rate_hz:.4g} Hz grid: held at the grid, the commands between its samples are "
                               "dropped and the recording's torque is not all that drove the robot (import at the "
                               "command rate for identification and diagnosis)")
        for s in required:
            check_gaps(s, grid, period_ns, notices)
        method = {"method": "linear interpolation in time onto one grid (joints, IMU, optional channels); torque "
                            "by zero-order hold (latest command at or before the grid time, 1/4 period jitter "
                            "allowed)",
                  "error": {}}
    if len(grid) < 2:
        raise BagError(f"{path}: fewer than 2 samples between --start and --end")

    # --- wrapped encoders ---------------------------------------------------------------------
    unwrap_joints(joints, names, vel_from_angles, bm.velocity_field, notices)

    # --- values on the grid -------------------------------------------------------------------
    def on_grid(s: Series, key: str, err_name: str | None = None, unit: str = "") -> np.ndarray:
        v = s.values[key]
        if shared:
            return v[np.searchsorted(s.stamps, grid)]
        x = (s.stamps - grid[0]).astype(float)
        xg = (grid - grid[0]).astype(float)
        out = np.column_stack([np.interp(xg, x, v[:, c]) for c in range(v.shape[1])])
        out[(xg < x[0] - period_ns / 2) | (xg > x[-1] + period_ns / 2)] = np.nan  # beyond the held edge
        inside = (x >= -period_ns) & (x <= xg[-1] + period_ns)  # the source samples of the imported part
        if err_name is not None and inside.sum() > 2:
            e = loo_error(x[inside], v[inside])
            method["error"][err_name] = {"rms": e[0], "max": e[1], "unit": unit}
        return out

    def hold(s: Series, key: str) -> np.ndarray:
        v = s.values[key]
        if shared:
            return v[np.searchsorted(s.stamps, grid)]
        i = np.searchsorted(s.stamps, grid + int(period_ns / 4), side="right") - 1
        return v[np.clip(i, 0, len(v) - 1)]

    origin = 0 if origin_custom else int(grid[0])
    t = (grid - origin) * 1e-9
    rec = Recording(t=t, torque=hold(torque, "torque"))
    if not no_joints:
        rec.joint_pos = on_grid(joints, "position", "joint position", "rad")
        rec.joint_vel = on_grid(joints, "velocity", "joint velocity", "rad/s")
    if imu is not None:
        rec.imu_accel = on_grid(imu, "accel", "IMU accel", "m/s^2")
        rec.imu_gyro = on_grid(imu, "gyro", "IMU gyro", "rad/s")
    if "truth" in opt:
        v = on_grid(opt["truth"], "v")
        rec.truth_q, rec.truth_qd = v[:, :6], v[:, 6:]
        if "/truth/force" in opt:
            rec.truth_force = on_grid(opt["/truth/force"], "v")
    if "odom" in opt:
        v = on_grid(opt["odom"], "v")
        rec.estimate_pose, rec.estimate_twist, rec.estimate_std = v[:, :3], v[:, 3:6], v[:, 6:]
        if "/odom/gyro_bias" in opt:
            rec.estimate_gyro_bias = on_grid(opt["/odom/gyro_bias"], "v")[:, 0]
    if "reference" in opt:
        v = on_grid(opt["reference"], "v")
        rec.reference_p, rec.reference_pd = v[:, :3], v[:, 3:6]
        rec.reference_pdd = None if np.all(np.isnan(v[:, 6:])) else v[:, 6:]
    if "payload" in opt:
        v = on_grid(opt["payload"], "v")
        rec.payload_value, rec.payload_std, rec.payload_used = v[:, :4], v[:, 4:8], v[:, 8:]
    for ns, m in events_raw:
        if ns < grid[0] - period_ns / 2 or ns > grid[-1] + period_ns / 2:
            continue
        k = int(np.clip(np.searchsorted(grid, ns + int(period_ns / 4), side="right") - 1, 0, len(grid) - 1))
        rec.events.extend(M.diagnostic_events(m, float(t[k])))
    for name, arr in (("joint angles", rec.joint_pos), ("IMU", rec.imu_accel)):
        if arr is not None and np.any(np.isnan(arr)):
            raise BagError(f"{path}: {name} undefined at {int(np.isnan(arr).any(axis=1).sum())} grid samples")

    # --- metadata and report ------------------------------------------------------------------
    topics = {c.topic: {"type": c.msgtype, "messages": c.count} for c in (jc, tc, imu_c, *optional.values())
              if c is not None}
    for s in [joints] + ([imu] if imu else []) + ([torque] if torque.topic != joints.topic else []):
        if len(s.stamps) > 1:
            d = np.diff(s.stamps) * 1e-9
            topics[s.topic].update({"rate_hz": float(1 / np.median(d)), "jitter_s": float(np.std(d))})
    conversion = ("joints: angle, rate and effort times the map's sign "
                  f"{list(bm.joint_sign)} (REP-103 wheel axes +y, pivot +z: the project's signs); effort N m x "
                  f"{bm.torque_scale} = torque command; IMU: "
                  + ("identity (REP-103 body axes x forward, y left, z up = B'' axes 1'', 2'', 3'')"
                     if bm.imu_rotation() is None else f"rotated into B'' by rpy {list(bm.imu_rpy)} rad")
                  + ("; linear acceleration with gravity (+g up at rest) = specific force"
                     if bm.imu_gravity == "included"
                     else "; +g added on z (gravity removed by the source, flat ground assumed)"))
    resampling = {"rate_hz": rate_hz, "period_s": period_ns * 1e-9, **method}
    meta = {k: v for k, v in bag.custom.items() if k not in ("format", "format_version")}
    if not (shared and "sample_period" in meta):  # an exported recording keeps its own
        meta["sample_period"] = period_ns * 1e-9
    meta.setdefault("source", source_metadata(program="ros2 bag")["source"])
    meta.setdefault("fixture", bm.fixture)
    meta["import"] = {"bag": str(Path(path).resolve()), "storage": bag.storage, "truncated": bag.truncated,
                      "topics": topics, "mapping": bm.to_dict(), "conversion": conversion, "resampling": resampling,
                      "start_time_ns": int(grid[0]), "time_origin_ns": origin, "notices": notices}
    rec.metadata = meta
    report = {"bag": str(path), "samples": len(rec), "duration_s": float(t[-1] - t[0]), "rate_hz": rate_hz,
              "topics": topics, "conversion": conversion, "resampling": resampling, "notices": notices,
              "truncated": bag.truncated, "channels": rec.channels()}
    return ImportResult(rec, report)
