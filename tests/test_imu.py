"""Serial IMU: VectorNav ASCII parser, driver over a real pty against the simulated IMU,
mounting rotation, faults, config section and ``otbot imu parse``."""
from __future__ import annotations

import json
import time
from functools import reduce
from pathlib import Path

import numpy as np
import pytest

from drivers import vectornav as vn
from drivers.imu import ImuFault, VectorNavIMU
from drivers.imu_config import check_rotation, load_imu_config
from otbot_hw.params import ParameterError
from sim.imu import SimulatedIMU

DATA = Path(__file__).parent / "data"
ROBOT_YAML = Path(__file__).resolve().parents[1] / "config" / "robot.yaml"

# The VN-100 user manual's register-27 (YMR) example reply, UM001 §7.2.3, checksum *4F.
MANUAL_YMR = (b"$VNRRG,27,+006.380,+000.023,-001.953,+1.0640,-0.2531,+3.0614,+00.005,+00.344,"
              b"-09.758,-0.001222,-0.000450,-0.001218*4F\r\n")
MANUAL_VALUES = "+006.380,+000.023,-001.953,+1.0640,-0.2531,+3.0614,+00.005,+00.344,-09.758,-0.001222,-0.000450,-0.001218"


def rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def imu_sentence(k: float = 1.0) -> bytes:
    return vn.frame(vn.format_imu("VNIMU", (0.1 * k, -0.2 * k, 9.8), (0.01 * k, 0.0, -0.5)))


# -- checksums and framing ------------------------------------------------------------------
def test_checksum_matches_the_manuals_examples():
    # Every example command/response printed in the VN-100 manual, with its checksum.
    for body, cs in [("VNWRG,06,0", 0x6C), ("VNRRG,5", 0x46), ("VNRRG,5,9600", 0x65),
                     ("VNWRG,5,9600", 0x60), ("VNERR,03", 0x72), ("VNRRG,11", 0x73),
                     (MANUAL_YMR[1:MANUAL_YMR.index(b"*")].decode(), 0x4F)]:
        assert vn.checksum8(body.encode()) == cs, body
    rng = np.random.default_rng(1)
    for n in (0, 1, 2, 3, 7, 64, 255):
        data = rng.integers(0, 256, n).astype(np.uint8).tobytes()
        assert vn.checksum8(data) == reduce(lambda a, b: a ^ b, data, 0)
    assert vn.crc16(b"123456789") == 0x31C3  # CRC16-CCITT (XModem) check value


def test_manual_register_reply_parses_as_sentence():
    p = vn.SentenceParser()
    (s,) = p.feed(MANUAL_YMR)
    assert isinstance(s, vn.Sentence) and s.header == "VNRRG" and s.checked
    assert s.fields[0] == "27" and ",".join(s.fields[1:]) == MANUAL_VALUES
    assert p.stats.good == 1 and p.stats.records == 0


# -- decoding ---------------------------------------------------------------------------
def test_vnymr_fields_and_units():
    data = vn.frame("VNYMR," + MANUAL_VALUES)
    (r,) = vn.SentenceParser().feed(data)
    assert isinstance(r, vn.ImuRecord) and r.kind == "VNYMR"
    assert r.ypr == (6.380, 0.023, -1.953)  # deg
    assert r.mag == (1.0640, -0.2531, 3.0614)  # Gauss
    assert r.accel == (0.005, 0.344, -9.758)  # m/s^2: z reads -g with z down
    assert r.gyro == (-0.001222, -0.000450, -0.001218)  # rad/s
    assert r.temperature is None and r.pressure is None


def test_vnimu_fields_and_units():
    body = "VNIMU,+0.5141,+0.0516,+1.7407,-00.042,+00.052,-09.806,-0.001373,-0.000574,-0.000219,+25.7,+083.716"
    (r,) = vn.SentenceParser().feed(vn.frame(body))
    assert r.kind == "VNIMU"
    assert r.mag == (0.5141, 0.0516, 1.7407)
    assert r.accel == (-0.042, 0.052, -9.806)
    assert r.gyro == (-0.001373, -0.000574, -0.000219)
    assert r.temperature == 25.7 and r.pressure == 83.716 and r.ypr is None


def test_format_then_parse_round_trip_within_print_resolution():
    rng = np.random.default_rng(7)
    for kind in ("VNIMU", "VNYMR"):
        for _ in range(50):
            a, g = rng.normal(0, 20, 3), rng.normal(0, 3, 3)
            (r,) = vn.SentenceParser().feed(vn.frame(vn.format_imu(kind, a, g)))
            assert np.abs(np.array(r.accel) - a).max() <= 0.5e-3 + 1e-12
            assert np.abs(np.array(r.gyro) - g).max() <= 0.5e-6 + 1e-12


# -- rejection and resynchronization ------------------------------------------------------
def test_bad_checksum_rejected_counted_and_stream_continues():
    good = imu_sentence(1)
    star = good.index(b"*")
    body_flip = good[:10] + bytes([good[10] ^ 0x01]) + good[11:]  # one bit flipped in a field
    wrong_digits = good[:star + 1] + b"00\r\n" if good[star + 1:star + 3] != b"00" else good[:star + 1] + b"01\r\n"
    p = vn.SentenceParser()
    out = p.feed(body_flip + wrong_digits + b"$VNIMU,1*ZZ\r\n" + imu_sentence(2))
    assert [r.accel[0] for r in out] == [0.2]
    assert p.stats.bad_checksum == 3 and p.stats.good == 1 and p.stats.truncated == 0


def test_truncated_sentences_rejected_counted():
    s1, s2 = imu_sentence(1), imu_sentence(2)
    p = vn.SentenceParser()
    out = p.feed(s1[:40] + s2)  # bytes lost: the next '$' arrives before the end
    out += p.feed(s1[:s1.index(b"*")] + b"\r\n")  # line ends before the checksum
    out += p.feed(s1[:s1.index(b"*") + 2] + b"\r\n")  # only one checksum digit
    out += p.feed(s2[:30])  # stream ends inside a sentence
    assert [r.accel[0] for r in out] == [0.2]
    assert p.stats.truncated == 3
    p.finish()
    assert p.stats.truncated == 4 and p.stats.good == 1


def test_garbage_between_sentences_skipped_and_counted():
    junk = bytes([0x00, 0xFF, 0x13, 0x37]) + b"hello"
    p = vn.SentenceParser()
    out = p.feed(junk + imu_sentence(1) + b"\r\n\r\n" + junk + imu_sentence(2) + junk)
    p.finish()
    assert [r.accel[0] for r in out] == [0.1, 0.2]
    assert p.stats.garbage_bytes == 3 * len(junk)  # blank lines are not garbage
    assert p.stats.good == 2 and p.stats.bad_checksum == 0 and p.stats.truncated == 0


def test_overlong_line_without_end_is_dropped_and_parser_resyncs():
    p = vn.SentenceParser()
    out = p.feed(b"$VNIMU," + b"1" * 400)
    assert out == [] and p.stats.truncated == 1 and p.stats.garbage_bytes == 0
    out = p.feed(b"222\r\n" + imu_sentence(3))
    assert [r.accel[0] for r in out] == [pytest.approx(0.3)]
    assert p.stats.truncated == 1 and p.stats.garbage_bytes == 3


def test_split_across_reads_gives_the_same_result():
    stream = (b"xx" + imu_sentence(1) + vn.frame("VNYMR," + MANUAL_VALUES) + imu_sentence(2)[:50]
              + imu_sentence(3) + b"\x00\x01" + vn.frame("VNWRG,07,100") + imu_sentence(4))
    whole, stats = vn.parse_bytes(stream)
    rng = np.random.default_rng(3)
    for chunking in ("bytes", "random"):
        p = vn.SentenceParser()
        got = []
        i = 0
        while i < len(stream):
            n = 1 if chunking == "bytes" else int(rng.integers(1, 40))
            got += p.feed(stream[i:i + n])
            i += n
        p.finish()
        assert got == whole
        assert p.stats == stats
    assert [type(x).__name__ for x in whole] == ["ImuRecord", "ImuRecord", "ImuRecord", "Sentence", "ImuRecord"]
    assert stats.garbage_bytes == 4 and stats.truncated == 1
    assert whole[1].offset == 2 + len(imu_sentence(1))


def test_unchecked_xx_accepted_lowercase_is_not():
    p = vn.SentenceParser()
    out = p.feed(b"$VNRRG,1*XX\r\n$VNWRG,75,2,8,01,0128*XXXX\r\n" + vn.frame("VNIMU,1,2,3,4,5,6,7,8,9,10,11", "unchecked"))
    assert [getattr(x, "checked") for x in out] == [False, False, False]
    assert out[2].accel == (4.0, 5.0, 6.0) and out[2].gyro == (7.0, 8.0, 9.0)
    assert p.stats.unchecked == 3 and p.stats.good == 3
    assert p.feed(b"$VNRRG,1*xx\r\n") == [] and p.stats.bad_checksum == 1


def test_crc16_sentences_checked():
    good = vn.frame("VNWRG,07,40", "crc")
    assert len(good.split(b"*")[1].strip()) == 4
    p = vn.SentenceParser()
    assert len(p.feed(good)) == 1
    bad = good.replace(b"07,40", b"07,50")
    assert p.feed(bad) == [] and p.stats.bad_checksum == 1


@pytest.mark.parametrize("body", ["VNIMU,1,2,3", "VNYMR,1,2,3,4,5,6,7,8,9,10,11,12,13",
                                  "VNIMU,1,2,3,4,5,6,7,x,9,10,11", "VNIMU,1,2,3,4,nan,6,7,8,9,10,11",
                                  "VNimu,1", "GPGGA,1"])
def test_malformed_sentences_with_good_checksum_rejected(body):
    p = vn.SentenceParser()
    assert p.feed(vn.frame(body) + imu_sentence(1))[0].accel[0] == 0.1
    assert p.stats.malformed == 1 and p.stats.bad_checksum == 0 and p.stats.good == 1


def test_device_error_text():
    (e,) = vn.SentenceParser().feed(b"$VNERR,03*72\r\n")
    assert vn.device_error_text(e) == "VNERR 03 (invalid checksum)"
    (e,) = vn.SentenceParser().feed(vn.frame("VNERR,0C"))
    assert "insufficient baud rate" in vn.device_error_text(e)


# -- driver against the simulated IMU over a real pty --------------------------------------
@pytest.fixture
def rig():
    sims, imus = [], []

    def make(mounting=None, sim_mounting=None, timeout=0.3, output="VNOFF", baudrate=115200, **kw):
        sim = SimulatedIMU(output=output, mounting=sim_mounting, **kw)
        imu = VectorNavIMU(sim.port, baudrate, mounting=mounting, timeout=timeout)
        sims.append(sim)
        imus.append(imu)
        imu.open()
        return sim, imu

    yield make
    for imu in imus:
        imu.close()
    for sim in sims:
        sim.close()


def test_configure_writes_registers_6_and_7_and_verifies_replies(rig):
    sim, imu = rig(baudrate=230400)
    assert sim.output is None
    imu.configure("VNIMU", 50)
    assert (sim.output, sim.rate_hz) == ("VNIMU", 50)
    assert sim.commands[-2:] == ["VNWRG,06,19", "VNWRG,07,50"]
    assert imu.read_register(6) == ("19",) and imu.read_register(7) == ("50",)
    imu.configure("VNYMR", 100)
    assert (sim.output, sim.rate_hz) == ("VNYMR", 100)
    assert imu.read_register(1) == ("VN-100-SIM",)


def test_configure_rejections(rig):
    sim, imu = rig()
    n = len(sim.commands)
    with pytest.raises(ValueError, match="rate_hz"):
        imu.configure("VNIMU", 3)
    with pytest.raises(ValueError, match="output"):
        imu.configure("VNYPR", 10)
    with pytest.raises(ValueError, match="baud"):
        imu.configure("VNIMU", 200)  # ~105 bytes * 10 bit * 200 Hz > 115200 bit/s
    with pytest.raises(ValueError, match="baud"):
        imu.configure("VNYMR", 100)  # 116 bytes * 10 bit * 100 Hz > 115200 bit/s
    assert len(sim.commands) == n  # nothing was sent
    with pytest.raises(ImuFault, match="invalid parameter"):
        imu.write_register(7, 3)  # the device refuses a rate it does not have
    with pytest.raises(ImuFault, match="invalid register"):
        imu.write_register(42, 1)
    assert sim.rate_hz == 40


def test_configure_detects_a_wrong_echo(rig, monkeypatch):
    sim, imu = rig()
    # a device that answers register writes with some other value than the one written
    monkeypatch.setattr(sim, "_write_register", lambda fields: sim._send(vn.frame(f"VNWRG,{fields[0]},1")))
    with pytest.raises(ImuFault, match="echoed"):
        imu.configure("VNIMU", 100)


def test_port_cannot_be_opened_twice(rig):
    sim, imu = rig()
    with pytest.raises(ImuFault, match="cannot open"):
        VectorNavIMU(sim.port).open()


def test_configure_without_answer_is_a_fault(rig):
    sim, imu = rig(timeout=0.15)
    sim.silent = True
    t0 = time.monotonic()
    with pytest.raises(ImuFault, match="no reply"):
        imu.configure("VNIMU", 100)
    assert 0.14 < time.monotonic() - t0 < 1.0


@pytest.mark.parametrize("output", ["VNIMU", "VNYMR"])
def test_samples_round_trip_identity_mounting(rig, output):
    sim, imu = rig(baudrate=921600)
    imu.configure(output, 100)
    rng = np.random.default_rng(11)
    for _ in range(20):
        a, g = rng.normal(0, 5, 3), rng.normal(0, 1, 3)
        t0 = time.monotonic()
        sim.publish(a, g)
        s = imu.read()
        assert s is not None and t0 <= s.t <= time.monotonic()
        assert s.accel.shape == (3,) and s.gyro.shape == (3,)
        np.testing.assert_allclose(s.accel, a, atol=0.5e-3 + 1e-12)
        np.testing.assert_allclose(s.gyro, g, atol=0.5e-6 + 1e-12)


def test_read_returns_the_latest_sample_and_polls_none(rig):
    sim, imu = rig()
    imu.configure("VNIMU", 100)
    for k in range(5):
        sim.publish([k, 0, 9.8], [0, 0, 0.1 * k])
    time.sleep(0.02)
    s = imu.read()
    assert s.accel[0] == 4.0 and s.gyro[2] == pytest.approx(0.4)
    assert imu.read(timeout=0) is None  # healthy, nothing new
    assert imu.stats.records == 5


def test_mounting_90deg_yaw_maps_sensor_x_to_platform_y(rig):
    sim, imu = rig(mounting=rot_z(90))
    imu.configure("VNIMU", 100)
    sim.publish([1.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    s = imu.read()
    np.testing.assert_allclose(s.accel, [0.0, 1.0, 0.0], atol=1e-12)
    sim.publish([0.0, 2.0, 9.81], [0.3, 0.0, 0.7])
    s = imu.read()
    np.testing.assert_allclose(s.accel, [-2.0, 0.0, 9.81], atol=1e-12)
    np.testing.assert_allclose(s.gyro, [0.0, 0.3, 0.7], atol=1e-12)


def test_platform_values_survive_sim_and_driver_with_any_mounting(rig):
    rng = np.random.default_rng(5)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    mounting = q * np.sign(np.linalg.det(q))  # a random proper rotation
    sim, imu = rig(mounting=mounting, sim_mounting=mounting)
    imu.configure("VNIMU", 100)
    a_b, w_b = np.array([0.4, -1.3, 9.80665]), np.array([0.0, 0.0, 1.2])
    sent = sim.publish_platform(a_b, w_b)
    r = vn.parse_bytes(sent)[0][0]
    assert not np.allclose(r.accel, a_b, atol=0.1)  # the wire carries sensor-frame values
    s = imu.read()
    np.testing.assert_allclose(s.accel, a_b, atol=2e-3)
    np.testing.assert_allclose(s.gyro, w_b, atol=2e-6)


def test_publish_at_decimates_a_faster_plant_to_the_output_rate(rig):
    sim, imu = rig()
    imu.configure("VNIMU", 100)
    published = [bool(sim.publish_at(k * 1e-3, [k, 0, 9.8], [0, 0, 0])) for k in range(100)]  # 1 kHz, 0.1 s
    assert sum(published) == 10 and [k for k, p in enumerate(published) if p] == list(range(0, 100, 10))
    newest, deadline = None, time.monotonic() + 5  # the simulated IMU's thread writes them to the pty
    while imu.stats.records < 10 and time.monotonic() < deadline:
        newest = imu.read(timeout=0.05) or newest
    assert newest.accel[0] == 90.0 and imu.stats.records == 10


def test_driver_survives_garbage_bad_checksum_truncation(rig):
    sim, imu = rig()
    imu.configure("VNIMU", 100)
    sim.write_garbage(25, seed=1)
    sim.publish([1, 1, 1], [0, 0, 0], corrupt="checksum")
    sim.publish([2, 2, 2], [0, 0, 0], corrupt="truncate")
    sim.publish([3, 3, 3], [0, 0, 0])
    s = imu.read()
    assert s.accel[0] == 3.0
    st = imu.stats
    assert (st.garbage_bytes, st.bad_checksum, st.truncated, st.records) == (25, 1, 1, 1)


def test_silence_times_out_to_fault(rig):
    sim, imu = rig(timeout=0.2)
    imu.configure("VNIMU", 100)
    sim.publish([0, 0, 9.8], [0, 0, 0])
    assert imu.read() is not None
    sim.silent = True
    sim.publish([0, 0, 9.8], [0, 0, 0])  # not sent
    t0 = time.monotonic()
    assert imu.read(timeout=0.05) is None  # still within the watchdog
    with pytest.raises(ImuFault, match="no valid IMU sentence"):
        imu.read()
    assert 0.1 < time.monotonic() - t0 < 1.0
    sim.silent = False
    sim.publish([0, 0, 9.8], [0, 0, 0])
    assert imu.read() is not None  # recovers when data comes back


def test_only_garbage_is_not_data(rig):
    sim, imu = rig(timeout=0.2)
    imu.configure("VNIMU", 100)
    t0 = time.monotonic()
    with pytest.raises(ImuFault):
        for _ in range(100):
            sim.write_garbage(20)
            sim.publish([1, 2, 3], [0, 0, 0], corrupt="checksum")
            imu.read(timeout=0.01)
    assert time.monotonic() - t0 < 1.0 and imu.stats.bad_checksum > 5


def test_disconnected_port_is_a_fault(rig):
    sim, imu = rig()
    imu.configure("VNIMU", 100)
    sim.publish([0, 0, 9.8], [0, 0, 0])
    assert imu.read() is not None
    sim.disconnect()
    with pytest.raises(ImuFault, match="failed|disconnected"):
        imu.read()
    assert not imu.is_open
    with pytest.raises(ImuFault, match="not open"):
        imu.read()


def test_missing_port_and_bad_arguments():
    with pytest.raises(ImuFault, match="cannot open"):
        VectorNavIMU("/dev/does-not-exist-imu").open()
    with pytest.raises(ValueError, match="baudrate"):
        VectorNavIMU("/dev/null", baudrate=12345)
    with pytest.raises(ValueError, match="proper rotation"):
        VectorNavIMU("/dev/null", mounting=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="not a rotation"):
        VectorNavIMU("/dev/null", mounting=np.diag([1.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="3x3"):
        check_rotation(np.eye(2))


# -- configuration --------------------------------------------------------------------------
def test_default_config_loads():
    cfg = load_imu_config()
    assert cfg.protocol == "vectornav-ascii" and cfg.output in ("VNIMU", "VNYMR")
    assert cfg.rate_hz in vn.ASYNC_RATES_HZ
    np.testing.assert_allclose(cfg.mounting @ cfg.mounting.T, np.eye(3), atol=1e-12)
    # an upright VectorNav (z down, reads -g at rest) gives +g on the platform's z (up)
    np.testing.assert_allclose(cfg.mounting @ [0.0, 0.0, -9.80665], [0.0, 0.0, 9.80665], atol=1e-12)


def _write_config(tmp_path, **changes) -> Path:
    import yaml

    data = yaml.safe_load(ROBOT_YAML.read_text())
    for key, value in changes.items():
        if value is None:
            data["imu"].pop(key)
        else:
            data["imu"][key] = value
    p = tmp_path / "robot.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_config_mounting_90deg(tmp_path):
    m = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    cfg = load_imu_config(_write_config(tmp_path, mounting={"matrix": m}))
    np.testing.assert_allclose(cfg.mounting @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # 4 significant digits of a 45 deg rotation are accepted and re-orthonormalized
    h = 0.7071
    cfg = load_imu_config(_write_config(tmp_path, mounting={"matrix": [[h, -h, 0], [h, h, 0], [0, 0, 1]]}))
    np.testing.assert_allclose(cfg.mounting, rot_z(45), atol=1e-12)


@pytest.mark.parametrize("changes, match", [
    ({"mounting": {"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}}, "imu.mounting.matrix.*proper rotation"),
    ({"mounting": {"matrix": [[1, 0.1, 0], [0, 1, 0], [0, 0, 1]]}}, "imu.mounting.matrix.*not a rotation"),
    ({"mounting": {"matrix": [[1, 0, 0], [0, 1, 0]]}}, "imu.mounting.matrix"),
    ({"mounting": {"rpy": [0, 0, 90]}}, "imu.mounting.matrix"),
    ({"rate_hz": 30}, "imu.rate_hz"),
    ({"rate_hz": 200}, "imu.rate_hz.*baud"),
    ({"output": "VNQTN"}, "imu.output"),
    ({"protocol": "nmea"}, "imu.protocol"),
    ({"baudrate": 1234}, "imu.baudrate"),
    ({"port": None}, "imu.port"),
    ({"timeout": -1}, "imu.timeout"),
])
def test_config_errors_name_the_key(tmp_path, changes, match):
    with pytest.raises(ParameterError, match=match):
        load_imu_config(_write_config(tmp_path, **changes))


def test_config_missing_section(tmp_path):
    p = tmp_path / "robot.yaml"
    p.write_text("motors: {}\n")
    with pytest.raises(ParameterError, match="missing section 'imu'"):
        load_imu_config(p)


# -- CLI ----------------------------------------------------------------------------------
def test_cli_parse_capture_json(capsys):
    from otbot_hw.cli import main

    assert main(["imu", "parse", str(DATA / "imu_capture.bin"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    # see tests/data/make_imu_capture.py for what the capture holds
    assert out["errors"] == {"bad_checksum": 1, "truncated": 2, "malformed": 0, "garbage_bytes": 7,
                             "device_errors": 1}
    recs = out["records"]
    assert [r["type"] for r in recs] == ["VNIMU"] * 10 + ["VNYMR"] * 3
    ks = [0, 1, 2, 3, 4, 6, 7, 9, 10, 11]  # k = 5 bad checksum, k = 8 truncated
    for r, k in zip(recs[:10], ks):
        assert r["accel"] == pytest.approx([0.1 * k, -0.2 * k, 9.807], abs=1e-9)
        assert r["gyro"] == pytest.approx([0.003 * k, -0.001 * k, 0.5], abs=1e-9)
        assert r["temperature"] == 25.0 and r["pressure"] == 101.325 and r["ypr"] is None
    for j, r in enumerate(recs[10:]):
        assert r["accel"] == [1.0, 2.0, 3.0 + j] and r["ypr"] == [10.0 * j, 1.0, -2.0]
    assert [r["index"] for r in recs] == list(range(13))
    assert [(o["type"], o["fields"]) for o in out["other_sentences"]] == [
        ("VNWRG", ["06", "19"]), ("VNWRG", ["07", "50"]), ("VNWRG", ["06", "14"]), ("VNERR", ["07"])]


def test_cli_parse_text_and_bad_files(capsys, tmp_path):
    from otbot_hw.cli import main

    assert main(["imu", "parse", str(DATA / "imu_capture.bin"), "--limit", "2"]) == 0
    text = capsys.readouterr().out
    assert "13 IMU records" in text and "11 more records" in text and "bad_checksum 1" in text
    assert main(["imu", "parse", str(tmp_path / "missing.bin"), "--json"]) == 2
    assert "cannot read" in capsys.readouterr().err
    assert main(["imu", "parse", str(tmp_path), "--json"]) == 2
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    assert main(["imu", "parse", str(empty), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["record_count"] == 0


def test_cli_read_simulated_imu_at_rest(capsys):
    from otbot_hw.cli import main
    from otbot_hw.sensors import GRAVITY

    assert main(["imu", "read", "--sim", "--duration", "0.3", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["simulated"] and out["samples"] >= 10 and out["sentences"] >= out["samples"]
    # config mounting diag(1,-1,-1): the wire carries z = -g, the driver reports +g in B''
    assert out["accel_mean"] == pytest.approx([0.0, 0.0, GRAVITY], abs=0.015)
    assert out["gyro_mean"] == pytest.approx([0.0, 0.0, 0.0], abs=0.015)
    assert all(0.006 < s < 0.025 for s in out["accel_std"] + out["gyro_std"])  # paper sigma 13.7e-3
    assert out["errors"] == {"bad_checksum": 0, "truncated": 0, "malformed": 0, "garbage_bytes": 0}


def test_cli_read_bad_port_or_config(capsys, tmp_path):
    from otbot_hw.cli import main

    assert main(["imu", "read", "--port", str(tmp_path / "ttyNONE"), "--duration", "0.1"]) == 2
    assert "cannot open" in capsys.readouterr().err
    bad = _write_config(tmp_path, rate_hz=7)
    assert main(["imu", "read", "--config", str(bad), "--sim", "--json"]) == 2
    assert "imu.rate_hz" in capsys.readouterr().err


def test_cli_read_silent_device_exits_1(capsys):
    import os
    import tty

    from otbot_hw.cli import main

    master, slave = os.openpty()  # a port with nothing behind it
    tty.setraw(slave)
    try:
        with pytest.raises(SystemExit) as exc:
            main(["imu", "read", "--port", os.ttyname(slave), "--duration", "0.1"])
        assert exc.value.code == 1
        assert "no reply to $VNWRG,06,19" in capsys.readouterr().err
    finally:
        os.close(master)
        os.close(slave)


def test_simulator_answers_commands_like_the_device():
    import serial

    with SimulatedIMU(output="VNOFF") as sim:
        port = serial.Serial(sim.port, 115200, timeout=0.5)
        try:
            def ask(cmd: bytes) -> bytes:
                port.write(cmd)
                return port.readline()

            assert ask(b"$VNWRG,06,19*00\r\n") == b"$VNERR,03*72\r\n"  # wrong checksum
            assert ask(b"$VNWRG,06,19*XX\r\n") == vn.frame("VNWRG,06,19")  # checksum bypass
            assert ask(vn.write_register_command(7, 25)) == vn.frame("VNWRG,07,25")
            assert ask(vn.read_register_command(7)) == vn.frame("VNRRG,07,25")
            assert ask(b"$VNWRG,07*XX\r\n") == vn.frame("VNERR,05")  # not enough parameters
            assert ask(b"$VNWRG,07,25,1,9*XX\r\n") == vn.frame("VNERR,06")  # too many
            assert ask(b"$VNWRG,06,3*XX\r\n") == vn.frame("VNERR,07")  # an output the sim cannot make
            assert ask(b"$VNRRG,99*XX\r\n") == vn.frame("VNERR,08")  # invalid register
            assert ask(b"$VNXYZ,1*XX\r\n") == vn.frame("VNERR,04")  # invalid command
            assert (sim.output, sim.rate_hz) == ("VNIMU", 25)
            line = (sim.publish([0.0, 0.0, -9.8], [0.0, 0.0, 0.0]), port.readline())
            assert line[0] == line[1] and vn.parse_bytes(line[1])[0][0].accel == (0.0, 0.0, -9.8)
        finally:
            port.close()
    assert sim.closed and sim.publish([0, 0, 0], [0, 0, 0]) == b""
