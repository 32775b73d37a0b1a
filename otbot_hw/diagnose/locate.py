"""Where and when model and recording part ways: windows flagged by statistical tests, tagged by regime.

For each recording the residuals are cut into windows of ``WINDOW`` seconds:

* simulation residual per channel (CHANNELS), in units of the channel's white-noise
  level sigma (``DiagnosisData.noise_sigma``): chi-square test of sum (r/sigma)^2 with
  n degrees of freedom, and a Wald-Wolfowitz runs test on the residual signs
  (too few runs = structured, non-white residual);
* inverse-dynamics torque residual per joint (N m): chi-square against the noise level
  the encoder noise gives the torque residual through the same filters (Monte Carlo with
  the encoder noise level estimated from the recording), with n / L degrees of freedom
  (L = filter window: the filtered residual is correlated over L samples).

A window is flagged when a test's p-value is below ``ALPHA`` / (number of tests of
that recording) (Bonferroni). Regimes come from the measured signals only:
direction reversal, low speed, standstill, high turn rate, high torque, torque step.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats

from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.residuals import estimate_motion, joint_rates, torque_residual
from otbot_hw.diagnose.simulated_run import simulation_residual
from otbot_hw.model.effects import ExtendedModel

WINDOW = 0.5  # s
ALPHA = 0.01
STANDSTILL = 0.05  # rad/s, every joint slower than this
LOW_SPEED = 0.05  # m/s of the pivot (floor) / 0.5 rad/s of the wheels (bench)
HIGH_TURN = 0.5  # rad/s of the platform
HIGH_TORQUE = 0.8  # fraction of the largest |command| in the recording
STEP = 0.25  # fraction of the command range changing in one sample


@dataclass
class Window:
    """A flagged window: recording, residual ``kind`` (simulation / torque), channel, time span (s),
    test statistic, p-value, RMS of the residual in the window (channel units) and regime tags."""

    recording: str
    kind: str
    channel: str
    t_start: float
    t_end: float
    test: str
    statistic: float
    p_value: float
    rms: float
    regimes: list[str]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["p_value"] = float(max(d["p_value"], 1e-300))
        return d


def runs_test(r: np.ndarray) -> tuple[float, float]:
    """Wald-Wolfowitz runs test on the signs of r: (z statistic, one-sided p for too few runs)."""
    s = r > np.median(r)
    n1, n2 = int(s.sum()), int((~s).sum())
    if n1 == 0 or n2 == 0:
        return 0.0, 1.0
    runs = 1 + int(np.sum(s[1:] != s[:-1]))
    mu = 2.0 * n1 * n2 / (n1 + n2) + 1
    var = 2.0 * n1 * n2 * (2.0 * n1 * n2 - n1 - n2) / ((n1 + n2) ** 2 * (n1 + n2 - 1))
    if var <= 0:
        return 0.0, 1.0
    z = (runs - mu) / np.sqrt(var)
    return float(z), float(stats.norm.cdf(z))


def regimes(data: DiagnosisData, k0: int, k1: int, speed: np.ndarray, turn: np.ndarray,
            vel: np.ndarray) -> list[str]:
    """Regime tags of samples k0..k1-1 (measured signals only; vel: smoothed joint rates)."""
    tags = []
    v = vel[k0:k1]
    moving = np.abs(v) > STANDSTILL
    if np.any(np.diff(np.sign(v[:, :]), axis=0)[np.abs(v[1:]) > STANDSTILL] != 0):
        tags.append("direction reversal")
    if not np.any(moving):
        tags.append("standstill")
    elif np.median(speed[k0:k1]) < LOW_SPEED:
        tags.append("low speed")
    if np.max(np.abs(turn[k0:k1])) > HIGH_TURN:
        tags.append("high turn rate")
    umax = np.max(np.abs(data.u), axis=0)
    if np.any(np.abs(data.u[k0:k1]) > HIGH_TORQUE * np.maximum(umax, 1e-9)):
        tags.append("high torque")
    rng = np.ptp(data.u, axis=0)
    du = np.abs(np.diff(data.u[max(k0 - 1, 0):k1], axis=0))
    if np.any(du > STEP * np.maximum(rng, 1e-9)):
        tags.append("torque step")
    return tags


def locate(recordings: list[DiagnosisData], model: ExtendedModel) -> list[Window]:
    """Flagged windows of every recording against ``model``."""
    out: list[Window] = []
    for d in recordings:
        sim = simulation_residual(d, model)
        m = estimate_motion(d, model)
        tr = torque_residual(d, model, m)
        speed = np.hypot(m.qd[:, 0], m.qd[:, 1]) if d.fixture == "floor" else np.abs(m.qd[:, 3]) * 0.1
        turn = m.qd[:, 2]
        vel, _ = joint_rates(d)
        w = max(8, int(round(WINDOW / d.dt)))
        starts = list(range(0, len(d) - w // 2, w))
        tests = []
        for ch, r in sim.items():
            sig = d.noise_sigma(ch)
            for k0 in starts:
                rr = r[k0:k0 + w] / sig
                chi = float(rr @ rr)
                tests.append(("simulation", ch, k0, min(k0 + w, len(d)), "chi-square", chi,
                              float(stats.chi2.sf(chi, len(rr))), float(np.sqrt(np.mean((rr * sig) ** 2)))))
                z, p = runs_test(rr)
                tests.append(("simulation", ch, k0, min(k0 + w, len(d)), "runs", z, p,
                              float(np.sqrt(np.mean((rr * sig) ** 2)))))
        L = d.window
        level = torque_noise(d, model, tr)
        joints = ("tau_r", "tau_l", "tau_p") if d.fixture != "locked" else ("tau_p",)
        for j, name in enumerate(("tau_r", "tau_l", "tau_p")):
            if name not in joints:
                continue
            for k0 in starts:
                a, b = max(k0, L), min(k0 + w, len(d) - L)
                if b - a < L:
                    continue
                rr = tr[a:b, j]
                dof = max(1.0, (b - a) / L)
                chi = float(np.mean(rr ** 2) / level[j] ** 2 * dof)
                tests.append(("torque", name, k0, min(k0 + w, len(d)), "chi-square", chi,
                              float(stats.chi2.sf(chi, dof)), float(np.sqrt(np.mean(rr ** 2)))))
        limit = ALPHA / max(1, len(tests))
        for kind, ch, k0, k1, test, stat, p, rms in tests:
            if p < limit:
                out.append(Window(d.name, kind, ch, float(d.t[k0]), float(d.t[k1 - 1] + d.dt), test, stat, p, rms,
                                  regimes(d, k0, k1, speed, turn, vel)))
    return out


def torque_noise(data: DiagnosisData, model: ExtendedModel, clean: np.ndarray, seed: int = 0) -> np.ndarray:
    """RMS (3,) N m that encoder noise alone gives the torque residual: Monte Carlo through the same
    filters, with each encoder rate's white-noise level estimated from the recording."""
    from dataclasses import replace

    rng = np.random.default_rng(seed)
    vel = data.enc_vel.copy()
    for j, ch in enumerate(("w_r", "w_l", "w_p")):
        if ch not in data.unusable:
            vel[:, j] = vel[:, j] + data.noise_sigma(ch) * rng.standard_normal(len(data))
    noisy = torque_residual(replace(data, enc_vel=vel), model)
    L = data.window
    d = (noisy - clean)[L:-L]
    return np.maximum(np.sqrt(np.mean(d ** 2, axis=0)), 1e-9)


def summarize(windows: list[Window]) -> dict:
    """Counts of flagged windows per (kind, channel) and per regime."""
    per_channel: dict[str, int] = {}
    per_regime: dict[str, int] = {}
    for w in windows:
        key = f"{w.kind}:{w.channel}"
        per_channel[key] = per_channel.get(key, 0) + 1
        for r in w.regimes or ["none"]:
            per_regime[r] = per_regime.get(r, 0) + 1
    return {"per_channel": per_channel, "per_regime": per_regime}
