"""Recordings with one hidden effect, for proving the diagnosis (``otbot diagnose --demo``, tests, study).

The run is simulated with the extended model (``otbot_hw.model.effects``) and recorded
with the paper's sensor noise. The recording holds only what a real robot logs
(commands, encoders, IMU); the hidden effect and the true state are written to the
``/otbot/truth`` topic and the ``truth`` metadata entry, which the diagnosis never reads.

Excitations (all at ``dt`` s zero-order hold):

* ``multisine``: zero-mean sums of sines 0.1-1.5 Hz on every motor (arbitrary torques, reversals);
* ``tracking``: smooth low-frequency torques with a slowly varying drive, as a
  trajectory-tracking controller commands them;
* ``steps``: piecewise-constant torque steps of random sign and size (bench-like);
* ``stand``: multisine wheel and pivot torques with the robot on the stand (wheels free).
"""
from __future__ import annotations

import numpy as np

from otbot_hw.model import effects as fx
from otbot_hw.params import OtbotParams
from otbot_hw.recording import Recording
from otbot_hw.sensors import NoiseModel
from otbot_hw.simulation.runs import extended_recording

EXCITATIONS = ("multisine", "tracking", "steps", "stand")


def excitation(kind: str, duration: float, dt: float, seed: int) -> tuple[np.ndarray, str]:
    """Commanded torques (N, 3) N m and the fixture for an excitation ``kind``."""
    rng = np.random.default_rng(seed)
    n = int(round(duration / dt))
    t = np.arange(n) * dt
    if kind in ("multisine", "stand"):
        freqs = np.array([0.1, 0.23, 0.37, 0.61, 0.9, 1.3])
        amp = np.array([4.0, 4.0, 2.5]) if kind == "multisine" else np.array([1.2, 1.2, 3.0])
        U = np.zeros((n, 3))
        for j in range(3):
            ph = rng.uniform(0, 2 * np.pi, len(freqs))
            w = rng.uniform(0.5, 1.0, len(freqs))
            s = (w[:, None] * np.sin(2 * np.pi * freqs[:, None] * t[None, :] + ph[:, None])).sum(0)
            U[:, j] = amp[j] * s / np.max(np.abs(s))
        return U, ("floor" if kind == "multisine" else "stand")
    if kind == "tracking":
        drive = 3.0 * np.sin(2 * np.pi * 0.12 * t + rng.uniform(0, 6.3))
        turn = 2.0 * np.sin(2 * np.pi * 0.31 * t + rng.uniform(0, 6.3))
        piv = 2.0 * np.sin(2 * np.pi * 0.2 * t + rng.uniform(0, 6.3)) + 0.8 * np.sin(2 * np.pi * 0.73 * t)
        U = np.column_stack([drive + turn, drive - turn, piv]) + 0.3 * rng.standard_normal((n, 3))
        return U, "floor"
    if kind == "steps":
        hold = max(1, int(round(0.5 / dt)))
        levels = rng.uniform(-6, 6, (n // hold + 1, 3)) * np.array([1.0, 1.0, 0.6])
        return np.repeat(levels, hold, axis=0)[:n], "floor"
    raise ValueError(f"unknown excitation '{kind}' (known: {', '.join(EXCITATIONS)})")


def concealed_recording(params: OtbotParams, effect_values: dict[str, float] | None, kind: str = "multisine",
                        duration: float = 10.0, dt: float = 0.01, seed: int = 0,
                        noise: NoiseModel | None = None, effect_name: str | None = None) -> Recording:
    """A recording of the extended model with hidden ``effect_values`` ({} = negative control)."""
    noise = noise or NoiseModel.paper()
    model = fx.ExtendedModel(params, fx.effect_vector()).with_values(dict(effect_values or {}))
    U, fixture = excitation(kind, duration, dt, seed)
    rec = extended_recording(model, U, dt, noise, seed=10_000 + seed, fixture=fixture)
    # what the diagnosis must find stays under "truth" (never read by it), not in plain metadata
    for k in ("params", "effects", "noise", "seed", "initial_state"):
        rec.metadata.pop(k)
    rec.metadata.update({"experiment": kind, "truth": {
        "hidden_effect": effect_name or ("none" if not effect_values else "custom"),
        "effect_parameters": dict(effect_values or {}), "params": params.to_dict(), "noise": noise.to_dict(),
        "seed": seed}})
    return rec
