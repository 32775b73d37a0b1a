"""ROS 2 bags in and out without ROS (``otbot export --ros2``, ``otbot import``; otbot_hw/ros2/).

Round trip to float precision and nanosecond stamps; rosbags reads every exported bag with the
standard definitions; a bag laid out as a ROS 2 robot records it (joint_states 200 Hz, imu 400 Hz
with jitter) imports and diagnoses like the native recording; the import's refusals and notices.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from otbot_hw.cli import main
from otbot_hw.recording import Recording, read_recording, write_recording
from otbot_hw.ros2 import messages as M

RNG = np.random.default_rng(3)


def full_recording(n: int = 60, dt: float = 0.01, t0: float = 0.37) -> Recording:
    """Every channel, random values (angles far beyond +-pi), a time offset, events with extras."""
    r = RNG
    t = t0 + np.arange(n) * dt
    alpha = np.cumsum(r.uniform(0.05, 0.3, n)) + 5.0  # continuous, wraps several times
    rec = Recording(t=t, torque=r.normal(0, 5, (n, 3)), joint_pos=np.cumsum(r.normal(0, 0.5, (n, 3)), axis=0),
                    joint_vel=r.normal(0, 3, (n, 3)), imu_accel=r.normal(0, 1, (n, 3)) + [0, 0, 9.80665],
                    imu_gyro=r.normal(0, 0.5, (n, 3)),
                    truth_q=np.column_stack([r.normal(0, 1, (n, 2)), alpha, r.normal(0, 9, (n, 3))]),
                    truth_qd=r.normal(0, 1, (n, 6)), truth_force=r.normal(0, 3, (n, 2)),
                    estimate_pose=np.column_stack([r.normal(0, 1, (n, 2)), alpha + r.normal(0, 0.01, n)]),
                    estimate_twist=r.normal(0, 1, (n, 3)), estimate_std=r.uniform(1e-4, 1e-2, (n, 6)),
                    estimate_gyro_bias=r.normal(0, 1e-3, n),
                    reference_p=np.column_stack([r.normal(0, 1, (n, 2)), alpha - 0.1]),
                    reference_pd=r.normal(0, 1, (n, 3)), reference_pdd=r.normal(0, 1, (n, 3)),
                    events=[{"t": float(t[0]), "kind": "mode", "text": "track corridor"},
                            {"t": float(t[7]), "kind": "fault", "text": "drive 2 silent", "drive": 2, "code": "0x8130"},
                            {"t": float(t[7]), "kind": "note", "text": "two at one sample"}],
                    metadata={"sample_period": dt, "source": "test", "fixture": "floor", "seed": 5,
                              "noise": {"accel": 0.02, "gyro": 0.003, "enc_angle": 0, "enc_rate": 0.01,
                                        "counts_per_rev": None}})
    return rec


def test_export_import_round_trip_gives_every_channel_back(tmp_path, capsys):
    rec = full_recording()
    write_recording(tmp_path / "run.mcap", rec)
    assert main(["export", str(tmp_path / "run.mcap"), "--ros2", str(tmp_path / "bag"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["topics"]) == {"/joint_states", "/imu", "/odom", "/odom/gyro_bias", "/truth", "/truth/force",
                                  "/reference", "/events", "/tf"}
    assert out["topics"]["/events"] == [M.DIAGNOSTIC_ARRAY, 3]
    assert main(["import", str(tmp_path / "bag"), "--out", str(tmp_path / "back.mcap"), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["resampling"]["method"].startswith("none")
    back = read_recording(tmp_path / "back.mcap")
    assert len(back) == len(rec)
    assert np.array_equal(np.round(back.t * 1e9).astype(np.int64), np.round(rec.t * 1e9).astype(np.int64))
    # plain float fields: bit for bit
    for name in ("torque", "joint_pos", "joint_vel", "imu_accel", "imu_gyro", "truth_q", "truth_qd", "truth_force",
                 "estimate_gyro_bias", "reference_pd", "reference_pdd"):
        assert np.array_equal(getattr(back, name), getattr(rec, name)), name
    # through a quaternion (yaw) or a rotation into the body frame: to rounding, angles unwrapped back
    for name in ("estimate_pose", "estimate_twist", "estimate_std", "reference_p"):
        np.testing.assert_allclose(getattr(back, name), getattr(rec, name), rtol=1e-12, atol=1e-13, err_msg=name)
    assert [(e["kind"], e["text"]) for e in back.events] == [(e["kind"], e["text"]) for e in rec.events]
    assert back.events[1]["drive"] == 2 and back.events[1]["code"] == "0x8130"
    assert [round(e["t"] * 1e9) for e in back.events] == [round(e["t"] * 1e9) for e in rec.events]
    for k in ("sample_period", "source", "fixture", "seed", "noise"):
        assert back.metadata[k] == rec.metadata[k], k
    assert back.metadata["import"]["storage"] == "mcap"


def test_rosbags_reads_every_exported_bag_with_the_standard_definitions(tmp_path):
    from rosbags.rosbag2 import Reader

    rec = full_recording(n=30)
    for variant, r in (("full", rec), ("command only", Recording(t=rec.t, torque=rec.torque))):
        out = tmp_path / variant.replace(" ", "_")
        from otbot_hw.ros2.bag_export import export_recording

        export_recording(r, out)
        assert sorted(p.name for p in out.iterdir()) == sorted(["metadata.yaml", f"{out.name}.mcap"])
        with Reader(out) as bag:
            assert bag.message_count > 0
            for c in bag.connections:
                text, digest = M.msgdef(c.msgtype)
                assert c.msgdef.data == text and c.digest == digest, c.topic
                assert c.ext.serialization_format == "cdr"
            n = 0
            for c, ns, raw in bag.messages():
                msg = M.typestore().deserialize_cdr(raw, c.msgtype)
                if hasattr(msg, "header"):
                    assert M.stamp_ns(msg.header) == ns  # header stamp = log time
                n += 1
            assert n == bag.message_count
        if variant == "full":
            with Reader(out) as bag:
                imu = next(c for c in bag.connections if c.topic == "/imu")
                _, _, raw = next(bag.messages(connections=[imu]))
                m = M.typestore().deserialize_cdr(raw, M.IMU)
                assert m.header.frame_id == "platform" and m.orientation_covariance[0] == -1
                assert m.linear_acceleration_covariance[0] == pytest.approx(0.02 ** 2)
                assert m.angular_velocity_covariance[8] == pytest.approx(0.003 ** 2)


def test_export_replaces_an_earlier_bag_only_when_the_new_one_is_complete(tmp_path, capsys):
    write_recording(tmp_path / "run.mcap", full_recording(n=10))
    bag = tmp_path / "bag"
    assert main(["export", str(tmp_path / "run.mcap"), "--ros2", str(bag)]) == 0
    assert main(["export", str(tmp_path / "run.mcap"), "--ros2", str(bag)]) == 0  # replaced
    (tmp_path / "notabag").mkdir()
    (tmp_path / "notabag" / "keep.txt").write_text("mine")
    capsys.readouterr()
    assert main(["export", str(tmp_path / "run.mcap"), "--ros2", str(tmp_path / "notabag")]) == 2
    assert "holds files but no metadata.yaml" in capsys.readouterr().err
    assert (tmp_path / "notabag" / "keep.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "notabag", "run.mcap"]  # no temporary left
