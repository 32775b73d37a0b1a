"""``otbot daemon`` end to end (issue 14, item 7), judged from the simulated drives' and the plant's
own state, not from what the daemon believes.

* In-process, ``--bus sim`` (the plant behind virtual CAN in the daemon's process; one daemon shared
  by the tests in order): idle at start; enable; track corridor-smooth with EKF feedback within the
  documented bound, live in Foxglove; estop mid-run stops the plant's drives and latches; the
  velocity deadman ramps to rest; a fuzzed socket leaves it running and the robot held; overruns
  latch a fault; shutdown disables the drives and leaves loadable recordings.
* A daemon process, ``--bus sim``: systemd's READY/WATCHDOG/STATUS/STOPPING; SIGTERM gives exit 0
  and a loadable recording.
* A daemon process over slcan to ``otbot plant`` in its own process (``sim.plant_process.PlantProcess``,
  whose report gives the drives' own states): tracks with EKF feedback; estop stops the drives and
  latches; ``kill -9`` of the daemon is stopped by the drives' master-heartbeat consumer.

The e2e configuration allows 50 consecutive overruns (instead of 5), and over slcan heartbeat
consumer times of 1 s and 20 periods for a stale TPDO or a quick stop to be confirmed, so that a machine shared with other jobs does not stop these runs for
reasons they do not test; the overrun fault itself is tested with the daemon's own limit set back
to a few cycles, and kill -9 is judged against the consumer time the drives were given.
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import random
import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from otbot_hw.recording import read_recording
from otbot_hw.runtime.control_client import ControlClient, ControlError
from otbot_hw.runtime.daemon_process import DaemonProcess, local_config, plant_bus_args
from otbot_hw.sensors import NoiseModel

ENABLED = "OPERATION ENABLED"
#: Documented bound (docs/daemon.md): corridor-smooth tracked by the daemon at 100 Hz over the
#: simulated bus with EKF feedback: position and heading error of the true pose.
TRACK_BOUND_M, TRACK_BOUND_RAD = 0.005, 0.005
RELAXED = {"max_consecutive_overruns: {value: 5": "max_consecutive_overruns: {value: 50"}
#: ... and over slcan to a plant process, heartbeat consumer times of 1 s on both sides (as the bus
#: tests' plant process), instead of 100 ms (drives) and 200 ms (master): measured on the shared
#: machine, both processes together went 0.55 s without running at a CPU pressure of 98 %
#: (and with it, single SYNCs whose TPDOs came late: 20 periods of misses or of unconfirmed quick
#: stop, instead of 2, before a stale fault or an NMT STOP)
RELAXED_SLCAN = {**RELAXED, "master_heartbeat_consumer: {value: 100, unit: ms}": "master_heartbeat_consumer: {value: 1000, unit: ms}",
                 "heartbeat_consumer: {value: 200, unit: ms}": "heartbeat_consumer: {value: 1000, unit: ms}",
                 "tpdo_timeout: {value: 2, unit: periods}": "tpdo_timeout: {value: 20, unit: periods}",
                 "reaction_timeout: {value: 2, unit: periods}": "reaction_timeout: {value: 20, unit: periods}"}


def request(sock: Path, cmd: str, **args):
    with ControlClient(sock, timeout=10.0) as c:
        return c.request(cmd, args or None)


def wait_for(predicate, timeout: float, step: float = 0.01):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = predicate()
        if v:
            return v
        time.sleep(step)
    return predicate()


class SimDaemon:
    """The in-process daemon (``--bus sim``) and what the tests look at behind it."""

    def __init__(self, folder: Path, replace: dict | None = None):
        from otbot_hw.cli import build_parser
        from otbot_hw.cli.daemon import prepare

        self.folder = folder
        self.sock = folder / "control.sock"
        cfg = local_config(folder / "cfg", replace=RELAXED if replace is None else replace)
        (folder / "rec").mkdir()  # the daemon never creates it
        args = build_parser().parse_args(["daemon", "--bus", "sim", "--config", str(cfg), "--socket", str(self.sock),
                                          "--record-dir", str(folder / "rec"), "--telemetry", "127.0.0.1:0"])
        self.daemon, opener = prepare(args)
        self.at_exit: dict = {}
        self.summary: dict = {}

        @contextlib.contextmanager
        def spy():  # the plant's drives as the daemon leaves them, before the bus closes
            with opener() as robot:
                yield robot
                self.at_exit["states"] = [d.state for d in robot.plant.drives]
                self.at_exit["torque"] = [d.joint_torque() for d in robot.plant.drives]

        self.thread = threading.Thread(target=lambda: self.summary.update(self.daemon.serve(spy)), daemon=True)
        self.thread.start()
        assert wait_for(lambda: self.daemon.runner is not None and self.daemon.mode != "starting", 60, 0.05), \
            "the daemon did not start"

    def ctl(self, cmd: str, **args):
        return request(self.sock, cmd, **args)

    @property
    def plant(self):
        return self.daemon.robot.plant

    def drive_states(self) -> list[str]:
        return [d.state for d in self.plant.drives]

    def drive_torques(self) -> list[float]:
        return [d.joint_torque() for d in self.plant.drives]

    def true_speed(self) -> float:
        x = self.daemon.robot.truth()
        return float(math.hypot(x[6], x[7]))

    def recording(self):
        return read_recording(self.daemon.runner.recording.path)

    def to_hold_at_rest(self) -> None:
        """From any state: reset a fault, enable, wait until the hold has the robot at rest."""
        st = self.ctl("status")
        if st["faults"]:
            self.ctl("reset")
        if self.ctl("status")["mode"] == "idle":
            self.ctl("enable")
        elif st["mode"] != "hold":
            self.ctl("stop")

        def ready():
            try:
                return self.daemon._at_rest() and self.daemon.mode == "hold"
            except Exception:  # noqa: BLE001
                return False
        assert wait_for(ready, 10, 0.05), self.ctl("status")


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    d = SimDaemon(tmp_path_factory.mktemp("daemon"))
    yield d
    if d.thread.is_alive():
        d.daemon.request_stop("end of tests")
        d.thread.join(30)


STOPPED = {"QUICK STOP ACTIVE", "SWITCH ON DISABLED"}  # a quick-stopped drive, before / after its stop


def test_starts_idle_with_the_drives_unpowered_and_refuses_motion(sim):
    st = sim.ctl("status")
    assert st["mode"] == "idle" and st["faults"] == []
    assert set(st["drive_states"].values()) == {"SWITCH ON DISABLED"}
    assert ENABLED not in sim.drive_states()                              # the plant's own drives
    for cmd, args in (("track", {"target": "corridor-smooth"}), ("velocity", {"vx": 0.1, "vy": 0.0, "wz": 0.0}),
                      ("hold", {})):
        with pytest.raises(ControlError, match="enable first") as e:
            sim.ctl(cmd, **args)
        assert e.value.code == "refused"
    assert st["loop"]["rate"] == 100.0 and st["loop"]["cycles"] > 0 and st["recording"]["samples"] > 0
    assert st["pose"]["std"][0] < 0.01


def test_tracks_corridor_smooth_with_ekf_feedback_then_estop_stops_the_drives_and_latches(sim):
    from foxglove_client import FoxgloveClient

    sim.to_hold_at_rest()
    assert sim.drive_states() == [ENABLED] * 3
    with pytest.raises(ControlError, match="stop first|not at rest|tolerance") as e:  # a CSV far from here
        csv = sim.folder / "far.csv"
        csv.write_text("t,x,y,alpha\n0,5,5,0\n1,5.1,5,0\n")
        sim.ctl("track", target=str(csv))
    assert e.value.code == "refused"
    client = FoxgloveClient(sim.daemon.telemetry.url)
    try:
        client.subscribe({"/tf", "/otbot/status"})
        reply = sim.ctl("track", target="corridor-smooth")
        assert reply["mode"] == "track" and reply["duration_s"] > 30
        msgs = client.messages(quiet=1.5, duration=2.0)  # the stream may start late on a busy machine
    finally:
        client.close()
    modes = [m.get("mode") for topic, _, m in msgs if topic == "/otbot/status"]
    xs = [tf.translation.x for topic, _, m in msgs if topic == "/tf" for tf in m.transforms
          if tf.child_frame_id == "platform"]
    assert "track" in modes and len(xs) > 10 and xs[-1] > xs[0] + 0.005  # the pose moves in Foxglove
    time.sleep(3.5)                                                        # into the first corner's approach
    assert sim.true_speed() > 0.3                                          # moving when the estop comes
    stopped = {}

    def watch():  # the plant's drives, polled while the estop travels
        t_end = time.monotonic() + 2
        while time.monotonic() < t_end:
            if all(s != ENABLED for s in sim.drive_states()) and not any(sim.drive_torques()):
                stopped["t"] = time.monotonic()
                return
            time.sleep(0.0002)

    w = threading.Thread(target=watch)
    w.start()
    t_sent = time.monotonic()
    reply = sim.ctl("estop")
    w.join()
    assert reply["latched"] and reply["stopped"]
    latency = stopped["t"] - t_sent
    assert latency < 0.08, f"drives stopped {latency * 1e3:.1f} ms after the estop was sent"
    print(f"estop -> all simulated drives stopped: {latency * 1e3:.1f} ms")
    st = sim.ctl("status")
    assert st["mode"] == "idle" and st["faults"][0]["kind"] == "estop"
    time.sleep(0.3)
    # latched; quick stop option 0x605A = 2 (config/robot.yaml): the stop, then SWITCH ON DISABLED
    assert set(sim.drive_states()) <= STOPPED and sim.drive_torques() == [0.0] * 3
    for cmd, args in (("enable", {}), ("track", {"target": "corridor-smooth"})):
        with pytest.raises(ControlError, match="reset first"):
            sim.ctl(cmd, **args)
    rec = sim.recording()
    t_track = next(e["t"] for e in rec.events if e["kind"] == "mode" and e["text"].startswith("track"))
    t_stop = next(e["t"] for e in rec.events if e["kind"] == "fault" and "estop" in e["text"])
    k = (rec.t > t_track + 0.05) & (rec.t < t_stop)
    assert k.sum() > 200                                                   # 4.5 s of wall time (a loaded machine: fewer)
    err = rec.truth_q[k, :3] - rec.reference_p[k]
    est = rec.estimate_pose[k] - rec.truth_q[k, :3]
    e_pos, e_alpha = np.hypot(err[:, 0], err[:, 1]).max(), np.abs(err[:, 2]).max()
    print(f"tracking error of the true pose: {e_pos * 1e3:.2f} mm, {e_alpha * 1e3:.2f} mrad; estimation "
          f"{np.hypot(est[:, 0], est[:, 1]).max() * 1e3:.2f} mm")
    assert e_pos < TRACK_BOUND_M and e_alpha < TRACK_BOUND_RAD
    assert np.hypot(est[:, 0], est[:, 1]).max() < TRACK_BOUND_M
    assert np.ptp(rec.reference_p[k, 0]) > 0.5                             # it did travel the corridor


def test_velocity_deadman_ramps_to_rest_and_holds(sim):
    sim.to_hold_at_rest()
    dead = sim.daemon.settings.daemon.velocity
    t_end = time.monotonic() + 1.2
    while True:
        assert sim.ctl("velocity", vx=0.3, vy=0.0, wz=0.0)["mode"] == "velocity"
        t_last = time.monotonic()                                          # the last command has arrived
        if t_last > t_end:
            break
        time.sleep(0.1)
    trace = []
    while time.monotonic() < t_last + dead.deadman + 0.4:
        trace.append((time.monotonic() - t_last, sim.true_speed(), sim.daemon.mode))
        time.sleep(0.01)
    assert trace[0][1] > 0.25                                              # moving at the commanded twist
    assert min(v for a, v, _ in trace if a < dead.deadman - 0.1) > 0.25    # no stop before the deadman
    held = [a for a, _, m in trace if m == "hold"]
    assert held and dead.deadman - 0.05 < held[0] < dead.deadman + 0.3    # wall time: the deadman fired on time
    # the ramp runs in loop time (one plant period per cycle), however the machine delays the cycles
    ramp = 1.5 * 0.3 / dead.max_acceleration
    rec = sim.recording()
    t_d = next(e["t"] for e in reversed(rec.events) if e["kind"] == "mode" and "deadman" in e["text"])
    rec = wait_for(lambda: (r := sim.recording()).t[-1] > t_d + ramp + 1.0 and r, 10, 0.2)
    speed = np.hypot(rec.truth_qd[:, 0], rec.truth_qd[:, 1])
    assert speed[(rec.t > t_d - 0.3) & (rec.t < t_d)].min() > 0.25
    assert speed[rec.t > t_d + ramp + 0.5].max() < 0.01                    # ramped to rest, then held
    t0 = next(e["t"] for e in reversed(rec.events) if e["kind"] == "mode" and e["text"].startswith("velocity"))
    k = rec.t >= t0
    dv = np.abs(np.diff(rec.reference_pd[k, :2], axis=0)).max()
    assert dv <= dead.max_acceleration * 0.01 * 1.01 + 1e-9                # bumpless, within the limit
    assert np.abs(np.diff(rec.reference_p[k, :2], axis=0)).max() < 0.3 * 0.01 * 1.01   # no jump of the pose


def test_a_fuzzed_socket_leaves_the_daemon_running_and_the_robot_held(sim):
    sim.to_hold_at_rest()
    cycles0 = sim.ctl("status")["loop"]["cycles"]
    rng = random.Random(14)

    def raw(payload: bytes, read: bool = True):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(2)
        try:
            s.connect(str(sim.sock))
            s.sendall(payload)
            if read:
                with contextlib.suppress(OSError):
                    s.recv(65536)
        except OSError:
            pass
        finally:
            s.close()

    junk = [bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 3000))) for _ in range(20)]
    half = [b'{"id": 1, "cmd": "velo', b'{"id": 2, "cmd": "estop"', b'{"id": 3, "args": {"vx": 1e999']
    bad = [b'{"id": 4, "cmd": "velocity", "args": {"vx": NaN, "vy": 0, "wz": 0}}\n',
           b'{"id": 5, "cmd": "velocity", "args": {"vx": 9, "vy": 0, "wz": 0}}\n',
           b'{"id": 6, "cmd": "rm -rf /"}\n', b'[1, 2, 3]\n', b'{"id": {"a": 1}, "cmd": "status"}\n',
           b'{"id": 7, "cmd": "track", "args": {"target": "../../etc/passwd"}}\n',
           b'{"id": 8, "cmd": "excite", "args": {"path": "/dev/zero.csv"}}\n', b"\xff\xfe\n" * 50]
    threads = [threading.Thread(target=raw, args=(p,)) for p in junk + bad]
    threads += [threading.Thread(target=raw, args=(p, False)) for p in half]
    threads += [threading.Thread(target=raw, args=(b"x" * (1 << 20) + b"\n",))]            # a 1 MB line
    threads += [threading.Thread(target=raw, args=(b'{"id": 9, "cmd": "status"}\n',)) for _ in range(50)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    st = sim.ctl("status")
    assert st["mode"] == "hold" and st["faults"] == []
    cycles1 = st["loop"]["cycles"]
    assert cycles1 > cycles0                                                # it ran through the fuzz
    assert wait_for(lambda: sim.ctl("status")["loop"]["cycles"] > cycles1 + 20, 5)  # and keeps running
    assert sim.drive_states() == [ENABLED] * 3 and sim.true_speed() < 0.01  # held, at rest
    assert sim.daemon.server.counters["errors"] >= len(bad)


def test_overruns_at_rest_are_counted_warnings_and_while_moving_a_fault_that_quick_stops(sim, monkeypatch):
    """The overrun rule (docs/daemon.md): held at rest, a streak of overruns is a warning with a count
    (the drives stay enabled, ``stop`` is not refused); in velocity mode the same streak latches."""
    sim.to_hold_at_rest()
    d = sim.daemon
    sup = d.runner.supervisor
    monkeypatch.setattr(sup, "config", dataclasses.replace(sup.config, max_consecutive_overruns=3))
    slow = {"n": 0}
    after = d._after_cycle

    def slow_cycle():  # the loop's own work takes 2.5 periods, 20 cycles in a row
        after()
        if slow["n"] < 20:
            slow["n"] += 1
            time.sleep(0.025)
    warnings0 = sim.ctl("status")["overrun_warnings"]
    monkeypatch.setattr(d, "_after_cycle", slow_cycle)
    assert wait_for(lambda: slow["n"] >= 20, 5)
    st = sim.ctl("status")
    assert d.runner.fault is None and st["faults"] == [] and st["mode"] == "hold", st
    assert st["overrun_warnings"] >= warnings0 + 15                          # counted, not latched
    assert sim.drive_states() == [ENABLED] * 3
    assert sim.ctl("stop")["mode"] == "hold"                                 # not refused
    sim.ctl("velocity", vx=0.05, vy=0.0, wz=0.0)                             # moving: the same streak
    slow["n"] = 0
    assert wait_for(lambda: d.runner.fault is not None, 5)
    assert d.runner.fault.kind == "overrun"
    assert wait_for(lambda: set(sim.drive_states()) <= STOPPED, 1)
    assert sim.drive_torques() == [0.0] * 3
    monkeypatch.undo()
    assert sim.ctl("reset")["mode"] == "idle" and sim.ctl("status")["faults"] == []


def test_excite_plays_the_torques_then_holds_and_record_restarts_the_session(sim):
    sim.to_hold_at_rest()
    bad = sim.folder / "bad.csv"
    bad.write_text("t,tau_r,tau_l\n0,1,1\n")
    with pytest.raises(ControlError, match="missing column") as e:
        sim.ctl("excite", path=str(bad))
    assert e.value.code == "bad_request" and sim.ctl("status")["mode"] == "hold"
    rows = [(0.0, 3.0, 3.0, 0.0), (0.2, -3.0, -3.0, 0.5), (0.4, 0.0, 0.0, -0.5)]
    f = sim.folder / "excite.csv"
    f.write_text("t,tau_r,tau_l,tau_p\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    assert sim.ctl("excite", path=str(f))["rows"] == 3
    assert sim.ctl("status")["mode"] == "excite"
    with pytest.raises(ControlError, match="stop first"):
        sim.ctl("track", target="corridor-smooth")
    assert wait_for(lambda: sim.daemon.mode == "hold", 5)                  # the sequence ended: hold
    first = sim.daemon.runner.recording.path
    stopped = sim.ctl("record", action="stop")["recording"]
    assert stopped["closed"] and stopped["path"] == str(first)
    assert sim.ctl("status")["recording"] is None
    rec = read_recording(first)
    assert not rec.truncated                                               # closed: complete
    t0 = next(e["t"] for e in reversed(rec.events) if e["kind"] == "mode" and e["text"].startswith("excite"))
    for start, *u in rows:                                                 # every row was applied as written
        k = (rec.t > t0 + start + 0.015) & (rec.t < t0 + start + 0.19)
        np.testing.assert_allclose(rec.torque[k], np.tile(u, (k.sum(), 1)), atol=0.02)   # drives' per-mille
    started = sim.ctl("record", action="start")["recording"]
    assert started["path"] != str(first) and started["index"] == 0
    with pytest.raises(ControlError, match="already recording"):
        sim.ctl("record", action="start")


def test_shutdown_quick_stops_disables_and_leaves_loadable_recordings(sim):
    sim.to_hold_at_rest()
    assert sim.ctl("shutdown") == {"stopping": True}
    sim.thread.join(30)
    assert not sim.thread.is_alive()
    assert sim.at_exit["states"] == ["SWITCH ON DISABLED"] * 3 and sim.at_exit["torque"] == [0.0] * 3
    assert sim.summary["stopped"].startswith("shutdown") and sim.summary["faults_seen"] >= 2
    assert not sim.sock.exists()
    assert len(sim.summary["sessions"]) == 2                               # record stop / start
    recs = [read_recording(f) for s in sim.summary["sessions"] for f in sorted((sim.folder / "rec").glob(f"{s}-*.mcap"))]
    assert len(recs) == 2 and not any(r.truncated for r in recs)
    assert recs[1].events[0]["kind"] == "mode" and recs[1].events[0]["text"].startswith("hold")  # says the mode
    rec = recs[0]
    assert rec.estimate_pose is not None and rec.reference_p is not None and rec.truth_q is not None
    assert np.all(np.isfinite(rec.estimate_pose)) and np.all(np.diff(rec.t) > 0)
    kinds = {e["kind"] for e in rec.events}
    texts = " | ".join(e["text"] for e in rec.events)
    assert {"mode", "fault"} <= kinds and "estop" in texts and "deadman" in texts and "overrun" in texts
    assert recs[1].events[-1]["text"].startswith("idle: stopped (shutdown")


# -- a daemon process ------------------------------------------------------------------------------
def test_daemon_process_notifies_systemd_and_sigterm_gives_exit_0_and_a_loadable_recording(tmp_path):
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify"))
    notify.settimeout(0.2)
    cfg = local_config(tmp_path / "cfg", replace=RELAXED)
    d = DaemonProcess(["--bus", "sim", "--config", str(cfg), "--record-dir", str(tmp_path / "rec"), "--no-telemetry"],
                      tmp_path / "control.sock", tmp_path / "daemon.log",
                      env={"NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "200000"})
    try:
        d.request("enable")
        time.sleep(0.6)
        code, summary = d.terminate()
    finally:
        d.kill()
    got = []
    with contextlib.suppress(TimeoutError, socket.timeout):
        while True:
            got.append(notify.recv(4096).decode())
    notify.close()
    assert code == 0, d.log()[-2000:]
    assert got[0].startswith("READY=1") and "STATUS=idle" in got[0]
    assert any(m.startswith("STATUS=hold") for m in got)
    pings = sum(m == "WATCHDOG=1" for m in got)
    assert pings >= 4                                                      # every 0.1 s while the loop ran
    assert got[-1].startswith("STOPPING=1") and "SIGTERM" in got[-1]
    assert summary["stopped"] == "SIGTERM" and summary["fault"] is None
    rec = read_recording(next((tmp_path / "rec").glob("*.mcap")))
    assert not rec.truncated and len(rec) > 20 and rec.events[-1]["text"] == "idle: stopped (SIGTERM)"
    assert rec.estimate_pose is not None and rec.reference_p is not None


# -- over slcan to a plant in its own process --------------------------------------------------------
@pytest.fixture(scope="module")
def slcan(tmp_path_factory):
    """``otbot plant`` in its own process (its report gives the drives' own states) and a daemon on it."""
    from drivers.config import load_robot_config
    from sim.plant_process import PlantProcess

    folder = tmp_path_factory.mktemp("slcan")
    cfg_path = local_config(folder / "cfg", replace=RELAXED_SLCAN)
    config = load_robot_config(cfg_path)
    with PlantProcess(config, noise=NoiseModel.paper()) as pp:
        d = DaemonProcess([*plant_bus_args(pp.info), "--config", str(cfg_path), "--record-dir", str(folder / "rec"),
                           "--no-telemetry"], folder / "control.sock", folder / "daemon.log")
        try:
            yield d, pp, config
        finally:
            d.kill()


def _moving(d, pp, seconds: float) -> dict:
    """Velocity mode at 0.3 m/s for ``seconds``; returns the plant's report while moving."""
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        d.request("velocity", vx=0.3, vy=0.0, wz=0.0)
        time.sleep(0.1)
    return pp.report()


def test_over_slcan_the_daemon_tracks_with_ekf_feedback_and_estop_stops_the_drives_and_latches(slcan):
    d, pp, config = slcan
    assert d.request("status")["mode"] == "idle"
    d.request("enable")
    assert wait_for(lambda: [x["state"] for x in pp.report()["drives"]] == [ENABLED] * 3, 2)
    time.sleep(0.3)
    t0 = d.request("track", target="corridor-smooth") and d.request("status")["t"]
    errors = []
    wall_end = time.monotonic() + 30
    st = d.request("status")
    while st["t"] < t0 + 3.0 and time.monotonic() < wall_end:              # 3 s of loop (= plant) time
        st = d.request("status")
        assert st["mode"] == "track" and not st["faults"], st
        errors.append(math.hypot(st["tracking_error"]["x"], st["tracking_error"]["y"]))
        time.sleep(0.05)
    assert st["pose"]["x"] ** 2 + st["pose"]["y"] ** 2 > 0.5 ** 2          # it travels
    assert max(errors) < TRACK_BOUND_M                                     # reference - EKF estimate
    before = pp.report()
    assert [x["state"] for x in before["drives"]] == [ENABLED] * 3 and any(x["torque_permille"] for x in before["drives"])
    t_sent = time.monotonic()
    reply = d.request("estop")
    after = pp.report(wait_stopped=True, timeout=2.0)
    assert reply["latched"] and reply["stopped"]
    worst = max(x["stopped_wall"] for x in after["drives"]) - t_sent
    print(f"over slcan: estop -> every simulated drive stopped {worst * 1e3:.1f} ms after it was sent")
    for x in after["drives"]:
        assert x["state"] != ENABLED and x["torque_permille"] == 0, after
    assert worst < 3 * config.bus.period + 0.05
    st = d.request("status")
    assert st["mode"] == "idle" and st["faults"][0]["kind"] == "estop"
    with pytest.raises(ControlError, match="reset first"):
        d.request("enable")
    time.sleep(0.3)
    # latched: still stopped (0x605A = 2: QUICK STOP ACTIVE during the ramp, then SWITCH ON DISABLED)
    assert all(x["state"] in STOPPED and x["torque_permille"] == 0 for x in pp.report()["drives"])
    d.request("reset")
    assert d.request("status")["faults"] == []


def test_over_slcan_kill_9_of_the_daemon_stops_the_motors_through_the_drives_heartbeat_consumer(slcan):
    d, pp, config = slcan
    st = d.request("status")
    if st["faults"]:
        d.request("reset")
    if d.request("status")["mode"] == "idle":
        d.request("enable")
    else:
        d.request("stop")
    assert wait_for(lambda: d.request("status")["mode"] == "hold", 10)
    before = _moving(d, pp, 1.0)
    assert [x["state"] for x in before["drives"]] == [ENABLED] * 3
    assert any(x["torque_permille"] for x in before["drives"])             # the motors work
    t_kill = time.monotonic()
    os.kill(d.pid, signal.SIGKILL)
    after = pp.report(wait_stopped=True, timeout=3.0)
    d.kill()
    consumer = max(dc.master_heartbeat_consumer for dc in config.drives)
    for x in after["drives"]:
        assert x["state"] != ENABLED and x["torque_permille"] == 0, after
        assert [a[0] for a in x["aborts"]] == [0x8130] and "heartbeat of the master" in x["aborts"][0][1], x
    first = min(x["stopped_wall"] for x in after["drives"]) - t_kill
    worst = max(x["stopped_wall"] for x in after["drives"]) - t_kill
    print(f"kill -9 -> every simulated drive stopped by itself {first * 1e3:.1f}-{worst * 1e3:.1f} ms later "
          f"(master heartbeat consumer {consumer * 1e3:.0f} ms)")
    # about the consumer time after the last heartbeat, which left at most one heartbeat period
    # before the kill on an idle machine (954 ms measured: the daemon's heartbeat thread is delayed
    # too when the machine is saturated); after it, as soon as the drive's own watchdog runs (a
    # thread of the plant process: 1.15 s measured at 98 % CPU pressure)
    assert consumer - 0.2 < first and worst < consumer + 0.5
