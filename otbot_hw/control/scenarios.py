"""The paper's test cases (§5.4): what to track, and the figures of a tracking run.

The runs themselves go through the one loop runner (``otbot_hw.runtime.tracking``: ``track``,
``run_scenario``) on any back end.

* ``corridor``        — five 3 m segments at 0.6 m/s with 90 deg turns, alpha = 0, from rest,
  ending at (9, 0) m and held 5 s (velocity jumps at start, corners and stop).
* ``corridor-smooth`` — the same corridor rest-to-rest with continuous velocity and
  acceleration (corners rounded over 1 s), no overshoot at the goal.
* ``figure8``         — 18 s figure-8 of straight and circular sections with pivot forces
  of 150 N along -y at 4 s, 200 N along +x at 8 s, 350 N along -x at 11 s, 1 s each.
* ``planned``         — a corridor crowded with circular obstacles planned by
  ``otbot_hw.control.planner``; the planned torques are also replayed open loop (drift and
  collisions reported) before tracking the planned states in closed loop.
* a CSV trajectory file (``sampled_trajectory.load_csv``).

Robustness variants rerun a scenario with (a) the controller's platform mass and inertia
20 % below the plant's (an unknown payload) and (b) viscous friction in the plant that the
controller does not model (the parameters' b_w, b_p, or the paper's 0.18 / 0.24 N m s/rad
when those are zero). Baseline runs use the same parameters in plant and controller.
``growth_vs_nominal`` gives the ratio of each maximum error to the baseline's.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from otbot_hw.control.metrics import Event, error_summary, event_summary, fraction_within, peak_torques
from otbot_hw.control.sampled_trajectory import load_csv
from otbot_hw.control.trajectories import DesiredTrajectory, PolylineTrajectory, corridor, figure_eight
from otbot_hw.motors import MOTORS, MotorLimits
from otbot_hw.params import OtbotParams
from otbot_hw.simulation.simulator import ForceSchedule, PivotForce

SCENARIOS = ("corridor", "corridor-smooth", "figure8", "planned")
PLANNED_HOLD_S = 2.0  # rest at the goal after a planned / CSV trajectory, s
CSV_HOLD_S = 2.0
LONG_RUN_S = 60.0     # simulated seconds beyond which a run reports its progress
#: Paper friction values used by the friction robustness variant when the parameters have none.
PAPER_FRICTION = {"b_w": 0.18, "b_p": 0.24}
#: Half width of the narrow corridor's walls about its centre line, m. The paper gives no width; ours
#: leaves 0.2 m on each side of the nominal 0.5 m footprint.
CORRIDOR_HALF_WIDTH_M = 0.7
FIGURE8_FORCES = (PivotForce(4.0, 1.0, 0.0, -150.0), PivotForce(8.0, 1.0, 200.0, 0.0),
                  PivotForce(11.0, 1.0, -350.0, 0.0))


@dataclass
class ScenarioSpec:
    """What to track: the reference, external forces, events to score, start state, obstacles."""

    name: str
    reference: DesiredTrajectory
    events: list[Event]
    forces: ForceSchedule | None = None
    x0: np.ndarray | None = None
    obstacles: Sequence[tuple[float, float, float]] = ()
    open_loop_torques: np.ndarray | None = None      # (K, 3) N m held from open_loop_times[k]
    open_loop_times: np.ndarray | None = None
    info: dict = field(default_factory=dict)
    walls: Sequence[np.ndarray] = ()                  # wall polylines, (k, 2) m each


def offset_polyline(points, d: float) -> np.ndarray:
    """The polyline ``points`` (k, 2) m moved sideways by ``d`` m (left of the direction of travel
    for d > 0), with mitred corners: the wall of a corridor of half width |d|."""
    pts = np.asarray(points, dtype=float)
    seg = np.diff(pts, axis=0)
    n = np.stack([-seg[:, 1], seg[:, 0]], axis=1) / np.linalg.norm(seg, axis=1)[:, None]
    out = [pts[0] + d * n[0]]
    for i in range(1, len(pts) - 1):
        m = n[i - 1] + n[i]
        out.append(pts[i] + d * m / (1.0 + n[i - 1] @ n[i]))
    out.append(pts[-1] + d * n[-1])
    return np.array(out)


def wall_clearance(xy: np.ndarray, walls: Sequence[np.ndarray], footprint: float) -> float:
    """Smallest distance (m) between the footprint (radius, m) around the pivot path ``xy`` (N, 2)
    and the walls; < 0 means the footprint crossed a wall."""
    best = np.inf
    for wall in walls:
        for a, b in zip(wall[:-1], wall[1:]):
            ab = b - a
            s = np.clip((xy - a) @ ab / (ab @ ab), 0.0, 1.0)
            best = min(best, float(np.min(np.linalg.norm(xy - (a + s[:, None] * ab), axis=1))))
    return best - footprint


def corridor_spec(smooth: bool = False) -> ScenarioSpec:
    ref = corridor(speed=0.6, hold=5.0, smoothing=1.0 if smooth else 0.0)
    ct = ref.corner_times
    kinds = ["start"] + ["corner"] * (len(ct) - 2) + ["stop"]
    # with smoothing there are no velocity steps to recover from: nothing to settle
    events = [] if smooth else [Event(float(t), k, float(t)) for t, k in zip(ct, kinds)]
    centre = np.array(ref.waypoints, dtype=float)  # walls reach past both ends by the half width
    for end, inner in ((0, 1), (-1, -2)):
        d = centre[end] - centre[inner]
        centre[end] += CORRIDOR_HALF_WIDTH_M * d / np.linalg.norm(d)
    walls = [offset_polyline(centre, d) for d in (CORRIDOR_HALF_WIDTH_M, -CORRIDOR_HALF_WIDTH_M)]
    return ScenarioSpec("corridor-smooth" if smooth else "corridor", ref, events, walls=walls)


def figure8_spec() -> ScenarioSpec:
    ref = figure_eight(duration=18.0)
    fs = ForceSchedule(FIGURE8_FORCES)
    events = [Event(f.start, f"force ({f.fx:g}, {f.fy:g}) N", f.start + f.duration) for f in FIGURE8_FORCES]
    return ScenarioSpec("figure8", ref, events, forces=fs)


def csv_spec(path: str | Path) -> ScenarioSpec:
    ref = load_csv(path, hold=CSV_HOLD_S)
    spec = ScenarioSpec(Path(path).stem, ref, [], obstacles=list(ref.obstacles))
    if ref.torques is not None:
        spec.open_loop_torques, spec.open_loop_times = ref.torques, ref.t_samples
    return spec


def build_spec(name: str, params: OtbotParams, limits: MotorLimits,
               progress: Callable[[str], None] | None = None) -> ScenarioSpec:
    """A scenario by name, or a CSV file path."""
    if name == "corridor":
        return corridor_spec(False)
    if name == "corridor-smooth":
        return corridor_spec(True)
    if name == "figure8":
        return figure8_spec()
    if name == "planned":
        from otbot_hw.control.planner import crowded_corridor_problem, plan

        prob = crowded_corridor_problem(params, limits)
        if progress:
            progress("planning the crowded corridor (CasADi + IPOPT) ...")
        res = plan(prob)
        spec = ScenarioSpec("planned", res.trajectory(hold=PLANNED_HOLD_S), [],
                            x0=res.x[0].copy(), obstacles=prob.obstacles_with_radius(),
                            open_loop_torques=res.u, open_loop_times=res.t[:-1], info={"planner": res.summary()})
        if prob.walls is not None:
            x0, x1 = min(prob.start[0], prob.goal[0]) - params.radius, max(prob.start[0], prob.goal[0]) + params.radius
            spec.walls = [np.array([[x0, y], [x1, y]]) for y in prob.walls]
        return spec
    return csv_spec(name)


def controller_params(params: OtbotParams, variant: str,
                      plant: OtbotParams | None = None) -> tuple[OtbotParams, OtbotParams]:
    """(plant, controller) parameters for a robustness variant: nominal, payload, friction.

    ``params`` are the controller's belief; ``plant`` (default: the same) the simulated robot's.
    """
    if plant is not None and variant == "nominal":
        return plant, params
    if plant is not None and hasattr(plant, "eff"):  # ExtendedModel plant: vary its paper parameters
        base, ctrl = controller_params(params, variant, plant.params)
        return type(plant)(base, plant.eff), ctrl
    if plant is not None:
        base_plant, _ = controller_params(plant, variant)
        _, ctrl = controller_params(params, variant)
        return base_plant, ctrl
    if variant == "nominal":
        return params, params
    if variant == "payload":
        return params, params.replace(m_p=0.8 * params.m_p, I_p=0.8 * params.I_p)
    if variant == "friction":
        plant = params if (params.b_w > 0 or params.b_p > 0) else params.replace(**PAPER_FRICTION)
        return plant, params.replace(b_w=0.0, b_p=0.0)
    raise ValueError(f"unknown variant {variant!r} (nominal, payload, friction)")


def collisions(q: np.ndarray, t: np.ndarray, obstacles, footprint: float) -> list[dict]:
    """Contacts of the platform footprint (radius, m) with circular obstacles (cx, cy, r) m:
    one entry per contact episode with its start time and deepest penetration (m)."""
    out = []
    for j, (cx, cy, r) in enumerate(obstacles):
        pen = footprint + r - np.hypot(q[:, 0] - cx, q[:, 1] - cy)
        hit = pen > 0
        if not hit.any():
            continue
        edges = np.flatnonzero(np.diff(np.concatenate([[0], hit.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            out.append({"obstacle": j, "center": [cx, cy], "radius": r, "t_start": float(t[a]),
                        "t_end": float(t[b - 1]), "max_penetration_m": float(pen[a:b].max())})
    return sorted(out, key=lambda c: c["t_start"])


def goal_overshoot(ref: PolylineTrajectory, xy: np.ndarray) -> float:
    """How far (m) the pivot ever got past the goal along the last segment's direction (0 if never)."""
    d = ref.waypoints[-1] - ref.waypoints[-2]
    d = d / np.linalg.norm(d)
    return float(max(0.0, np.max((xy - ref.waypoints[-1]) @ d)))


def summarize(spec: ScenarioSpec, run, limits: MotorLimits, params: OtbotParams) -> dict:
    out = {"duration_s": float(run.t[-1]), "rate_hz": run.rate_hz}
    out.update(error_summary(run.e_p, run.e_v))
    out["fraction_within"] = fraction_within(run.e_p, run.e_v)
    out["peak_torque"] = peak_torques(run.u, limits)
    out["peak_commanded_torque_Nm"] = dict(zip(MOTORS, np.max(np.abs(run.u_cmd), axis=0).tolist()))
    out["events"] = event_summary(run.t, run.e_p, run.e_v, spec.events)
    if isinstance(spec.reference, PolylineTrajectory):
        out["goal_overshoot_m"] = goal_overshoot(spec.reference, run.x[:, :2])
    out["saturation"] = run.saturation
    if spec.obstacles:
        out["collisions"] = collisions(run.x[:, :3], run.t, spec.obstacles, params.radius)
    if spec.walls:
        out["min_wall_clearance_m"] = wall_clearance(run.x[:, :2], spec.walls, params.radius)
    return out
