"""ROS 2 bags in and out without ROS (``otbot export --ros2``, ``otbot import``; otbot_hw/ros2/).

Round trip to float precision and nanosecond stamps; rosbags reads every exported bag with the
standard definitions; a bag laid out as a ROS 2 robot records it (joint_states 200 Hz, imu 400 Hz
with jitter) imports and diagnoses like the native recording; the import's refusals and notices.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

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
                    payload_value=r.normal([60, 4, 0.05, -0.02], 1, (n, 4)), payload_std=r.uniform(0, 1, (n, 4)),
                    payload_used=r.normal([60, 4, 0.05, -0.02], 1, (n, 4)),
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
                                  "/reference", "/payload", "/events", "/tf"}
    assert out["topics"]["/events"] == [M.DIAGNOSTIC_ARRAY, 3] and out["topics"]["/payload"] == [M.PAYLOAD, 60]
    assert main(["import", str(tmp_path / "bag"), "--out", str(tmp_path / "back.mcap"), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["resampling"]["method"].startswith("none")
    back = read_recording(tmp_path / "back.mcap")
    assert len(back) == len(rec)
    assert np.array_equal(np.round(back.t * 1e9).astype(np.int64), np.round(rec.t * 1e9).astype(np.int64))
    # plain float fields: bit for bit
    for name in ("torque", "joint_pos", "joint_vel", "imu_accel", "imu_gyro", "truth_q", "truth_qd", "truth_force",
                 "estimate_gyro_bias", "reference_pd", "reference_pdd", "payload_value", "payload_std", "payload_used"):
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
        from otbot_hw.ros2.bag_import import import_bag

        export_recording(r, out)
        assert sorted(p.name for p in out.iterdir()) == sorted(["metadata.yaml", f"{out.name}.mcap"])
        if variant == "command only":  # and back: the torque, a notice that there are no joints
            res = import_bag(out)
            assert np.array_equal(res.recording.torque, r.torque) and res.recording.joint_pos is None
            assert any("the recording has no /otbot/joints" in n for n in res.report["notices"])
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


# --- a bag as a ROS 2 robot records it ------------------------------------------------------------

EPOCH_NS = 1_763_000_000 * 10 ** 9  # header stamps in ROS time (s since 1970)
ROBOT_JOINTS = ["pivot", "caster_front", "left_wheel", "right_wheel"]  # any order, extra joints


def fine_run(values: dict, duration: float, seed: int, dt: float = 0.005, sub: int = 10) -> Recording:
    """A concealed-effect run simulated at dt/sub (2 kHz) with the torque held for dt (200 Hz)."""
    from otbot_hw.model import effects as fx
    from otbot_hw.params import nominal
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.concealed import excitation
    from otbot_hw.simulation.runs import extended_recording

    U, fixture = excitation("multisine", duration, dt, seed)
    model = fx.ExtendedModel(nominal(), fx.effect_vector()).with_values(values)
    return extended_recording(model, np.repeat(U, sub, axis=0), dt / sub, NoiseModel.paper(), seed=100 + seed,
                              fixture=fixture)


def native(fine: Recording, sub: int = 10) -> Recording:
    """What the project's own 200 Hz recorder writes of the run (every sub-th sample)."""
    i = np.arange(0, len(fine), sub)
    return Recording(t=fine.t[i], torque=fine.torque[i], joint_pos=fine.joint_pos[i], joint_vel=fine.joint_vel[i],
                     imu_accel=fine.imu_accel[i], imu_gyro=fine.imu_gyro[i],
                     metadata={"sample_period": float(fine.t[sub] - fine.t[0]), "fixture": "floor"})


def robot_bag(path, fine: Recording, *, names=ROBOT_JOINTS, effort=True, imu=True, imu_jitter=True, gap=None,
              clock_jump=None, wrap_pivot=False, storage="mcap", seed=0, robot_names=None, split=False,
              split_offsets=None, split_drop=None):
    """Write ``fine`` with rosbags' own writer as a ROS 2 robot would: /joint_states at 200 Hz (sub-sampled
    1:10), /imu at 400 Hz with +-0.5 ms jitter (true sample times), stamps in ROS time, receive (log) times
    0.2-1 ms later. ``gap`` (t0, t1) s: no messages in it; ``clock_jump`` (t, s): header stamps jump;
    ``wrap_pivot``: pivot angle shifted to straddle pi and reported in (-pi, pi]; ``robot_names``: the
    message's name of each of right_wheel, left_wheel, pivot; ``split``: one JointState per joint (as some
    drivers publish), stamped alike unless ``split_offsets`` {name: s} moves one, ``split_drop`` (name, t)
    leaves that joint's message of the first sample at or after t s out."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    rng = np.random.default_rng(seed)
    ts = M.typestore()
    n = len(fine)
    js_i = np.arange(0, n, 10)
    imu_i = np.arange(0, n, 5)
    if imu_jitter:
        imu_i = np.clip(imu_i + rng.integers(-1, 2, len(imu_i)), 0, n - 1)
        imu_i = np.unique(imu_i)
    out = []

    def keep(i):
        return gap is None or not gap[0] <= fine.t[i] < gap[1]

    def hdr_ns(i):
        ns = EPOCH_NS + int(round(fine.t[i] * 1e9))
        if clock_jump is not None and fine.t[i] >= clock_jump[0]:
            ns += int(clock_jump[1] * 1e9)
        return ns

    def log_ns(i):
        return EPOCH_NS + int(round(fine.t[i] * 1e9)) + int(rng.uniform(2e5, 1e6))

    pivot = fine.joint_pos[js_i, 2]
    shift = math.pi - (pivot.max() + pivot.min()) / 2
    for i in js_i:
        if not keep(i):
            continue
        full = {(robot_names or {}).get(x, x): j for j, x in enumerate(("right_wheel", "left_wheel", "pivot"))}
        p = fine.joint_pos[i].copy()
        if wrap_pivot:
            p[2] = math.atan2(math.sin(p[2] + shift), math.cos(p[2] + shift))
        val = lambda arr: np.array([arr[full[x]] if x in full else 0.0 for x in names])  # noqa: E731
        h = ts.types["std_msgs/msg/Header"](stamp=M.stamp(hdr_ns(i)), frame_id="")
        msg = ts.types[M.JOINT_STATE](header=h, name=list(names), position=val(p), velocity=val(fine.joint_vel[i]),
                                      effort=val(fine.torque[i]) if effort else np.array([], dtype=float))
        if not split:
            out.append((log_ns(i), "/joint_states", msg))
            continue
        for j, x in enumerate(names):
            if split_drop is not None and x == split_drop[0] and fine.t[i] >= split_drop[1]:
                split_drop = None
                continue
            dt_ns = int(round((split_offsets or {}).get(x, 0.0) * 1e9))
            hj = ts.types["std_msgs/msg/Header"](stamp=M.stamp(hdr_ns(i) + dt_ns), frame_id="")
            one = ts.types[M.JOINT_STATE](header=hj, name=[x], position=msg.position[j:j + 1],
                                          velocity=msg.velocity[j:j + 1], effort=msg.effort[j:j + 1])
            out.append((log_ns(i) + j * 1000, "/joint_states", one))
    if imu:
        for i in imu_i:
            if keep(i):
                out.append((log_ns(i), "/imu", M.imu(hdr_ns(i), fine.imu_accel[i], fine.imu_gyro[i], 1.9e-4, 1.9e-4)))
    out.sort(key=lambda e: e[0])
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {"/joint_states": w.add_connection("/joint_states", M.JOINT_STATE, typestore=ts)}
        if imu:
            conns["/imu"] = w.add_connection("/imu", M.IMU, typestore=ts)
        for ns, tp, msg in out:
            w.write(conns[tp], ns, ts.serialize_cdr(msg, msg.__msgtype__))
    return path


def test_a_robots_bag_imports_and_diagnoses_like_the_native_recording(tmp_path, capsys):
    from otbot_hw.diagnose.data import from_recording
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.params import nominal

    truth = {"b_ax": 0.06, "b_ay": 0.04, "b_gz": -0.01}
    fine = fine_run(truth, 2.0, seed=11)
    bag = robot_bag(tmp_path / "robot_bag", fine)
    assert main(["import", str(bag), "--out", str(tmp_path / "imp.mcap"), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["rate_hz"] == 200.0 and rep["resampling"]["method"].startswith("linear interpolation")
    assert rep["topics"]["/imu"]["rate_hz"] == pytest.approx(400, rel=0.01) and rep["topics"]["/imu"]["jitter_s"] > 1e-4
    err = rep["resampling"]["error"]
    assert set(err) == {"joint position", "joint velocity", "IMU accel", "IMU gyro"}
    assert err["IMU accel"]["rms"] < 0.1  # m/s^2: noise (13.7e-3) plus 2.5 ms of interpolation
    imp = read_recording(tmp_path / "imp.mcap")
    nat = native(fine)
    # the grid is the joint states' own: joints and torque are the native samples, the IMU interpolated
    assert len(imp) == len(nat) and np.allclose(imp.t, nat.t - nat.t[0], atol=1e-9)
    assert np.array_equal(imp.torque, nat.torque) and np.array_equal(imp.joint_pos, nat.joint_pos)
    assert np.sqrt(np.mean((imp.imu_accel - nat.imu_accel) ** 2)) < 0.05
    assert imp.metadata["import"]["start_time_ns"] == EPOCH_NS
    found = {}
    for name, rec in (("native", nat), ("imported", imp)):
        r = diagnose([from_recording(rec, name)], nominal())
        assert r["model_adequate"], (name, r["verdict"])
        found[name] = {e["name"]: {k: v["value"] for k, v in e["parameters"].items()} for e in r["effects"]}
    assert list(found["imported"]) == list(found["native"]) == ["imu_bias"], found
    for k, v in truth.items():
        assert found["imported"]["imu_bias"][k] == pytest.approx(v, rel=0.15)
        assert found["imported"]["imu_bias"][k] == pytest.approx(found["native"]["imu_bias"][k], rel=0.1)


@pytest.fixture(scope="module")
def short_run():
    return fine_run({}, 0.6, seed=2)


def _import(tmp_path, bag, *extra):
    out = tmp_path / "out.mcap"
    rc = main(["import", str(bag), "--out", str(out), *extra])
    return rc, out


@pytest.mark.parametrize("case, kwargs, expected", [
    ("another robot", {"names": ["front_left_wheel", "front_right_wheel", "rear_left_wheel", "rear_right_wheel"]},
     "/joint_states: joints ['front_left_wheel', 'front_right_wheel', 'rear_left_wheel', 'rear_right_wheel'] are "
     "not this robot's: no 'right_wheel', 'left_wheel', 'pivot'"),
    ("no effort", {"effort": False}, "/joint_states: field effort (the torque command, N m) is empty in every message"),
    ("gap", {"gap": (0.2, 0.3)}, "/joint_states: gap of 0.1"),
    ("clock jump", {"clock_jump": (0.3, -2.0)}, "/joint_states: clock jump at message"),
    ("clock jump forward", {"clock_jump": (0.3, 30.0)}, "receive time moves"),
])
def test_import_refuses_what_would_be_wrong(tmp_path, capsys, short_run, case, kwargs, expected):
    bag = robot_bag(tmp_path / "bag", short_run, **kwargs)
    rc, out = _import(tmp_path, bag)
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert expected in err, err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["bag"]  # nothing half-written


def test_import_notices_what_is_merely_less(tmp_path, capsys, short_run):
    bag = robot_bag(tmp_path / "bag", short_run, imu=False, wrap_pivot=True, storage="sqlite3")
    nat = native(short_run)
    assert np.ptp(nat.joint_pos[:, 2]) > 0.05
    rc, out = _import(tmp_path, bag, "--json")
    rep = json.loads(capsys.readouterr().out)
    assert rc == 0
    assert any(n.startswith("no IMU: the bag has no /imu") for n in rep["notices"])
    rec = read_recording(out)
    assert rec.imu_accel is None and rec.metadata["import"]["storage"] == "sqlite3"
    assert any("pivot (pivot) position wraps at +-pi" in n for n in rep["notices"]), rep["notices"]
    np.testing.assert_allclose(rec.joint_pos[:, 2] - rec.joint_pos[0, 2], nat.joint_pos[:, 2] - nat.joint_pos[0, 2],
                               atol=1e-12)


# --- bad input: one line naming the topic/field, exit 2, nothing written ------------------------------

def _bad(tmp_path, capsys, argv, expected):
    out = tmp_path / "out.mcap"
    before = sorted(p.name for p in tmp_path.iterdir())
    rc = main(["import", *argv, "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert expected in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing half-written


def test_bad_bags_and_maps_are_refused_naming_the_topic_or_field(tmp_path, capsys, short_run):
    from rosbags.rosbag2 import StoragePlugin, Writer

    bag = robot_bag(tmp_path / "bag", short_run)
    # a mapping naming a missing topic, a missing field, an unknown key
    (tmp_path / "m1.yaml").write_text("imu: {topic: /imu/data_raw}\n")
    _bad(tmp_path, capsys, [str(bag), "--map", str(tmp_path / "m1.yaml")], "no topic /imu/data_raw (IMU); the bag has: "
         "/imu, /joint_states")
    (tmp_path / "m2.yaml").write_text("joints: {position: positions}\n")
    _bad(tmp_path, capsys, [str(bag), "--map", str(tmp_path / "m2.yaml")],
         "joints.position: sensor_msgs/msg/JointState on /joint_states has no field 'positions' (fields: header, name, "
         "position, velocity, effort)")
    (tmp_path / "m3.yaml").write_text("torque: {topic: /joint_states, feild: effort}\n")
    _bad(tmp_path, capsys, [str(bag), "--map", str(tmp_path / "m3.yaml")], "'torque' has unknown key(s) ['feild']")
    (tmp_path / "m4.yaml").write_text("joints: {sign: [1, -1, 2]}\n")
    _bad(tmp_path, capsys, [str(bag), "--map", str(tmp_path / "m4.yaml")], "'joints.sign' entries must be 1 or -1")
    # a topic with no messages; a non-CDR topic
    with Writer(tmp_path / "empty_imu", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/joint_states", M.JOINT_STATE, typestore=M.typestore())
        w.add_connection("/imu", M.IMU, typestore=M.typestore())
        w.write(c, EPOCH_NS, M.serialize(M.joint_state(EPOCH_NS, [0, 0, 0], [0, 0, 0], [0, 0, 0])))
    _bad(tmp_path, capsys, [str(tmp_path / "empty_imu")], "topic /imu (IMU) has no messages")
    with Writer(tmp_path / "json_bag", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        w.add_connection("/joint_states", M.JOINT_STATE, typestore=M.typestore())
        w.add_connection("/imu", M.IMU, typestore=M.typestore(), serialization_format="json")
    _bad(tmp_path, capsys, [str(tmp_path / "json_bag")], "topic /imu is serialized as 'json', not CDR")
    # a folder without metadata.yaml; a project recording given as a bag; a MCAP cut short
    (tmp_path / "nometa").mkdir()
    (tmp_path / "nometa" / "nometa.mcap").write_bytes((bag / "bag.mcap").read_bytes())
    _bad(tmp_path, capsys, [str(tmp_path / "nometa")], "folder without metadata.yaml: not a rosbag2 bag")
    write_recording(tmp_path / "ours.mcap", native(short_run))
    _bad(tmp_path, capsys, [str(tmp_path / "ours.mcap")], "is a project recording (JSON messages), not a ROS 2 bag")
    data = (bag / "bag.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[:len(data) * 2 // 3])
    _bad(tmp_path, capsys, [str(tmp_path / "cut.mcap")], "cut.mcap: MCAP file is truncated (no footer")
    _bad(tmp_path, capsys, [str(tmp_path / "cut.mcap"), "--allow-truncated"], "MCAP file cut short before its first "
         "channel")  # rosbags' writer keeps its channels in the chunk that was cut
    _bad(tmp_path, capsys, [str(tmp_path / "m1.yaml")], "not a ROS 2 bag (expected a rosbag2 folder")


def test_a_map_puts_another_layout_right(tmp_path, capsys, short_run):
    """Joint names and signs, IMU mounted upside down (rpy pi, 0, 0) with gravity removed: the map undoes both."""
    names = ["wheel_r_joint", "wheel_l_joint", "turret_joint"]
    flipped = Recording(t=short_run.t, torque=short_run.torque * [1, -1, 1],
                        joint_pos=short_run.joint_pos * [1, -1, 1], joint_vel=short_run.joint_vel * [1, -1, 1],
                        imu_accel=(short_run.imu_accel - [0, 0, 9.80665]) * [1, -1, -1],
                        imu_gyro=short_run.imu_gyro * [1, -1, -1])
    mapped = {"right_wheel": "wheel_r_joint", "left_wheel": "wheel_l_joint", "pivot": "turret_joint"}
    bag = robot_bag(tmp_path / "bag", flipped, names=[mapped[n] for n in ("pivot", "left_wheel", "right_wheel")],
                    imu_jitter=False, robot_names=mapped)
    (tmp_path / "map.yaml").write_text(
        "joints: {names: [wheel_r_joint, wheel_l_joint, turret_joint], sign: [1, -1, 1]}\n"
        "imu: {rpy: [3.141592653589793, 0, 0], gravity: removed}\n")
    assert main(["import", str(bag), "--map", str(tmp_path / "map.yaml"), "--out", str(tmp_path / "o.mcap"),
                 "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert "rotated into B'' by rpy" in rep["conversion"] and "+g added on z" in rep["conversion"]
    rec = read_recording(tmp_path / "o.mcap")
    nat = native(short_run)
    np.testing.assert_allclose(rec.joint_pos, nat.joint_pos, atol=1e-12)
    np.testing.assert_allclose(rec.torque, nat.torque, atol=1e-12)
    assert np.sqrt(np.mean((rec.imu_accel - nat.imu_accel) ** 2)) < 0.05
    assert np.mean(rec.imu_accel[:, 2]) == pytest.approx(9.80665, abs=0.05)


def test_the_example_map_is_the_default():
    from otbot_hw.ros2.mapping import BagMap, load_map

    ex = load_map(Path(__file__).resolve().parents[1] / "config" / "ros2_map.yaml")
    d = BagMap()
    assert {k: v for k, v in ex.to_dict().items() if k != "source"} == {k: v for k, v in d.to_dict().items()
                                                                        if k != "source"}


def test_without_the_ros2_extra_import_and_export_say_what_to_install(monkeypatch, tmp_path, capsys):
    import sys

    from otbot_hw.ros2.messages import typestore

    write_recording(tmp_path / "run.mcap", full_recording(n=10))
    typestore.cache_clear()
    for mod in ("rosbags", "rosbags.typesys", "rosbags.rosbag2"):
        monkeypatch.setitem(sys.modules, mod, None)
    try:
        for argv in (["export", str(tmp_path / "run.mcap"), "--ros2", str(tmp_path / "bag")],
                     ["import", str(tmp_path), "--out", str(tmp_path / "o.mcap")]):
            assert main(argv) == 2
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and "pip install 'otbot-hw[ros2]'" in err, err
        assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]
    finally:
        typestore.cache_clear()


def test_a_grid_slower_than_the_commands_is_said(tmp_path, capsys, short_run):
    bag = robot_bag(tmp_path / "bag", short_run)
    rc, out = _import(tmp_path, bag, "--rate", "100", "--json")
    rep = json.loads(capsys.readouterr().out)
    assert rc == 0 and rep["rate_hz"] == 100.0
    assert any("the torque commands come at 200 Hz and change faster than the 100 Hz grid" in n
               for n in rep["notices"]), rep["notices"]
    rec = read_recording(out)
    nat = native(short_run)
    assert np.array_equal(rec.torque, nat.torque[::2])  # held: the command in force at each grid time
    rc, out = _import(tmp_path, bag, "--json")
    assert not any("torque commands" in n for n in json.loads(capsys.readouterr().out)["notices"])


#: the fields of the standard ROS 2 message files (common_interfaces), as the bag's schemas must carry them
STANDARD_FIELDS = {
    M.JOINT_STATE: "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n",
    M.IMU: "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
           "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
           "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n",
    M.ODOMETRY: "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
                "geometry_msgs/TwistWithCovariance twist\n",
    M.DIAGNOSTIC_ARRAY: "std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status\n",
    M.TF: "geometry_msgs/TransformStamped[] transforms\n",
}


def test_exported_schemas_are_the_standard_message_files(tmp_path):
    from mcap.reader import make_reader

    from otbot_hw.ros2.bag_export import export_recording

    export_recording(full_recording(n=10), tmp_path / "bag")
    with open(tmp_path / "bag" / "bag.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    schemas = {s.name: s for s in summary.schemas.values()}
    for name, fields in STANDARD_FIELDS.items():
        assert schemas[name].encoding == "ros2msg"
        assert schemas[name].data.decode().split("=" * 80)[0] == fields, name
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}


def test_a_robots_own_base_link_odometry_is_not_taken_for_the_estimate(tmp_path, capsys):
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = M.typestore()
    with Writer(tmp_path / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        js = w.add_connection("/joint_states", M.JOINT_STATE, typestore=ts)
        od = w.add_connection("/odom", M.ODOMETRY, typestore=ts)
        for k in range(20):
            ns = EPOCH_NS + k * 10_000_000
            w.write(js, ns, M.serialize(M.joint_state(ns, [0.01 * k] * 3, [1.0] * 3, [0.5, -0.5, 0.1])))
            m = M.odometry(ns, [0.001 * k, 0, 0], [0.1, 0, 0], [0.01] * 6)
            m.child_frame_id = "base_link"
            w.write(od, ns, M.serialize(m))
    rc, out = _import(tmp_path, tmp_path / "bag", "--json")
    rep = json.loads(capsys.readouterr().out)
    assert rc == 0 and "/otbot/estimate" not in rep["channels"]
    assert any("/odom is the pose of frame 'base_link', not of the platform" in n for n in rep["notices"])
    assert read_recording(out).estimate_pose is None


# --- joint states split over messages (one per joint, as some drivers publish) ---------------------

def test_joint_states_split_per_joint_merge_into_the_same_recording(tmp_path, capsys, short_run):
    """Four JointState messages per cycle (one per joint, extra caster included, stamps alike or
    apart within the tolerance) import to the samples of the one-message bag, bit for bit."""
    whole = robot_bag(tmp_path / "whole", short_run)
    assert main(["import", str(whole), "--out", str(tmp_path / "whole.mcap")]) == 0
    capsys.readouterr()
    ref = read_recording(tmp_path / "whole.mcap")
    for name, kw in (("alike", {}), ("apart", {"split_offsets": {"left_wheel": 4e-4, "pivot": 9e-4}})):
        bag = robot_bag(tmp_path / name, short_run, split=True, **kw)
        assert main(["import", str(bag), "--out", str(tmp_path / f"{name}.mcap"), "--json"]) == 0
        rep = json.loads(capsys.readouterr().out)
        assert any("joints come in separate messages" in n for n in rep["notices"]), rep["notices"]
        rec = read_recording(tmp_path / f"{name}.mcap")
        assert len(rec) == len(ref) == len(native(short_run)), name
        for f in ("t", "torque", "joint_pos", "joint_vel"):
            assert np.array_equal(getattr(rec, f), getattr(ref, f)), (name, f)
        np.testing.assert_allclose(rec.imu_accel, ref.imu_accel, atol=1e-9)


@pytest.mark.parametrize("case, kwargs, expected", [
    ("a joint missing at a stamp", {"split_drop": ("pivot", 0.3)},
     "/joint_states: split joint states: no 'pivot' at stamp 0.300000 s"),
    ("stamps that disagree", {"split_offsets": {"pivot": 2.5e-3}},
     "/joint_states: split joint states disagree: 'pivot' is stamped 0.002500 s and 'right_wheel', 'left_wheel' "
     "0.000000 s, 2.500 ms apart, beyond the 1 ms tolerance (map joints.stamp_tolerance)"),
])
def test_split_joint_states_that_do_not_make_a_sample_are_refused(tmp_path, capsys, short_run, case, kwargs,
                                                                  expected):
    bag = robot_bag(tmp_path / "bag", short_run, split=True, **kwargs)
    rc, out = _import(tmp_path, bag)
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert expected in err, err
    assert not out.exists()


def test_a_wider_stamp_tolerance_in_the_map_merges_what_the_default_refuses(tmp_path, capsys, short_run):
    bag = robot_bag(tmp_path / "bag", short_run, split=True, split_offsets={"pivot": 2.5e-3})
    (tmp_path / "map.yaml").write_text("joints:\n  stamp_tolerance: 0.003\n")
    rc, out = _import(tmp_path, bag, "--map", str(tmp_path / "map.yaml"))
    assert rc == 0, capsys.readouterr().err
    rec = read_recording(out)
    np.testing.assert_array_equal(rec.joint_pos, native(short_run).joint_pos)
    (tmp_path / "map.yaml").write_text("joints:\n  stamp_tolerance: -1\n")
    _bad(tmp_path, capsys, [str(bag), "--map", str(tmp_path / "map.yaml")],
         "'joints.stamp_tolerance' must be a number of seconds in [0, 1], got -1")
