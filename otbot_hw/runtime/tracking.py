"""Tracking the paper's scenarios (``otbot_hw.control.scenarios``) with the loop runner on a back end.

``track`` runs one scenario once: the computed-torque ``TrackingController`` on a ``Robot`` from a
back end (``otbot_hw.runtime.backends``: ``sim``, ``bus sim``, ``bus config``), fed by the EKF or the
simulator's truth, through the ``Supervisor``; ``run_scenario`` adds the feasibility check, the
robustness reruns, the isolated force reruns of the figure-8, the open-loop replay of a planned
trajectory, plots and the JSON summary (``otbot track``).

Time: the loop's first sample (t = 0) reads where the robot stands; the reference starts (its time 0)
at the next sample, where the first command computed from feedback takes effect. A ``TrackingRun``
is in reference time (t = 0 at that instant), the layout of the old closed-loop runs: t (N+1,),
states x (N+1, 12), commands u (N, 3) held on [t_k, t_k+1).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from otbot_hw.control.computed_torque import ComputedTorqueController
from otbot_hw.control.gains import Gains, gains_from_tstab
from otbot_hw.control.metrics import Event, error_summary, event_summary
from otbot_hw.control.scenarios import (FIGURE8_FORCES, LONG_RUN_S, ScenarioSpec, build_spec, collisions,
                                        controller_params, summarize)
from otbot_hw.motors import MotorLimits
from otbot_hw.params import OtbotParams
from otbot_hw.runtime.backends import DirectBackend
from otbot_hw.runtime.controllers import OpenLoopTorques, TrackingController
from otbot_hw.estimation import EstimatorConfig
from otbot_hw.runtime.feedback import EkfFeedback, TruthFeedback
from otbot_hw.runtime.loop import LoopResult, LoopRunner
from otbot_hw.runtime.supervisor import SafetyConfig, Supervisor
from otbot_hw.sensors import NoiseModel
from otbot_hw.simulation.simulator import ForceSchedule, rest_state


@dataclass
class TrackingRun:
    """A tracking run in reference time. t (N+1,) s; x (N+1, 12) the true state (q, q_dot) where the
    back end knows it, else the estimate's pose/twist with the encoders' joints; per sample k < N:
    u_cmd (law output before limiting), u (commanded), u_traj, u_corr (N, 3) N m; reference p_ref,
    pd_ref (N+1, 3); estimate est_pose, est_twist (N+1, 3) (None in open loop); f (N, 2) N the pivot
    forces held with u where the back end knows them (else None); ``loop``: the runner's
    result (recording in robot time, stats, fault); ``gates``: the EKF's accepted and rejected
    updates per kind ({"updates": {...}, "rejected": {...}}; None without an EKF)."""

    t: np.ndarray
    x: np.ndarray
    u_cmd: np.ndarray
    u: np.ndarray
    u_traj: np.ndarray
    u_corr: np.ndarray
    p_ref: np.ndarray
    pd_ref: np.ndarray
    rate_hz: float
    loop: LoopResult
    has_truth: bool = True
    est_pose: np.ndarray | None = None
    est_twist: np.ndarray | None = None
    saturation: list = field(default_factory=list)
    f: np.ndarray | None = None
    gates: dict | None = None
    adapter: object | None = None

    @property
    def e_p(self) -> np.ndarray:
        """Position errors p - p_d (N+1, 3): m, m, rad (true pose where known)."""
        return self.x[:, :3] - self.p_ref

    @property
    def e_v(self) -> np.ndarray:
        """Velocity errors p_dot - p_dot_d (N+1, 3): m/s, m/s, rad/s."""
        return self.x[:, 6:9] - self.pd_ref

    @property
    def wall_time_s(self) -> float:
        return self.loop.stats.wall_time

    @property
    def completed(self) -> bool:
        return self.loop.completed

    def estimation_error(self) -> dict | None:
        """{max, rms} of estimate - truth for x, y (m), alpha (rad, wrapped); None without truth or estimate."""
        if not self.has_truth or self.est_pose is None:
            return None
        from otbot_hw.estimation.errors import estimation_error

        return estimation_error(self.est_pose, self.x[:, :3])

    @classmethod
    def from_loop(cls, res: LoopResult, origin: float | None, period: float) -> "TrackingRun":
        rec = res.recording
        start = 0 if origin is None else int(np.searchsorted(rec.t, origin - 0.5 * period))
        end = len(rec)
        if res.recording.reference_p is None:  # stopped before the first sample (e.g. enabling failed)
            z3, z12 = np.zeros((0, 3)), np.zeros((0, 12))
            return cls(t=np.zeros(0), x=z12, u_cmd=z3, u=z3, u_traj=z3, u_corr=z3, p_ref=z3, pd_ref=z3,
                       rate_hz=1.0 / period, loop=res, has_truth=False, saturation=list(res.saturation))
        sl = slice(start, end)
        has_truth = rec.truth_q is not None
        if has_truth:
            x = np.hstack([rec.truth_q[sl], rec.truth_qd[sl]])
        else:
            x = np.hstack([rec.estimate_pose[sl], rec.joint_pos[sl], rec.estimate_twist[sl], rec.joint_vel[sl]])
        cmd = slice(start, end - 1)
        t0 = rec.t[start]
        sat = [{**e, "t_start": e["t_start"] - t0, "t_end": e["t_end"] - t0} for e in res.saturation]
        return cls(t=rec.t[sl] - t0, x=x, u_cmd=res.requested[cmd], u=rec.torque[cmd], u_traj=res.u_traj[cmd],
                   u_corr=res.u_corr[cmd], p_ref=rec.reference_p[sl], pd_ref=rec.reference_pd[sl],
                   rate_hz=1.0 / period, loop=res, has_truth=has_truth,
                   est_pose=None if rec.estimate_pose is None else rec.estimate_pose[sl],
                   est_twist=None if rec.estimate_twist is None else rec.estimate_twist[sl],
                   saturation=sat, f=None if rec.truth_force is None else rec.truth_force[cmd])


def make_feedback(kind: str | None, params, period: float, start_pose, config_path=None, fixes=None):
    """The feedback source by name: "ekf" (``EkfFeedback`` with the controller's parameters and the
    ``estimator:`` section of the hardware configuration ``config_path``, default config/robot.yaml,
    and the absolute pose source ``fixes``), "truth", or None."""
    if kind is None:
        return None
    if fixes is not None and kind != "ekf":
        raise ValueError("absolute pose fixes feed the EKF: use feedback 'ekf'")
    if kind == "truth":
        return TruthFeedback()
    if kind == "ekf":
        return EkfFeedback(params, period, start_pose, EstimatorConfig.load(config_path), fixes=fixes)
    raise ValueError(f"unknown feedback {kind!r} (ekf, truth)")


def warm_up(reference, law: ComputedTorqueController, feedback: str | None, period: float, x0=None,
            config_path=None, cycles: int = 5) -> None:
    """Compile what the loop runs (the law, its one-period prediction, the estimator's kernels, the
    supervisor) with a few cycles on the in-process simulated robot, before a bus opens: numba compiles
    a function at its first call and holds the interpreter meanwhile (seconds on a cold cache), which on
    a live bus would starve the heartbeat threads and trip every watchdog."""
    x0 = x0 if x0 is not None else rest_state(reference.sample(np.zeros(1))[0][0])
    with DirectBackend(rate=1.0 / period, noise=NoiseModel.paper()).open(law.model, x0=x0) as robot:
        controller = TrackingController(law, reference, period)
        fb = make_feedback(feedback, law.params, period, x0[:3], config_path)
        sup = Supervisor(MotorLimits(np.full(3, 1e9)), SafetyConfig(), period)
        LoopRunner(robot, controller, sup, fb).run(cycles)


def track_reference(reference, law: ComputedTorqueController, plant=None, limits: MotorLimits | None = None,
                    backend=None, feedback="truth", x0=None, forces: ForceSchedule | None = None,
                    duration: float | None = None, safety: SafetyConfig | None = None,
                    progress: Callable[[str], None] | None = None, path: str | Path | None = None,
                    metadata: dict | None = None, predict: bool = True,
                    rate_hz: float | None = None, config_path=None, fixes=None, adapt=None) -> TrackingRun:
    """Track a ``DesiredTrajectory`` with the computed-torque ``law`` through the loop runner.

    ``plant``: the simulated robot (``OtbotParams`` or ``ExtendedModel``; default the law's
    parameters; ignored on the configured bus); ``limits``: motor limits (default: none, 1e9 N m);
    ``backend``: default ``DirectBackend(rate_hz)`` (default 1 kHz, exact sensors); ``feedback``: "truth", "ekf" or a
    feedback object (``start``/``step`` -> ``StateEstimate``); ``x0``: start state (default rest at
    p_d(0), chassis heading 0); ``duration`` s (default the reference's); ``safety``: the supervisor's
    limits (default ``SafetyConfig()``); ``path``: MCAP recording; ``predict``: see ``TrackingController``;
    ``config_path``: the hardware YAML whose ``estimator:`` section configures the EKF; ``fixes``: an
    absolute pose source for the EKF (``EkfFeedback``); ``adapt``: an ``AdaptationConfig`` to adapt the
    law's payload online (``PayloadAdapter``, attached to ``law`` for the run; ``TrackingRun.adapter``)."""
    backend = backend or DirectBackend(rate=rate_hz or 1000.0)
    plant = plant if plant is not None else law.model
    limits = limits if limits is not None else MotorLimits(np.full(3, 1e9))
    x0 = x0 if x0 is not None else rest_state(reference.sample(np.zeros(1))[0][0])
    T = reference.duration if duration is None else float(duration)
    sim = backend.has_truth
    meta = {"backend": backend.describe(), **(metadata or {})}
    if not isinstance(backend, DirectBackend):
        warm_up(reference, law, feedback if isinstance(feedback, str) else None, backend.period, x0, config_path)
    adapter = None
    if adapt is not None:
        from otbot_hw.runtime.payload_adapter import PayloadAdapter

        law.adapter = adapter = PayloadAdapter(law, adapt, backend.period)
    with backend.open(plant if sim else None, x0=x0 if sim else None, forces=forces if sim else None) as robot:
        period = robot.period
        controller = TrackingController(law, reference, period, predict=predict)
        fb = (make_feedback(feedback, law.params, period, x0[:3], config_path, fixes) if isinstance(feedback, str)
              else feedback)
        sup = Supervisor(limits, safety, period, realtime=backend.realtime,
                         on_saturation=(lambda e: progress(
                             f"saturation: {e.motor} at t = {e.t_start - (controller.origin or 0.0):.3f} s (requested "
                             f"{e.peak_request:.1f} N m, limit {e.limit:g})")) if progress else None)
        runner = LoopRunner(robot, controller, sup, fb, path=path, metadata=meta, realtime=backend.realtime,
                            progress=progress if (progress is not None and T > LONG_RUN_S) else None,
                            progress_every=10.0)
        if adapter is not None:
            runner.payload = adapter
            adapter.on_fault, adapter.on_event = runner.trip, runner.event
            if progress is not None:
                adapter.on_event = lambda t, k, m: (runner.event(t, k, m), progress(
                    f"adaptation at t = {t - (controller.origin or 0.0):.2f} s: {m}"))
        res = runner.run(int(round(T / period)) + 2)
    run = TrackingRun.from_loop(res, controller.origin, period)
    run.gates = fb.gates() if hasattr(fb, "gates") else None
    run.adapter = adapter
    return run


def track(spec: ScenarioSpec, params: OtbotParams, limits: MotorLimits, gains: Gains,
          variant: str = "nominal", backend=None, feedback="truth",
          forces: ForceSchedule | None | str = "spec", progress: Callable[[str], None] | None = None,
          plant=None, effects: np.ndarray | None = None, safety: SafetyConfig | None = None,
          path: str | Path | None = None, metadata: dict | None = None, predict: bool = True,
          rate_hz: float | None = None, config_path=None, fixes=None, adapt=None) -> TrackingRun:
    """Track ``spec`` once with the controller believing ``params`` (see ``controller_params``) and
    ``variant``'s plant; ``effects``: an effect vector the controller compensates; the rest as
    ``track_reference``."""
    from otbot_hw.model.effects import ExtendedModel

    plant_v, ctrl = controller_params(params, variant, plant)
    if effects is not None:
        ctrl = ExtendedModel(ctrl, effects)
    meta = {"scenario": spec.name, "variant": variant, **(metadata or {})}
    return track_reference(spec.reference, ComputedTorqueController(ctrl, gains), plant_v, limits, backend, feedback,
                           x0=spec.x0, forces=spec.forces if forces == "spec" else forces, safety=safety,
                           progress=progress, path=path, metadata=meta, predict=predict, rate_hz=rate_hz,
                           config_path=config_path, fixes=fixes, adapt=adapt)


def _origin(run: TrackingRun) -> float:
    """Robot time (s) of the run's reference time 0."""
    rec = run.loop.recording
    if not len(run.t) or rec is None or not len(rec.t):
        return 0.0
    return float(rec.t[len(rec.t) - len(run.t)])


def replay_torques(torques, times, plant, x0, rate_hz: float, duration: float):
    """Torques (K, 3) N m, row k held from ``times[k]`` s, replayed open loop for ``duration`` s on the
    direct back end (exact sensors, no limits: a model study): (t (N+1,), X (N+1, 12) true states)."""
    backend = DirectBackend(rate=rate_hz, imu_rate=None)
    with backend.open(plant, x0=x0) as robot:
        ctrl = OpenLoopTorques(torques, times=times)
        sup = Supervisor(MotorLimits(np.full(3, np.inf)), SafetyConfig.off(), robot.period)
        res = LoopRunner(robot, ctrl, sup, None, stop_at_end=False).run(int(round(duration * rate_hz)) + 1)
    rec = res.recording
    return rec.t, np.hstack([rec.truth_q, rec.truth_qd])


def replay_open_loop(spec: ScenarioSpec, plant, rate_hz: float, duration: float):
    """A planned scenario's torques replayed open loop (``replay_torques``): (t, X, P, PD) with the reference."""
    x0 = spec.x0 if spec.x0 is not None else rest_state(spec.reference.sample(np.zeros(1))[0][0])
    times = np.asarray(spec.open_loop_times, dtype=float)
    # a plan has a torque at every node; the last node's is never held (the plan ends there)
    t, X = replay_torques(np.asarray(spec.open_loop_torques)[:len(times)], times, plant, x0, rate_hz, duration)
    P, PD, _ = spec.reference.sample(t)
    return t, X, P, PD


def run_scenario(name: str, params: OtbotParams, limits: MotorLimits, t_stab: float | Sequence[float] = 3.0,
                 rate_hz: float = 1000.0, robustness: bool = True, plot_dir: Path | None = None,
                 animate: Path | None = None, check_feasibility: bool = True,
                 error_bounds=None, progress: Callable[[str], None] | None = None,
                 spec: ScenarioSpec | None = None, plant=None, effects: np.ndarray | None = None,
                 backend=None, feedback: str = "truth", safety: SafetyConfig | None = None,
                 path: str | Path | None = None, metadata: dict | None = None, config_path=None,
                 fixes=None, adapt=None) -> dict:
    """Run scenario ``name`` (or a CSV path, or a prebuilt ``spec``); returns the JSON summary
    (see ``otbot track --help``). ``backend`` default: ``DirectBackend(rate_hz)`` (exact sensors);
    robustness and isolated-force reruns use the same back end when it is a simulator, and are
    skipped on the configured bus (its robot cannot be changed). ``fixes``: an absolute pose source
    for the EKF (e.g. ``sim.mocap.MotionCapture``); ``adapt``: an ``AdaptationConfig``: online payload
    adaptation in the main run (not the reruns), reported as ``payload_estimate`` and ``adaptation``."""
    say = progress or (lambda m: None)
    backend = backend or DirectBackend(rate=rate_hz)
    gains = gains_from_tstab(t_stab)
    spec = spec or build_spec(name, params, limits, progress)
    result: dict = {"scenario": spec.name, "gains": gains.to_dict(), **spec.info}
    if check_feasibility:
        from otbot_hw.control.feasibility import ErrorBounds, check_feasibility as feas

        say("torque-feasibility check (interval bound) ...")
        rep = feas(spec.reference, params, gains, limits, error_bounds or ErrorBounds.default(),
                   heading0=0.0 if spec.x0 is None else float(spec.x0[2] - spec.x0[5]), progress=say)
        result["feasibility"] = rep.to_dict()
        for v in rep.violations[:10]:
            say(f"feasibility: {v['motor']} may exceed {v['limit_Nm']:g} N m on "
                f"[{v['t_start']:.2f}, {v['t_end']:.2f}] s (bound {v['bound_Nm']:.1f} N m)")
    say(f"closed loop on {backend.name} at {backend.rate:g} Hz, feedback {feedback}, {spec.reference.duration:.1f} s ...")
    kw = dict(backend=backend, feedback=feedback, plant=plant, effects=effects, safety=safety, config_path=config_path,
              fixes=fixes)
    run = track(spec, params, limits, gains, "nominal", progress=progress, path=path, metadata=metadata, adapt=adapt,
                **kw)
    if run.adapter is not None:
        result["payload_estimate"] = run.adapter.payload_estimate()
        result["adaptation"] = run.adapter.summary(_origin(run))
    if len(run.t) < 2:  # stopped before it tracked anything
        return {**result, "completed": False, "fault": run.loop.fault.to_dict() if run.loop.fault else None,
                "feedback": result.get("feedback", feedback if isinstance(feedback, str) else None),
                "loop": run.loop.stats.to_dict(), "recording": str(path) if path is not None else None}
    result.update(summarize(spec, run, limits, params))
    result["feedback"] = feedback if isinstance(feedback, str) else getattr(feedback, "name", str(feedback))
    result["bus"] = {"sim": None, "bus sim": "sim", "bus config": "config"}.get(backend.name)
    result["backend"] = backend.describe()
    result["estimation_error"] = run.estimation_error()
    result["gates"] = run.gates
    if fixes is not None:
        result["fixes"] = {**fixes.describe(), "accepted": (run.gates or {}).get("updates", {}).get("fix", 0),
                           "rejected": (run.gates or {}).get("rejected", {}).get("fix", 0)}
    result["loop"] = run.loop.stats.to_dict()
    result["wall_time_s"] = run.wall_time_s
    result["completed"] = run.completed
    result["fault"] = run.loop.fault.to_dict() if run.loop.fault is not None else None
    result["true_pose_known"] = run.has_truth
    if path is not None:
        result["recording"] = str(path)
    if not run.completed:
        return result
    reruns = backend.has_truth
    if spec.name == "figure8" and reruns:
        for ev, f in zip(result["events"], FIGURE8_FORCES):
            iso = track(spec, params, limits, gains, "nominal", forces=ForceSchedule([f]), **kw)
            e = event_summary(iso.t, iso.e_p, iso.e_v, [Event(f.start, ev["kind"], f.start + f.duration)])[0]
            ev["settle_time_isolated_s"] = e["settle_time_s"]
    open_loop = None
    if spec.open_loop_torques is not None:
        # replayed for the length of the plan (its torques end there)
        say("open-loop replay of the planned torques ...")
        t, X, P, PD = replay_open_loop(spec, plant or params, backend.rate,
                                       getattr(spec.reference, "end", spec.reference.duration))
        open_loop = (t, X, P)
        ol = error_summary(X[:, :3] - P, X[:, 6:9] - PD)
        if spec.obstacles:
            ol["collisions"] = collisions(X[:, :3], t, spec.obstacles, params.radius)
        ol["final_position_error_m"] = float(np.hypot(*(X[-1, :2] - P[-1, :2])))
        result["open_loop"] = ol
        for c in ol.get("collisions", []):
            say(f"open loop collides with obstacle {c['obstacle']} at t = {c['t_start']:.2f} s "
                f"(penetration {1000 * c['max_penetration_m']:.0f} mm)")
    if robustness and not reruns:
        result["robustness_skipped"] = "the configured bus runs the robot that is there: no plant variants"
    elif robustness:
        result["robustness"] = {}
        for variant in ("payload", "friction"):
            say(f"robustness variant: {variant} ...")
            r = track(spec, params, limits, gains, variant, **kw)
            s = summarize(spec, r, limits, params)
            result["robustness"][variant] = {k: s[k] for k in ("max_abs_error", "rms_error", "fraction_within",
                                                                "peak_torque", "events", "goal_overshoot_m") if k in s}
            if "collisions" in s:
                result["robustness"][variant]["collisions"] = s["collisions"]
            result["robustness"][variant]["completed"] = r.completed
            result["robustness"][variant]["growth_vs_nominal"] = {
                k: (s["max_abs_error"][k] / result["max_abs_error"][k]) if result["max_abs_error"][k] > 0 else None
                for k in ("x", "y", "alpha", "x_dot", "y_dot", "alpha_dot")}
    if plot_dir is not None:
        from otbot_hw.control.plots import scenario_plots

        result["plots"] = scenario_plots(Path(plot_dir), spec, run, params, limits, open_loop)
    if animate is not None:
        from otbot_hw.control.plots import animate_run

        say(f"writing animation {animate} ...")
        result["animation"] = str(animate_run(Path(animate), spec, run, params))
    return result
