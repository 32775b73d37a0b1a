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

Its parts: ``steps`` (the steps, settings, errors), ``runs`` (the supervised runs through the loop),
``robot_fit`` (a designed excitation scaled to this robot), ``analysis`` (identification, the geometry
refit, diagnosis), ``summary`` (the JSON result), ``session`` (the folder, manifest and the robot's
identity), ``checks``, ``excitation``, ``operator``.
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from otbot_hw.identification.errors import IdentificationError
from otbot_hw.identification.experiments import ExperimentSpec
from otbot_hw.identification.uncertainty import robot_params
from otbot_hw.params import OtbotParams
from otbot_hw.robot import Robot
from otbot_hw.runtime.bench import checks as chk
from otbot_hw.runtime.bench.analysis import diagnose_session, geometry_mismatch, identify, step_recordings
from otbot_hw.runtime.bench.operator import NoOperator
from otbot_hw.runtime.bench.excitation import (ExcitationController, brake_gains, predicted_margins,
                                               probe_torques, step_spec)
from otbot_hw.runtime.bench.robot_fit import fit_excitation, scaled
from otbot_hw.runtime.bench.runs import BenchRuns
from otbot_hw.runtime.bench.session import SessionFolder
from otbot_hw.runtime.bench.steps import BENCH_STEPS, BenchAbort, BenchError, BenchSettings, SimulatedRobot
from otbot_hw.runtime.bench.summary import summary
from otbot_hw.runtime.loop import LoopResult

REST_TIME = 0.5       # s of the zero-torque run (and of the end of the settling run judged at rest)
BRAKE_TIME = 1.5      # s of braking after an excitation
PROBE_PAUSE = 0.1     # s of zero torque after the probe doublet
SETTLE_TIME = 2.5     # s of braking after the probe
#: prior std of the unloaded platform's mass when nobody weighs it, as a fraction of the file's value (a CAD
#: mass may be off by tens of per cent)
UNWEIGHED_FRACTION = 0.2


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
        self.say = progress or (lambda m: None)
        self.sim = sim
        self.metadata = dict(metadata or {})
        self.period = float(robot.period)
        self.timing = _Timing()
        self.runs = BenchRuns(robot, settings, session, self.timing, realtime, self.say, sim, self.metadata)
        self.result = None  # the latest SessionResult
        self.specs: dict[str, ExperimentSpec] = {}
        self.base_specs: dict[str, ExperimentSpec] = {}
        self.designs: dict[str, dict] = {}
        self.idle_resets = self.runs.idle_resets
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
                self.specs[step] = scaled(sp, float(k))
        return self.specs[step]

    def fit_to_robot(self, step: str, probe, probe_u: np.ndarray, best: OtbotParams) -> chk.Check | None:
        """Floor steps, designed excitation: the design scaled to this robot as the probe shows it
        (``robot_fit.fit_excitation``; the scale kept in session.json). None for the paper's excitation and
        the held fixtures."""
        base = self.spec(step) if step not in self.base_specs else self.base_specs[step]
        if self.s.excitation != "designed" or BENCH_STEPS[step].fixture != "floor":
            return None
        spec, scale, check = fit_excitation(base, probe, probe_u, best, BENCH_STEPS[step].loaded, self.s.limits,
                                            self.s.safety, self.period)
        self.specs[step] = spec
        self.session.data.setdefault("excitation_scale", {})[step] = scale
        self.session.save()
        return check

    # -- one step ----------------------------------------------------------------------------------
    def preflight(self, step: str, attempt: dict) -> list[chk.Check]:
        """The checks before the excitation (module docstring, 2-4); stops at the first group that fails."""
        bs = BENCH_STEPS[step]
        n = attempt["attempt"]
        rest_path = self.session.recording_path(step, n, "rest")
        zeros = np.zeros((int(round(REST_TIME / self.period)), 3))
        rest = self.runs.run(ExcitationController(zeros, self.period, np.zeros((3, 3)), 0.0), len(zeros) + 1, None,
                             rest_path, self.runs.meta(step, "rest", n, bs.fixture))
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
        probe = self.runs.run(ExcitationController(np.vstack([probe_u, zeros]), self.period, np.zeros((3, 3)), 0.0),
                              len(probe_u) + len(zeros) + 1, bs.fixture, probe_path,
                              self.runs.meta(step, "probe", n, bs.fixture))
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
        settle = self.runs.run(ExcitationController(np.zeros((0, 3)), self.period, gains, self.s.limits.torque, nb),
                               nb + 1, bs.fixture, settle_path, self.runs.meta(step, "settle", n, bs.fixture))
        attempt["check_recordings"].append(self.session.rel(settle_path))
        if out[-1].passed:  # judged on its last REST_TIME
            k = max(0, len(settle.recording) - int(round(REST_TIME / self.period)))
            c = chk.rest_check(settle.recording, self.s.noise, what="after the probe", start=k)
            out.append(dataclasses.replace(c, name="settled"))
        return out

    def geometry_mismatch(self, step: str, recording: Path) -> str | None:
        """The geometry refitted when ``step``'s gates fail (``analysis.geometry_mismatch``), once step
        chassis has passed or is this one."""
        if "chassis" not in self.s.steps or self.session.status("chassis") != "passed" and step != "chassis":
            return None
        recs = step_recordings(self.session, self.s.steps, step, recording)
        if "chassis" not in recs:
            return None
        t0 = time.perf_counter()
        try:
            return geometry_mismatch(recs, self.start_params(), self.s.params_start, {s: self.spec(s) for s in recs},
                                     self.known_std())
        finally:
            self.timing.identification += time.perf_counter() - t0

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
        meta = self.runs.meta(step, "excitation", n, bs.fixture,
                              {"experiment": f"{step}: {spec.description}", "excitation_samples": len(U),
                               "brake_from": len(U) * self.period})
        attempt["recording"] = self.session.rel(path)
        self.session.save()
        self.say(f"[bench] {step}: excitation ({self.s.excitation}, {spec.duration:g} s) then the brake")
        res = self.runs.run(ctrl, len(U) + nb + 1, bs.fixture, path, meta, feedback)
        return res, U

    def identify(self, step: str, recording: Path):
        """``identify_session`` on the passed steps' recordings and ``recording`` for ``step``."""
        recs = step_recordings(self.session, self.s.steps, step, recording)
        specs = {s: self.spec(s) for s in recs}
        t0 = time.perf_counter()
        try:
            return identify(recs, self.start_params(), specs, self.known_std())
        finally:
            self.timing.identification += time.perf_counter() - t0

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
        """The mismatch finder on the session's recordings (``analysis.diagnose_session``)."""
        t0 = time.perf_counter()
        try:
            return diagnose_session(self.session, self.s.steps, values, self.start_params(), extra, self.say)
        finally:
            self.timing.diagnosis += time.perf_counter() - t0

    def summary(self, final, diagnosis, wall: float, cpu: float) -> dict:
        return summary(self, final, diagnosis, wall, cpu)
