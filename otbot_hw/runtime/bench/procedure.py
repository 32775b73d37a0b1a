"""The bench procedure: the paper's identification experiments run through the loop and the drivers.

For each step (wheel on the stand, pivot with the wheels locked, chassis on the floor, platform
with its load; paper §4.3), attempt after attempt until its gates pass (at most ``attempts``):

1. **set-up**: the operator is told what to set up (``Operator.set_up``);
2. **checks before any torque**: a zero-torque run (0.5 s) through the loop runner: drives enabled
   and fault-free, IMU streaming, robot at rest (``checks``);
3. **limits**: the excitation's predicted motion on the best-known robot (the earlier steps'
   estimates; for the platform step without its load, the lightest robot it can be) within the
   experiment limits and the free area;
4. **fixture**: a small torque doublet; the sensors must show the step's fixture; then the brake
   (gains of the verified fixture) until the robot is at rest again (checked); a failed check
   says what is wrong and what to do, and the operator may fix it and check again;
5. **excitation**: the step's torques (the paper's or designed), then the brake, through the loop
   runner with the safety supervisor tightened to the experiment limits (``SafetyConfig.within``:
   joint rates, platform speed, the free area with the stopping distance; torques clipped to the
   experiment's) and on the floor the pose EKF for speed and travel. A violation or a fault stops
   the run: the recording up to it is kept and the session can be resumed;
6. **recording checks**: the applied torques are the planned ones (not saturated), no sensor clipped;
7. **identification**: ``identification.session.identify_session`` on the recordings of the passed
   steps and this one (each step fitted, then the joint fit of all; honest std); the step's quality
   gates decide pass or redo.

Then the session's final identification (``params.yaml`` with std), the mismatch finder
(``otbot_hw.diagnose``, as ``otbot diagnose`` runs it) on the session's recordings (the unloaded
robot's and the loaded platform's, each with its identified parameters), and the report.
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from otbot_hw.experiment_limits import ExperimentLimits
from otbot_hw.identification.errors import IdentificationError
from otbot_hw.identification.experiments import ExperimentSpec
from otbot_hw.identification.uncertainty import SESSION_PARAMS, robot_params, session_vector
from otbot_hw.json_output import json_safe
from otbot_hw.motors import MotorLimits
from otbot_hw.params import OtbotParams
from otbot_hw.recording import read_recording
from otbot_hw.robot import Robot, RobotError
from otbot_hw.robot import SimulatedRobot as SimulatedBackEnd
from otbot_hw.runtime.bench import checks as chk
from otbot_hw.runtime.bench.operator import NoOperator
from otbot_hw.runtime.bench.excitation import (PROBE, ExcitationController, brake_gains, predicted_margins,
                                               probe_torques, step_spec)
from otbot_hw.runtime.bench.session import SessionFolder
from otbot_hw.runtime.loop import LoopResult, LoopRunner
from otbot_hw.runtime.supervisor import SafetyConfig, Supervisor
from otbot_hw.sensors import NoiseModel

REST_TIME = 0.5       # s of the zero-torque run (and of the end of the settling run judged at rest)
BRAKE_TIME = 1.5      # s of braking after an excitation
PROBE_PAUSE = 0.1     # s of zero torque after the probe doublet
SETTLE_TIME = 2.5     # s of braking after the probe
UNKNOWN_COM = 0.05    # m: how far the chassis' centre of mass may lie from the file's (issue 21's prior)
UNKNOWN_INERTIA = 0.3  # fraction: how far the chassis' inertia may lie from the mass-scaled one
LIMIT_FILL = 0.95     # a designed excitation is scaled so that its peaks predicted on this robot stay below this
                      # fraction of each limit (the probe's mass estimate leaves the centres of mass unknown)
#: EMCY codes of the drives' communication watchdogs (CiA 301): SYNC timeout, life guard / heartbeat
WATCHDOG_CODES = (0x8100, 0x8130)
#: prior std of the unloaded platform's mass when nobody weighs it, as a fraction of the file's value (a CAD
#: mass may be off by tens of per cent)
UNWEIGHED_FRACTION = 0.2


@dataclass(frozen=True)
class BenchStep:
    """A step of the procedure: its fixture, whether the platform carries its load, what to set up."""

    name: str
    fixture: str
    loaded: bool
    setup: str

    def instructions(self, limits: ExperimentLimits) -> str:
        if self.fixture == "floor":
            return f"{self.setup}; clear a free area of {limits.travel_radius:g} m radius around the pivot"
        return self.setup


BENCH_STEPS: dict[str, BenchStep] = {
    "wheel": BenchStep("wheel", "stand", False, "put the robot on the stand (chassis held, both wheels free to "
                                               "spin, platform unloaded); keep hands away from the wheels"),
    "pivot": BenchStep("pivot", "locked", False, "lock both wheels (brake or chocks) so the chassis cannot move, "
                                                "platform unloaded and free to turn"),
    "chassis": BenchStep("chassis", "floor", False, "put the robot on the floor, wheels free, platform unloaded"),
    "platform": BenchStep("platform", "floor", True, "fix the load on the platform and put the robot on the floor, "
                                                    "wheels free"),
}


class BenchError(Exception):
    """Bad input found by a step (wrong fixture, robot that does not move, saturated or clipped data, a
    step that cannot identify its parameters): the CLI exits 2. The session is kept."""

    def __init__(self, step: str, reason: str):
        super().__init__(f"step {step}: {reason}")
        self.step = step
        self.reason = reason


class BenchAbort(Exception):
    """A run stopped by the safety supervisor or a fault (the CLI exits 1); recording and session kept."""

    def __init__(self, step: str, reason: str):
        super().__init__(f"step {step}: {reason}")
        self.step = step
        self.reason = reason


@dataclass
class BenchSettings:
    """What the procedure runs and how: ``steps`` in order, ``excitation`` paper/designed, at most
    ``attempts`` per step, experiment ``limits`` (its travel_radius is the free area), the ``safety``
    section, the motors' ``motor_limits``, ``params_start`` (the robot before the session, unloaded
    platform), the ``noise`` the sensors are stated to have (recorded; the fits' weights and the
    gates' Cramer-Rao bounds), the IMU's rate, ``diagnose`` (run the mismatch finder)."""

    steps: list[str]
    excitation: str
    attempts: int
    limits: ExperimentLimits
    safety: SafetyConfig
    motor_limits: MotorLimits
    params_start: OtbotParams
    noise: NoiseModel
    imu_rate: float | None
    diagnose: bool = True

    def to_dict(self) -> dict:
        return {"steps": list(self.steps), "excitation": self.excitation, "attempts": self.attempts,
                "limits": self.limits.to_dict(), "params_start": self.params_start.to_dict(),
                "noise": self.noise.to_dict()}


@dataclass
class SimulatedRobot:
    """What the bench knows about a simulated robot (for metadata and ``truth``): the unloaded robot's
    parameters and the load the simulated operator fixes for the platform step."""

    unloaded: OtbotParams
    load: tuple[float, float, float, float] | None = None
    effects: dict = field(default_factory=dict)

    @property
    def loaded(self) -> OtbotParams:
        return self.unloaded.with_load(*self.load) if self.load else self.unloaded

    def truth(self) -> dict[str, float]:
        return session_vector(self.unloaded, self.loaded)  # with the unloaded platform's m_p0, x_F0, y_F0


@dataclass
class _Timing:
    runs: float = 0.0
    robot_time: float = 0.0
    identification: float = 0.0
    diagnosis: float = 0.0


class BenchProcedure:
    """One invocation of the procedure on an opened ``robot`` (the ``Robot`` of a back end: the bus)."""

    def __init__(self, robot: Robot, settings: BenchSettings, session: SessionFolder, operator,
                 realtime: bool = False, progress: Callable[[str], None] | None = None,
                 sim: SimulatedRobot | None = None, metadata: dict | None = None):
        self.robot = robot
        self.s = settings
        self.session = session
        self.operator = operator
        self.realtime = realtime
        self.say = progress or (lambda m: None)
        self.sim = sim
        self.metadata = dict(metadata or {})
        self.period = float(robot.period)
        self.torque_limits = MotorLimits(np.minimum(np.asarray(settings.motor_limits.max_torque, dtype=float),
                                                    settings.limits.torque))
        self.timing = _Timing()
        self.result = None  # the latest SessionResult
        self.specs: dict[str, ExperimentSpec] = {}
        self.base_specs: dict[str, ExperimentSpec] = {}
        self.designs: dict[str, dict] = {}
        self.idle_resets: list = []
        self.notices: list[str] = []

    # -- the unloaded platform: what a floor run cannot tell -----------------------------------------
    def weigh(self) -> None:
        """The unloaded platform's mass m_p0, asked once per session (kept in session.json): a floor run
        sees only m_c + m_p0 (the regressor's two mass columns are the same), so either the operator
        weighs the platform, or m_p0 stays the file's with a prior std (``UNWEIGHED_FRACTION``) that the
        reported std of m_c and m_p carry (their sum and the load's mass are identified all the same)."""
        if not {"chassis", "platform"} & set(self.s.steps):
            return
        meas = self.session.data.setdefault("measurements", {})
        if "m_p0" in meas:
            return
        try:
            got = self.operator.weigh_platform(int(self.metadata.get("seed", 0)))
        except ValueError as exc:
            raise BenchError(self.s.steps[0], str(exc)) from None
        file_m = float(self.s.params_start.m_p)
        if got is None:
            got = {"value": file_m, "std": UNWEIGHED_FRACTION * file_m,
                   "source": f"not weighed: the parameter file's value with a prior std of {UNWEIGHED_FRACTION:.0%}"}
        meas["m_p0"] = got
        self.session.save()

    def start_params(self) -> OtbotParams:
        """The robot before the session: the start parameters with the weighed unloaded platform's mass."""
        m = self.session.data.get("measurements", {}).get("m_p0")
        return self.s.params_start.replace(m_p=float(m["value"])) if m else self.s.params_start

    def known_std(self) -> dict[str, float]:
        m = self.session.data.get("measurements", {}).get("m_p0")
        return {"m_p0": float(m["std"])} if m else {}

    # -- helpers -----------------------------------------------------------------------------------
    def best_params(self) -> OtbotParams:
        """The unloaded robot as known now: the start parameters with the passed steps' estimates."""
        if self.result is None:
            return self.start_params()
        return robot_params(self.result.values, self.start_params(), loaded=False)

    def spec(self, step: str) -> ExperimentSpec:
        """The step's excitation as run: the paper's or the designed one, the latter scaled to this robot
        (``fit_to_robot``; the scale is kept in session.json for a resumed session)."""
        if step not in self.specs:
            sp, rec = step_spec(step, self.s.excitation, self.s.params_start, self.s.limits,
                                [self.session.path / "designs"], progress=lambda m: self.say(f"[bench] {m}"))
            self.specs[step] = sp
            if rec is not None:
                self.designs[step] = {k: rec[k] for k in ("crb", "paper_crb", "crb_ratio", "margins", "paper_margins",
                                                          "source") if k in rec}
                d = self.session.path / "designs"
                d.mkdir(exist_ok=True)
                (d / f"{step}.json").write_text(json.dumps({k: v for k, v in rec.items() if k != "source"}))
            self.base_specs[step] = sp
            k = self.session.data.get("excitation_scale", {}).get(step)
            if k is not None:
                self.specs[step] = _scaled(sp, float(k))
        return self.specs[step]

    def fit_to_robot(self, step: str, probe, probe_u: np.ndarray, best: OtbotParams) -> chk.Check | None:
        """Floor steps, designed excitation: the design keeps the limits on the prior's corner robots (+-20 %),
        this robot may lie beyond. The probe's measured pivot speed against the one predicted for the
        best-known robot says how much heavier (or lighter) it is, rho = v_predicted / v_measured; the body
        that is still unknown (the chassis in step chassis, the loaded platform in step platform) is scaled so
        (mass and inertia), the excitation's peaks predicted on that robot (in step chassis also with its
        centre of mass moved by UNKNOWN_COM and its inertia by UNKNOWN_INERTIA, which a forward probe cannot
        tell), and the torques scaled down (speeds and travel go about linearly with them) until every peak
        is within LIMIT_FILL of its limit. None for the paper's excitation and the held fixtures."""
        from otbot_hw.runtime.bench.excitation import predicted_motion

        base = self.spec(step) if step not in self.base_specs else self.base_specs[step]
        scale = 1.0
        if self.s.excitation != "designed" or BENCH_STEPS[step].fixture != "floor":
            return None
        pspec = dataclasses.replace(base, profile=probe_u, torque=tuple(float(v) for v in probe_u[0]),
                                    duration=len(probe_u) * self.period)
        from otbot_hw.model.kinematics import forward_kinematics_matrix

        M = forward_kinematics_matrix(np.zeros(6), best)[:2]
        _, qd = predicted_motion(pspec, best)
        v_pred = float(np.max(np.linalg.norm(qd[:, 3:6] @ M.T, axis=1)))
        n = min(len(probe_u), len(probe))
        v_meas = float(np.max(np.linalg.norm(np.asarray(probe.joint_vel[:n], dtype=float) @ M.T, axis=1)))
        rho = float(np.clip(v_pred / max(v_meas, 1e-9), 0.25, 20.0))
        total = best.m_c + best.m_p
        if BENCH_STEPS[step].loaded:
            guess = best.replace(m_p=max(total * rho - best.m_c, 0.1 * best.m_p), I_p=best.I_p * rho)
        else:
            guess = best.replace(m_c=max(total * rho - best.m_p, 0.1 * best.m_c), I_c=best.I_c * rho)
        safety = self.s.safety.within(self.s.limits, "floor")
        robots = [guess]
        if not BENCH_STEPS[step].loaded:  # what a forward probe cannot tell: the chassis' centre and inertia
            c = UNKNOWN_COM
            robots += [guess.replace(x_B=guess.x_B + dx, y_B=guess.y_B + dy, I_c=guess.I_c * f)
                       for dx, dy in ((c, c), (c, -c), (-c, c), (-c, -c)) for f in (1 - UNKNOWN_INERTIA, 1 + UNKNOWN_INERTIA)]
        spec = base
        for _ in range(3):
            every = [predicted_margins(spec, r, self.s.limits, safety.max_wheel_rate, safety.max_pivot_rate)
                     for r in robots]
            margins = {k: max((m[k] for m in every), key=lambda v: v[0] / v[1]) for k in every[0]}
            worst = max((p / lim for k, (p, lim) in margins.items() if k != "torque"), default=0.0)
            if worst <= LIMIT_FILL:
                break
            scale *= LIMIT_FILL / worst
            spec = _scaled(base, scale)
        self.specs[step] = spec
        self.session.data.setdefault("excitation_scale", {})[step] = scale
        self.session.save()
        text = (f"the probe moved the robot at {v_meas:.3f} m/s, {v_pred:.3f} m/s predicted: about {rho:.2f} x the "
                f"mass believed; largest predicted peaks on that robot"
                + (f" with its centre of mass within {UNKNOWN_COM:g} m and inertia within {UNKNOWN_INERTIA:.0%}"
                   if len(robots) > 1 else "") + ": "
                + ", ".join(f"{k.replace('_', ' ')} {p:.3g} of {lim:.3g}" for k, (p, lim) in margins.items()))
        text += (f"; the designed torques scaled by {scale:.3f} to stay within the limits" if scale < 1.0 else
                 "; the designed torques as designed")
        return chk.Check("robot_limits", True, text, value=scale)


    def _meta(self, step: str, kind: str, attempt: int, fixture: str, extra: dict | None = None) -> dict:
        meta = {**self.metadata, "sample_period": self.period, "fixture": fixture, "noise": self.s.noise.to_dict(),
                "bench": {"session": str(self.session.path), "step": step, "attempt": attempt, "run": kind,
                          "excitation": self.s.excitation}}
        if self.sim is not None:
            params = (self.robot.simulated_params if isinstance(self.robot, SimulatedBackEnd)
                      else (self.sim.loaded if BENCH_STEPS[step].loaded else self.sim.unloaded))
            meta["params"] = params.to_dict()
            if self.sim.effects:
                meta["effects"] = self.sim.effects
        meta.update(extra or {})
        return meta

    def _clear_idle_watchdogs(self) -> None:
        """Between runs nothing commands torque (the drives are quick-stopped) and the bus rests while
        the bench computes or waits for the operator. Wall-clock watchdogs may trip meanwhile: the
        drives' watch of the master's heartbeat (or of SYNC, where configured) on a loaded host, said
        by EMCY; in lockstep a node's heartbeat or TPDO, or the simulated IMU (it publishes on SYNC)
        looks late. One SYNC shows them; such communication faults alone are then reset (and counted
        in the result): a node or an IMU that is really gone faults again at once and fails the run's
        drive or IMU check, as does any other fault, which is never reset."""
        try:
            self.robot.read()  # one SYNC: what went wrong while idle shows now (e.g. the IMU stream's watchdog)
        except RobotError:
            pass  # the bus is gone: the run's enable says so
        faults = self.robot.faults
        if faults and all(_communication(f) for f in faults):
            self.say("[bench] communication watchdogs tripped while the bench was idle ("
                     + "; ".join(sorted({f"{f.device}: {f.kind}" + (f" 0x{f.code:04X}" if f.code else "")
                                         for f in faults})) + "): reset")
            self.idle_resets.append([f.to_dict() for f in faults])
            self.robot.fault_reset()

    def _run(self, controller, cycles: int, fixture: str | None, path: Path, meta: dict,
             feedback=None) -> LoopResult:
        # the EKF serves the speed and free-area checks here; it may gate out the encoders for a while at
        # a hard torque step (seen on some platform-to-chassis angles), which its std then shows: the
        # std checks stay, the share of rejected innovations (a tracking loop's health check) does not
        safety = dataclasses.replace(self.s.safety.within(self.s.limits, fixture or "stand"),
                                     max_rejected_fraction=None)
        sup = Supervisor(self.torque_limits, safety, self.period, realtime=self.realtime)
        runner = LoopRunner(self.robot, controller, sup, feedback, path=path, metadata=meta, realtime=self.realtime)
        t0 = time.perf_counter()
        try:
            self._clear_idle_watchdogs()
            res = runner.run(cycles)
        except RobotError as exc:  # the bus failed underneath (not a latched fault)
            raise BenchAbort(meta["bench"]["step"], f"the robot stopped answering: {exc}") from None
        self.timing.runs += time.perf_counter() - t0
        self.timing.robot_time += res.stats.robot_time
        return res

    # -- one step ----------------------------------------------------------------------------------
    def preflight(self, step: str, attempt: dict) -> list[chk.Check]:
        """The checks before the excitation (module docstring, 2-4); stops at the first group that fails."""
        bs = BENCH_STEPS[step]
        n = attempt["attempt"]
        rest_path = self.session.recording_path(step, n, "rest")
        zeros = np.zeros((int(round(REST_TIME / self.period)), 3))
        rest = self._run(ExcitationController(zeros, self.period, np.zeros((3, 3)), 0.0), len(zeros) + 1, None,
                         rest_path, self._meta(step, "rest", n, bs.fixture))
        attempt["check_recordings"].append(self.session.rel(rest_path))
        out = [chk.drives_check(rest)]
        if not out[0].passed:
            return out
        out += [chk.imu_check(rest.recording, self.s.imu_rate), chk.rest_check(rest.recording, self.s.noise)]
        if not all(c.passed for c in out):
            return out
        best = self.best_params()
        safety = self.s.safety.within(self.s.limits, bs.fixture)
        margins = predicted_margins(self.spec(step), best, self.s.limits, safety.max_wheel_rate, safety.max_pivot_rate)
        out.append(chk.limits_check(step, margins, self.s.excitation))
        if not out[-1].passed:
            return out
        probe_u = probe_torques(bs.fixture, self.period)
        probe_path = self.session.recording_path(step, n, "probe")
        zeros = np.zeros((int(round(PROBE_PAUSE / self.period)), 3))
        probe = self._run(ExcitationController(np.vstack([probe_u, zeros]), self.period, np.zeros((3, 3)), 0.0),
                          len(probe_u) + len(zeros) + 1, bs.fixture, probe_path, self._meta(step, "probe", n, bs.fixture))
        attempt["check_recordings"].append(self.session.rel(probe_path))
        if not probe.completed:
            out.append(chk.Check("fixture", False, f"the fixture probe was stopped: {probe.fault}",
                                 f"{bs.setup}, then check again"))
        else:
            out.append(chk.fixture_check(bs.fixture, probe.recording, rest.recording, best, len(probe_u)))
            if bs.loaded and not out[-1].passed and "did not move" in out[-1].message:
                out[-1] = self._too_heavy(out[-1])
            elif out[-1].passed:
                fitted = self.fit_to_robot(step, probe.recording, probe_u, best)
                if fitted is not None:
                    out.append(fitted)
        # stop what the probe moved: with the step's brake where the fixture is verified, else gently
        settle_path = self.session.recording_path(step, n, "settle")
        gains = brake_gains(best, bs.fixture if out[-1].passed else None, self.period)
        nb = int(round(SETTLE_TIME / self.period))
        settle = self._run(ExcitationController(np.zeros((0, 3)), self.period, gains, self.s.limits.torque, nb),
                           nb + 1, bs.fixture, settle_path, self._meta(step, "settle", n, bs.fixture))
        attempt["check_recordings"].append(self.session.rel(settle_path))
        if out[-1].passed:  # judged on its last REST_TIME
            k = max(0, len(settle.recording) - int(round(REST_TIME / self.period)))
            c = chk.rest_check(settle.recording, self.s.noise, what="after the probe", start=k)
            out.append(dataclasses.replace(c, name="settled"))
        return out

    def geometry_mismatch(self, step: str, recording: Path) -> str | None:
        """When a step's gates fail, the last parameters the bench takes from the file are the geometry (l1,
        l2, r): the session refitted with them free too. If that explains every recording, the sentences
        naming each one that moved by more than 3 std; else None (the diagnosis looks for missing physics)."""
        from otbot_hw.identification.session import identify_session
        from otbot_hw.identification.uncertainty import NUISANCE_PARAMS

        if "chassis" not in self.s.steps or self.session.status("chassis") != "passed" and step != "chassis":
            return None
        recs: dict[str, list] = {}
        for s in self.s.steps:
            paths = [recording] if s == step else self.session.accepted_recordings(s)
            if paths and (s == step or self.session.status(s) == "passed"):
                recs[s] = [read_recording(p) for p in paths]
        if "chassis" not in recs:
            return None
        t0 = time.perf_counter()
        try:
            res = identify_session(recs, self.start_params(), specs={s: self.spec(s) for s in recs},
                                   known_std=self.known_std(), nuisance=NUISANCE_PARAMS + ("l1", "l2", "r"))
        except IdentificationError:
            return None
        finally:
            self.timing.identification += time.perf_counter() - t0
        if not res.passed:
            return None
        std = res.std
        off = [f"{n} {getattr(self.s.params_start, n):.4g} m in the file, estimated {res.values[n]:.4g} +- {std[n]:.2g} m"
               for n in ("l1", "l2", "r") if std.get(n, 0) > 0
               and abs(res.values[n] - getattr(self.s.params_start, n)) > 3 * std[n]]
        return "; ".join(off) or None

    def _too_heavy(self, found: chk.Check) -> chk.Check:
        """The loaded robot did not move under the probe's torque: name the load as the cause (the floor
        probe of the unloaded robot passed, or the load is the only thing the operator changed)."""
        moved = self.session.status("chassis") == "passed" if "chassis" in self.s.steps else False
        return chk.Check("load", False, "with the load on, " + found.message.replace("the robot", "the robot", 1)
                         + (", where it moved without the load in step chassis" if moved else "")
                         + f": the load is more than the motors can accelerate within the experiment limits "
                           f"(torque {self.s.limits.torque:g} N m per motor)",
                         "use a lighter load (or identify it in parts), or raise experiment_limits.torque within the "
                         "motors' rating (config/robot.yaml)", found.value)

    def excite(self, step: str, attempt: dict) -> tuple[LoopResult, np.ndarray]:
        bs = BENCH_STEPS[step]
        spec = self.spec(step)
        U = spec.torques()
        n = attempt["attempt"]
        path = self.session.recording_path(step, n)
        best = self.best_params()
        feedback = None
        if bs.fixture == "floor":
            from otbot_hw.runtime.feedback import EkfFeedback

            # the model is what this procedure identifies: the EKF's yaw adapts to its error (docs/estimation.md)
            feedback = EkfFeedback(best, self.period, np.zeros(3))
        nb = int(round(BRAKE_TIME / self.period))
        ctrl = ExcitationController(U, self.period, brake_gains(best, bs.fixture, self.period), self.s.limits.torque, nb)
        meta = self._meta(step, "excitation", n, bs.fixture,
                          {"experiment": f"{step}: {spec.description}", "excitation_samples": len(U),
                           "brake_from": len(U) * self.period})
        attempt["recording"] = self.session.rel(path)
        self.session.save()
        self.say(f"[bench] {step}: excitation ({self.s.excitation}, {spec.duration:g} s) then the brake")
        res = self._run(ctrl, len(U) + nb + 1, bs.fixture, path, meta, feedback)
        return res, U

    def identify(self, step: str, recording: Path):
        """``identify_session`` on the passed steps' recordings and ``recording`` for ``step``."""
        from otbot_hw.identification.session import identify_session

        recs: dict[str, list] = {}
        for s in self.s.steps:
            paths = [recording] if s == step else self.session.accepted_recordings(s)
            if paths and (s == step or self.session.status(s) == "passed"):
                recs[s] = [read_recording(p) for p in paths]
        specs = {s: self.spec(s) for s in recs}
        t0 = time.perf_counter()
        try:
            res = identify_session(recs, self.start_params(), specs=specs, known_std=self.known_std())
        finally:
            self.timing.identification += time.perf_counter() - t0
        return res

    def run_step(self, step: str) -> None:
        bs = BENCH_STEPS[step]
        reasons: list[str] = []
        for _ in range(self.s.attempts):
            attempt = self.session.new_attempt(step)
            n = attempt["attempt"]
            self.say(f"[bench] step {step}, attempt {n}: {bs.fixture}" + (", loaded" if bs.loaded else ""))
            try:
                self.operator.set_up(step, bs.instructions(self.s.limits), bs.fixture, bs.loaded)
            except NoOperator as exc:
                self.session.set_status(step, "failed", attempt, [str(exc)])
                raise BenchError(step, str(exc)) from None
            while True:
                found = self.preflight(step, attempt)
                attempt["checks"] = [c.to_dict() for c in found]
                self.session.save()
                for c in found:
                    self.say(f"[bench] {step}: {'ok' if c.passed else 'FAILED'} {c.name}: {c.message}")
                failed = [c for c in found if not c.passed]
                if not failed:
                    break
                try:
                    again = self.operator.retry(step, failed, bs.fixture, bs.loaded)
                except NoOperator:  # nobody answered: the checks' verdict is the error
                    again = False
                if not again:
                    self.session.set_status(step, "failed", attempt, [str(c) for c in failed])
                    raise BenchError(step, "; ".join(f"{c.name}: {c}" for c in failed))
            res, U = self.excite(step, attempt)
            if not res.completed:
                self.session.set_status(step, "aborted", attempt, [f"stopped: {res.fault}"])
                raise BenchAbort(step, f"the run was stopped: {res.fault}; recording up to the stop: "
                                       f"{self.session.path / attempt['recording']}")
            quality = [chk.saturation_check(res.recording, U), chk.clipping_check(res.recording, len(U) + 1)]
            attempt["checks"] += [c.to_dict() for c in quality]
            bad = [c for c in quality if not c.passed]
            if bad:
                self.session.set_status(step, "failed", attempt, [str(c) for c in bad])
                raise BenchError(step, "; ".join(f"{c.name}: {c}" for c in bad)
                                 + f" (recording kept: {self.session.path / attempt['recording']})")
            self.say(f"[bench] {step}: identifying (the step, then the joint fit of the session so far)")
            try:
                result = self.identify(step, self.session.path / attempt["recording"])
            except IdentificationError as exc:
                self.session.set_status(step, "failed", attempt, [str(exc)])
                raise BenchError(step, f"cannot identify its parameters: {exc}") from None
            st = result.steps.get(step)
            if st is not None and st.gates.passed and not result.reasons:
                self.result = result
                self.session.set_status(step, "passed", attempt, [], verdict="pass",
                                        fit=st.to_dict()["fit"], estimate=st.to_dict()["estimate"])
                self.say(f"[bench] {step}: passed ("
                         + ", ".join(f"{k} {v['value']:.5g} +- {v['session_std'] or v['std']:.2g}"
                                     for k, v in st.to_dict()["estimate"].items()) + ")")
                return
            reasons = (st.gates.reasons if st is not None else []) + list(result.reasons)
            self.session.set_status(step, "redo", attempt, reasons, verdict="redo")
            self.say(f"[bench] {step}: redo: {'; '.join(reasons)[:300]}")
            failed_result, failed_recording = result, self.session.path / attempt["recording"]
        self.session.set_status(step, "failed")
        why = "; ".join(reasons[:2]) + (f" (and {len(reasons) - 2} more in session.json)" if len(reasons) > 2 else "")
        geometry = self.geometry_mismatch(step, failed_recording)
        if geometry:
            raise BenchError(step, f"the geometry in {self.metadata.get('params_file', 'the parameter file')} does not "
                                   f"match this robot: {geometry}: with it estimated, every recording is explained "
                                   "(measure l1, l2, r and correct the file, then start a new session); the gates "
                                   f"with the file's geometry: {why}")
        found = ""
        if self.s.diagnose:  # where the model fails, the mismatch finder says what it misses
            d = self.diagnose(failed_result.values, {step: [failed_recording]})
            found = f"; otbot diagnose on the session's recordings: {d['verdict']} ({self.session.path}/diagnosis.json)"
        raise BenchError(step, f"its parameters could not be identified in {self.s.attempts} attempt(s): {why}{found}")

    # -- the whole procedure -----------------------------------------------------------------------
    def run(self) -> dict:
        """Every step not passed yet, then identification, diagnosis; returns the JSON-ready result."""
        t0, c0 = time.perf_counter(), time.process_time()
        self.weigh()
        for step in self.s.steps:
            if self.session.status(step) == "passed":
                self.say(f"[bench] step {step}: passed in an earlier run of this session")
                continue
            self.run_step(step)
        final = self.final_identification()
        diagnosis = self.diagnose(final.values) if self.s.diagnose else None
        return self.summary(final, diagnosis, time.perf_counter() - t0, time.process_time() - c0)

    def final_identification(self):
        last = self.s.steps[-1]
        if self.result is not None and set(self.result.steps) == set(self.s.steps):
            return self.result
        self.result = self.identify(last, self.session.accepted_recordings(last)[0])
        return self.result

    def diagnose(self, values: dict, extra: dict[str, list[Path]] | None = None) -> dict:
        """The mismatch finder on the session's recordings (the passed steps', and ``extra`` per step):
        the unloaded robot's steps with the identified unloaded robot (``values``, session symbols), the
        platform step with the loaded one. Written to ``diagnosis.json`` too."""
        from otbot_hw.diagnose.data import from_recording
        from otbot_hw.diagnose.diagnosis import diagnose

        t0 = time.perf_counter()
        out: dict[str, Any] = {}
        groups = {"unloaded": [s for s in self.s.steps if not BENCH_STEPS[s].loaded],
                  "loaded": [s for s in self.s.steps if BENCH_STEPS[s].loaded]}
        for label, steps in groups.items():
            paths = [p for s in steps for p in [*self.session.accepted_recordings(s), *(extra or {}).get(s, [])]]
            if not paths:
                continue
            self.say(f"[bench] diagnose: the {label} robot's recordings ({', '.join(self.session.rel(p) for p in paths)})")
            data = [from_recording(read_recording(p), name=self.session.rel(p)) for p in paths]
            params = robot_params(values, self.start_params(), loaded=label == "loaded")
            out[label] = diagnose(data, params, progress=lambda m: self.say(m))
        self.timing.diagnosis += time.perf_counter() - t0
        effects = sorted({e["name"] for d in out.values() for e in d["effects"]})
        ambiguous = [c["name"] for d in out.values() for g in d["ambiguous"] for c in g["candidates"]]
        out["effects"] = effects
        out["verdict"] = ("missing physics: " + ", ".join(effects) if effects else
                          ("ambiguous: " + " / ".join(ambiguous) if ambiguous else
                           "no missing physics found: no catalog effect improves the model by the evidence threshold"))
        (self.session.path / "diagnosis.json").write_text(json.dumps(out, indent=1, allow_nan=False))
        return out

    def unloaded_platform(self, final) -> tuple[dict, list[str]]:
        """The unloaded platform's m_p0, x_F0, y_F0 as the session used them ({value, std, file, source}) and
        the notices: the file against this robot, what the recordings cannot separate."""
        file_p = self.s.params_start
        meas = self.session.data.get("measurements", {}).get("m_p0")
        std = final.std
        out = {}
        for n, paper in (("m_p0", "m_p"), ("x_F0", "x_F"), ("y_F0", "y_F")):
            if n == "m_p0" and meas is not None:
                src = meas["source"]
            elif n in final.estimated:
                src = "estimated by the joint fit of the floor runs"
            else:
                src = "the parameter file's value, taken as exact"
            out[n] = {"value": float(final.values[n]), "std": float(std.get(n, 0.0)),
                      "file": float(getattr(file_p, paper)), "source": src}
        notices = []
        off = [m for n, u in (("m_p0", "kg"), ("x_F0", "m"), ("y_F0", "m"))
               if out[n]["source"] != "the parameter file's value, taken as exact"
               and not out[n]["source"].startswith("not weighed")
               and (m := _platform_mismatch(n, u, out[n]["file"], out[n]))]
        label = self.metadata.get("params_file", "the parameter file")
        if off:
            notices.append(f"the unloaded platform in {label} does not match this robot: {'; '.join(off)}; the "
                           "bench used the measured and estimated values (params.yaml; update the file, or weigh the "
                           "platform and let the bench estimate its centre)")
        if meas is not None and meas["source"].startswith("not weighed"):
            tot = final.combination({"m_c": 1.0, "m_p0": 1.0})
            notices.append(f"the unloaded platform was not weighed: the recordings cannot separate the chassis' mass "
                           f"m_c from the platform's m_p0 (a floor run sees only m_c + m_p0 = {tot['value']:.5g} +- "
                           f"{tot['std']:.2g} kg)" + (", nor the loaded platform's m_p from m_p0 (the load's mass "
                                                      "m_p - m_p0 is identified)" if "platform" in final.steps else "")
                           + f"; m_c, x_B, I_c" + (", m_p, I_p, x_F, y_F" if "platform" in final.steps else "")
                           + f" are reported for m_p0 = {meas['value']:.4g} +- {meas['std']:.2g} kg and their std "
                           "include it; the robot's dynamics depend only on the identified combinations "
                           "('combinations'); weigh the platform for the separate values")
        return out, notices

    def summary(self, final, diagnosis, wall: float, cpu: float) -> dict:
        params = final.parameters()
        steps = {}
        for s in self.s.steps:
            rec = self.session.step(s)
            acc = next((a for a in reversed(rec["attempts"]) if a["status"] == "passed"), None)
            st = final.steps.get(s)
            d = st.to_dict() if st is not None else {}
            steps[s] = {"status": rec["status"], "converged": d.get("converged"), "verdict": d.get("verdict"),
                        "fit": d.get("fit"), "estimate": d.get("estimate"), "reasons": d.get("reasons", []),
                        "recordings": [a["recording"] for a in rec["attempts"] if a.get("recording")],
                        "accepted_recording": acc["recording"] if acc else None,
                        "check_recordings": [r for a in rec["attempts"] for r in a.get("check_recordings", [])],
                        "checks": acc["checks"] if acc else [], "attempts": len(rec["attempts"])}
        out: dict[str, Any] = {
            "session": str(self.session.path), "passed": bool(final.passed), "excitation": self.s.excitation,
            "steps": steps, "parameters": params, "method": final.method,
            "units": final.to_dict()["units"], "correlation": final.to_dict()["correlation"],
            "diagnosis": diagnosis, "designs": self.designs or None, "idle_watchdog_resets": len(self.idle_resets),
            "timing": {"wall_time": wall, "cpu_time": cpu, "runs_wall_time": self.timing.runs,
                       "robot_time": self.timing.robot_time, "identification_wall_time": self.timing.identification,
                       "diagnosis_wall_time": self.timing.diagnosis},
        }
        out["unloaded_platform"], notices = self.unloaded_platform(final)
        out["combinations"] = {"m_c+m_p0": final.combination({"m_c": 1.0, "m_p0": 1.0})}
        if "platform" in final.steps:
            out["combinations"]["m_p-m_p0"] = final.combination({"m_p": 1.0, "m_p0": -1.0})
        out["notices"] = self.notices + notices
        if self.sim is not None:
            truth = self.sim.truth()
            out["truth"] = {n: truth[n] for n in SESSION_PARAMS}
            out["error_sigma"] = {n: ((params[n]["value"] - truth[n]) / params[n]["std"]
                                      if params[n]["std"] > 0 else None) for n in SESSION_PARAMS
                                  if n in final.estimated}
            out["load"] = dict(zip(("mass", "x", "y", "inertia"), self.sim.load)) if self.sim.load else None
            combo_truth = {"m_c+m_p0": truth["m_c"] + truth["m_p0"], "m_p-m_p0": truth["m_p"] - truth["m_p0"]}
            for n, d in out["combinations"].items():
                out["truth"][n] = combo_truth[n]
                if d["std"] > 0:
                    out["error_sigma"][n] = (d["value"] - combo_truth[n]) / d["std"]
            for n, d in out["unloaded_platform"].items():
                out["truth"][n] = truth[n]
                if d["std"] > 0:
                    out["error_sigma"][n] = (d["value"] - truth[n]) / d["std"]
        return json_safe(out)


def _platform_mismatch(name: str, unit: str, file_value: float, d: dict) -> str | None:
    """A sentence when the file's value of the unloaded platform's ``name`` is off by > 3 std of the bench's."""
    if d["std"] > 0 and abs(d["value"] - file_value) > 3.0 * d["std"]:
        how = "weighed" if d["source"].startswith("weighed") else "estimated"
        return f"{name} {file_value:.4g} {unit} in the file, {how} {d['value']:.4g} +- {d['std']:.2g} {unit}"
    return None


def _scaled(spec: ExperimentSpec, k: float) -> ExperimentSpec:
    """``spec`` with its torques multiplied by ``k``."""
    if k == 1.0:
        return spec
    U = spec.torques() * k
    return dataclasses.replace(spec, profile=U, torque=tuple(float(v) for v in U[0]),
                               description=f"{spec.description}, scaled by {k:.3f} to this robot")


def _communication(f) -> bool:
    """A fault of the bus's wall-clock watchdogs (not of a drive's power stage or its sensors)."""
    if f.kind == "emcy":
        return f.code in WATCHDOG_CODES
    if f.kind == "imu":
        return "no valid IMU sentence" in f.meaning or "no IMU sample within" in f.meaning
    return f.kind in ("heartbeat", "stale")



def identity(robot, bus: str, sim: SimulatedRobot | None = None, sim_label: str | None = None) -> dict:
    """Who the robot is: each node's CiA 301 identity object 0x1018 (vendor, product, revision, serial)
    read over SDO, and for a simulated robot a fingerprint of its parameters, effects and load."""
    import hashlib

    out: dict[str, Any] = {"bus": bus, "nodes": robot.node_identities(), "simulated": None}
    if sim is not None:
        blob = json.dumps({"params": sim.unloaded.values(), "effects": sim.effects, "load": sim.load}, sort_keys=True)
        out["simulated"] = {"sha": hashlib.sha256(blob.encode()).hexdigest()[:16], "label": sim_label or "simulated"}
    return out


def warm_up(params: OtbotParams, period: float) -> None:
    """Compile what the bench's runs call (the EKF's kernels, the supervisor, the brake's and the
    predicted motion's model functions) before a bus opens: numba compiles at the first call and holds
    the interpreter meanwhile (seconds on a cold cache), which on a live bus starves the heartbeat
    threads (as ``runtime.tracking.warm_up`` does for tracking)."""
    from otbot_hw.identification.experiments import PAPER_EXPERIMENTS
    from otbot_hw.runtime.backends import DirectBackend
    from otbot_hw.runtime.feedback import EkfFeedback

    with DirectBackend(rate=1.0 / period, noise=NoiseModel.paper()).open(params) as robot:
        ctrl = ExcitationController(np.zeros((3, 3)), period, brake_gains(params, "floor", period), 1.0, 3)
        sup = Supervisor(MotorLimits(np.full(3, 1e9)), SafetyConfig(max_travel=10.0), period)
        LoopRunner(robot, ctrl, sup, EkfFeedback(params, period, np.zeros(3))).run(6)
    predicted_margins(PAPER_EXPERIMENTS["wheel"], params, ExperimentLimits(), None, None)


def settings_from_manifest(data: dict, base: BenchSettings) -> BenchSettings:
    """The settings a session was started with (``--resume``), the hardware's limits and safety kept."""
    from otbot_hw.experiment_limits import limits_from_dict

    s = data["settings"]
    lim = ExperimentLimits(**s["limits"]) if isinstance(s.get("limits"), dict) else limits_from_dict(None)
    return dataclasses.replace(base, steps=list(s["steps"]), excitation=s["excitation"], attempts=int(s["attempts"]),
                               limits=lim, params_start=OtbotParams.from_dict(s["params_start"], "session.json"),
                               noise=NoiseModel(**s["noise"]))
