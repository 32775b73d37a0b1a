"""Fixed-rate closed loop in simulation: read -> update -> write, one tick per period.

Each tick k (t_k = k / rate): the feedback source reports the task state, the
computed-torque law evaluates u_k against the desired trajectory sampled at t_k, the
limiter clamps (and records) it, and the plant (``otbot_hw.simulation.simulator.Stepper``, the full
multiplier-free model) advances one zero-order-hold period under u_k and the external
pivot force at t_k. The default rate is 1 kHz: the law costs a few microseconds
(``benchmarks/control.py``) and the 1 ms hold makes the sampled loop indistinguishable
from the continuous design at the designed poles (|s2| = 13.3 1/s << 1000 1/s).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from otbot_hw.control.computed_torque import ComputedTorqueController, TaskState
from otbot_hw.control.limiter import TorqueLimiter
from otbot_hw.control.trajectories import DesiredTrajectory
from otbot_hw.params import OtbotParams
from otbot_hw.simulation.simulator import ForceSchedule, Stepper, make_stepper, simulate, simulate_extended

DEFAULT_RATE_HZ = 1000.0


class TruthFeedback:
    """Feedback from the simulator's true state (pure simulation; an EKF replaces it on the robot)."""

    def __init__(self, stepper: Stepper):
        self.stepper = stepper

    def read(self, t: float) -> TaskState:
        return TaskState.from_state(self.stepper.x)


@dataclass
class ClosedLoopRun:
    """A closed-loop run. t (N+1,) s; x (N+1, 12) plant states; per tick k < N: u_cmd (law output),
    u (applied after limiting), u_traj, u_corr (N, 3) N m, f (N, 2) N; reference p_ref, pd_ref (N+1, 3)."""

    t: np.ndarray
    x: np.ndarray
    u_cmd: np.ndarray
    u: np.ndarray
    u_traj: np.ndarray
    u_corr: np.ndarray
    f: np.ndarray
    p_ref: np.ndarray
    pd_ref: np.ndarray
    rate_hz: float
    saturation: list = field(default_factory=list)
    wall_time_s: float = 0.0

    @property
    def e_p(self) -> np.ndarray:
        """Position errors p - p_d (N+1, 3): m, m, rad."""
        return self.x[:, :3] - self.p_ref

    @property
    def e_v(self) -> np.ndarray:
        """Velocity errors p_dot - p_dot_d (N+1, 3): m/s, m/s, rad/s."""
        return self.x[:, 6:9] - self.pd_ref


def rest_state(p: np.ndarray, heading: float = 0.0) -> np.ndarray:
    """State (12,) at rest with the pivot at p = (x, y, alpha) and chassis heading theta (rad)."""
    x0 = np.zeros(12)
    x0[:3] = p
    x0[5] = p[2] - heading
    return x0


def run_closed_loop(reference: DesiredTrajectory, controller: ComputedTorqueController, plant,
                    limiter: TorqueLimiter | None = None, rate_hz: float = DEFAULT_RATE_HZ,
                    duration: float | None = None, x0: np.ndarray | None = None,
                    forces: ForceSchedule | None = None,
                    feedback: Callable[[Stepper], object] = TruthFeedback,
                    progress: Callable[[str], None] | None = None) -> ClosedLoopRun:
    """Track ``reference`` for ``duration`` s (default: its duration) at ``rate_hz``.

    ``plant`` are the true parameters of the simulated robot (``OtbotParams``, or an
    ``ExtendedModel`` with missing-physics effects; they may differ from the controller's);
    ``x0`` defaults to rest at p_d(0) with the chassis heading 0.
    ``feedback`` builds the feedback source from the plant's ``Stepper`` (default: ground truth;
    an estimator would read simulated sensors from ``stepper.x`` and be told the torques).
    """
    if not rate_hz > 0:
        raise ValueError(f"control rate must be > 0 Hz, got {rate_hz}")
    dt = 1.0 / rate_hz
    T = reference.duration if duration is None else float(duration)
    n = int(round(T * rate_hz))
    t = np.arange(n + 1) * dt
    P, PD, PDD = reference.sample(t)
    P, PD, PDD = (np.ascontiguousarray(a) for a in (P, PD, PDD))
    if x0 is None:
        x0 = rest_state(P[0])
    stepper = make_stepper(plant, dt, x0)
    source = feedback(stepper)
    X = np.empty((n + 1, 12))
    X[0] = stepper.x
    Ucmd = np.empty((n, 3))
    U = np.empty((n, 3))
    Ut = np.empty((n, 3))
    Uc = np.empty((n, 3))
    F = np.zeros((n, 2)) if forces is None else forces.sample(t[:-1])
    notify = getattr(source, "command", None)
    every = max(1, n // 10)
    start = time.perf_counter()
    for k in range(n):
        s = source.read(t[k])
        out = controller.update_fast(s.p, s.p_dot, s.phi_p, P[k], PD[k], PDD[k])
        Ucmd[k] = out[0]
        Ut[k] = out[1]
        Uc[k] = out[2]
        u = out[0] if limiter is None else limiter.apply(out[0], t[k])[0]
        U[k] = u
        if notify is not None:
            notify(u, t[k])
        X[k + 1] = stepper.step(u, F[k])
        if progress is not None and k % every == 0 and k:
            progress(f"t = {t[k]:.1f} / {T:.1f} s")
    wall = time.perf_counter() - start
    return ClosedLoopRun(t=t, x=X, u_cmd=Ucmd, u=U, u_traj=Ut, u_corr=Uc, f=F, p_ref=P, pd_ref=PD,
                         rate_hz=rate_hz, saturation=[] if limiter is None else limiter.report(), wall_time_s=wall)


def run_open_loop(torques: np.ndarray, torque_times: np.ndarray, plant, x0: np.ndarray,
                  rate_hz: float = DEFAULT_RATE_HZ, duration: float | None = None):
    """Replay torques (held from each of ``torque_times`` to the next, ZOH) at ``rate_hz``;
    returns (t (N+1,), X (N+1, 12), U (N, 3))."""
    dt = 1.0 / rate_hz
    T = float(torque_times[-1]) if duration is None else float(duration)
    n = int(round(T * rate_hz))
    tk = np.arange(n) * dt
    idx = np.clip(np.searchsorted(torque_times, tk + 1e-12, side="right") - 1, 0, len(torques) - 1)
    U = np.asarray(torques, float)[idx]
    if hasattr(plant, "eff") and plant.active_effects():  # ExtendedModel
        run = simulate_extended(plant.params, plant.eff, U, dt, x0=x0)
    else:
        run = simulate(getattr(plant, "params", plant), U, dt, x0=x0)
    return run.t, run.x, U
