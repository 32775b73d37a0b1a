"""Is the diagnosed model good enough to name anything?

A finding is only as good as the model around it. When the parameter file is wrong where
the diagnosis does not refit it (a platform load that is not there, a wrong geometry), the
fit reaches for whatever catalog effect bends it closest -- a floor slope of 0.8 m/s², a
chassis mass of 1.6e5 kg, a gain on its bound -- and still does not reach the data. So the
final model is judged three ways before any effect is named:

1. **noise level**, a test with a known size (``residual_tests``): per (recording, channel) and
   per segment of it, T = mean(e^2) / sigma^2 with e the simulation residual and sigma the
   channel's white-noise level measured from the same data (``DiagnosisData.noise_sigma``, MAD of
   second differences, floored at the reading's quantization). Under "the model explains the
   data" e is that white noise and log T is about normal with sd ``NULL_SD`` / sqrt(n - 10)
   (Monte Carlo of the statistic itself -- the MAD estimate's own scatter included, which at
   n = 1000 is larger than the chi-square's -- conservative from 50 to 60000 samples). The
   hypothesis tested is that the unexplained variance is at most ``EXCESS_FITTING`` (fitting) or
   ``EXCESS_HELDOUT`` (held-out: prediction with estimated parameters on a new excitation -- a held-out
   run that reaches beyond the fitting runs' commands or joint rates, ``identifiability.outside_range``,
   fails as "not identifiable from the fitting recordings", not as "model inadequate") of the
   noise variance: one-sided z-test on log T against log(1 + excess), Bonferroni over every
   (recording, channel, segment) test so that the whole diagnosis is wrong on a clean record with
   probability <= ``ALPHA``. Segments (the whole record and up to ``SEGMENTS`` equal parts of
   >= ``MIN_SEGMENT`` samples) catch a misfit that sits in one part of the record. The fitted
   parameters and initial rates absorb some noise (E[T] = 1 - p/n): ignored, which only makes
   the test more conservative;
2. **bounds**: no free parameter (nominal or effect) may sit on a bound of its physical range -- unless
   it is a nominal parameter the data do not determine (its std NaN, or the file's value within
   ``identifiability.BOUND_SIGMAS`` std of the bound, or -- the likelihood-ratio form, for a std
   linearized at the bound -- held at the file's value the fit is less than ``BOUND_SIGMAS`` ** 2 of
   chi2 worse): then it is "not identifiable from this
   recording" (``not_identifiable``, with what to record), not evidence of a wrong model;
3. **plausibility**: the refit nominal parameters stay near the file's values -- relative
   change below ``RELATIVE_SHIFT`` (masses, inertias, frictions), centre-of-mass offsets within
   ``OFFSET_SHIFT``.

Failing any of them gives "model inadequate" with the channels, the parameters under
suspicion (those that moved or hit a bound, and the ones the diagnosis takes as known) and
the identification step to redo.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.stats import norm

from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.identifiability import (BOUND_SIGMAS, PARAMETER_RECORD, outside_range,
                                                undetermined_on_bound)
from otbot_hw.diagnose.refit import FitResult, channel_sigmas, refit, weighted_residuals
from otbot_hw.model.effects import parameter_bounds
from otbot_hw.params import OtbotParams

ALPHA = 0.01  # size of the adequacy test of one diagnosis (all its channel/segment tests together)
NULL_SD = 2.6  # sd of log T x sqrt(n - 10) under the null (white Gaussian noise; Monte Carlo gives 2.45 x sqrt(n))
EXCESS_FITTING = 0.25  # unexplained variance / noise variance tolerated on the fitting recordings (RMS 1.12 x noise)
EXCESS_HELDOUT = 0.5  # ... on the held-out recordings (RMS 1.22 x noise)
SEGMENTS = 4  # equal parts of a record tested on their own besides the whole
MIN_SEGMENT = 100  # samples: shortest part tested on its own
MIN_TEST = 20  # samples: shortest record tested at all
BOUND_FRACTION = 1e-3  # of the bounded range: closer than this to a bound = on it
PROFILE_NFEV = 60  # evaluations of the refit with a parameter on a bound held at the file's value
RELATIVE_SHIFT = {"m_c": 0.3, "I_c": 0.6, "I_p": 0.6, "I_a": 0.6, "b_w": 1.0, "b_p": 1.0}
OFFSET_SHIFT = {"x_B": 0.1, "y_B": 0.1}  # m
#: parameters the diagnosis takes as known, by fixture: the suspects when nothing else moved
KNOWN = {"floor": ("m_p", "x_F", "y_F", "l1", "l2", "r"), "stand": ("I_a", "b_w"), "locked": ("I_p", "b_p")}
REDO = {"m_p": "step 3 (platform: otbot identify platform, with the load as it runs)",
        "x_F": "step 3 (platform: otbot identify platform, with the load as it runs)",
        "y_F": "step 3 (platform: otbot identify platform, with the load as it runs)",
        "I_p": "step 3 (platform: otbot identify platform, with the load as it runs)",
        "m_c": "step 2 (chassis: otbot identify chassis)", "I_c": "step 2 (chassis: otbot identify chassis)",
        "x_B": "step 2 (chassis: otbot identify chassis)", "y_B": "step 2 (chassis: otbot identify chassis)",
        "I_a": "step 1 (wheels on the stand: otbot identify wheel)",
        "b_w": "step 1 (wheels on the stand: otbot identify wheel)",
        "b_p": "step 1 (pivot with locked wheels: otbot identify pivot)",
        "l1": "a measurement of the geometry (l1, l2, r) in config/otbot.yaml",
        "l2": "a measurement of the geometry (l1, l2, r) in config/otbot.yaml",
        "r": "a measurement of the geometry (l1, l2, r) in config/otbot.yaml"}


@dataclass
class Adequacy:
    """Verdict on the final model: ``adequate``; channels above the noise level {set, recording, channel,
    noise_ratio, limit}; parameters on a bound; nominal parameters that moved implausibly; suspects; advice."""

    adequate: bool
    channels: list[dict] = field(default_factory=list)
    on_bound: list[dict] = field(default_factory=list)
    moved: list[dict] = field(default_factory=list)
    suspect_parameters: list[str] = field(default_factory=list)
    advice: str = ""
    tests: int = 0  # residual tests made (recording x channel x segment); each at ALPHA / tests
    alpha: float = ALPHA
    #: nominal parameters on a bound that the data do not determine {parameter, value, bound, side, std, file,
    #: why, record}: "not identifiable from this recording", not a reason for "model inadequate"
    not_identifiable: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def noise_ratios(recordings: list[DiagnosisData], fit_model) -> dict[tuple[str, str], float]:
    """RMS of the simulation residual / the channel's white-noise level, per (recording, channel)."""
    return {k: float(np.sqrt(np.mean(r ** 2))) for k, r in _residuals(recordings, fit_model).items()}


def _residuals(recordings, fit_model) -> dict[tuple[str, str], np.ndarray]:
    return weighted_residuals(recordings, fit_model, channel_sigmas(recordings))


def segments(n: int) -> list[tuple[int, int]]:
    """Sample ranges tested: the whole record, then up to ``SEGMENTS`` equal parts of >= ``MIN_SEGMENT``."""
    out = [(0, n)]
    k = min(SEGMENTS, n // MIN_SEGMENT)
    if k >= 2:
        edges = np.linspace(0, n, k + 1).astype(int)
        out += [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]
    return out


def log_t_sd(n: int) -> float:
    """Standard deviation of log(mean(e^2) / sigma_hat^2) for n samples of white noise."""
    return NULL_SD / np.sqrt(max(n - 10, 1))


def residual_tests(residuals: dict[tuple[str, str], np.ndarray], excess: float, label: str) -> list[dict]:
    """One test per (recording, channel, segment) of noise-weighted residuals r = e / sigma_hat:
    {set, recording, channel, t_start_sample, t_end_sample, samples, noise_ratio (RMS of r), excess
    (tolerated), z, p_value (one-sided, at the tolerated excess)}."""
    out = []
    for (name, ch), r in residuals.items():
        r = np.asarray(r, dtype=float)
        if len(r) < MIN_TEST:
            continue
        for a, b in segments(len(r)):
            ms = float(np.mean(r[a:b] ** 2))
            z = (np.log(max(ms, 1e-300)) - np.log1p(excess)) / log_t_sd(b - a)
            out.append({"set": label, "recording": name, "channel": ch, "samples": [a, b],
                        "noise_ratio": float(np.sqrt(ms)), "excess": excess, "z": float(z),
                        "p_value": float(norm.sf(z))})
    return out


def failed(tests: list[dict], alpha: float = ALPHA) -> list[dict]:
    """Tests rejected at the Bonferroni level alpha / (number of tests); each gets its ``limit``: the RMS
    ratio at which it would have been rejected."""
    if not tests:
        return []
    level = alpha / len(tests)
    zc = float(norm.isf(level))
    out = []
    for t in tests:
        a, b = t["samples"]
        limit = float(np.sqrt(np.exp(np.log1p(t["excess"]) + zc * log_t_sd(b - a))))
        if not t["p_value"] >= level:
            out.append({**t, "limit": limit, "level": level})
    return out


def above_noise(ratios: dict[tuple[str, str], float], limit: float, label: str) -> list[dict]:
    """(recording, channel) entries whose residual RMS / noise ratio exceeds ``limit`` (a plain check, used
    for reports; the verdict is ``residual_tests``)."""
    return [{"set": label, "recording": name, "channel": ch, "noise_ratio": r, "limit": limit}
            for (name, ch), r in ratios.items() if not r <= limit]


def on_bound(values: dict[str, float]) -> list[dict]:
    """Free parameters within ``BOUND_FRACTION`` of the range of a finite bound. A lower bound of
    exactly 0 is not counted: there 0 is a physical value (that part of the effect is absent, e.g.
    no creep below the traction limit), not a clipped estimate."""
    out = []
    for n, v in values.items():
        lo, hi = parameter_bounds(n)
        span = (hi - lo) if np.isfinite(hi - lo) else max(abs(v), 1.0)
        for side, b in (("lower", lo), ("upper", hi)):
            if np.isfinite(b) and abs(v - b) <= BOUND_FRACTION * span and not (side == "lower" and b == 0.0):
                out.append({"parameter": n, "value": float(v), "bound": float(b), "side": side})
    return out


SHIFT_SIGMAS = 3.0  # a move counts as implausible only when it exceeds the limit by this many of its std


def implausible_shifts(values: dict[str, float], given: OtbotParams, std: dict[str, float] | None = None) -> list[dict]:
    """Nominal parameters the refit moved further from the parameter file than is physically plausible --
    by more than the limit plus ``SHIFT_SIGMAS`` of the estimate's std (``std``; a parameter the record
    does not determine, std NaN, is not evidence of a wrong file: a 1 s run under one constant torque
    leaves x_B free to wander)."""
    out = []
    std = std or {}
    for n, v in values.items():
        s = std.get(n, 0.0)
        if s is None or not np.isfinite(s):
            if n in std:
                continue
            s = 0.0
        if n in RELATIVE_SHIFT:
            ref = getattr(given, n)
            rel = abs(v - ref) / abs(ref) if ref != 0 else float("inf")
            if rel > RELATIVE_SHIFT[n] + SHIFT_SIGMAS * s / max(abs(ref), 1e-12):
                out.append({"parameter": n, "file": float(ref), "refit": float(v), "change": f"{100 * rel:.0f} %",
                            "limit": f"{100 * RELATIVE_SHIFT[n]:.0f} %"})
        elif n in OFFSET_SHIFT:
            ref = getattr(given, n)
            if abs(v - ref) > OFFSET_SHIFT[n] + SHIFT_SIGMAS * s:
                out.append({"parameter": n, "file": float(ref), "refit": float(v),
                            "change": f"{abs(v - ref):.3f} m", "limit": f"{OFFSET_SHIFT[n]} m"})
    return out


def _profile_undetermined(recordings: list[DiagnosisData], final: FitResult, b: dict, file_value: float) -> dict | None:
    """The likelihood-ratio form of ``undetermined_on_bound`` for a nominal parameter on a bound whose std
    says it is determined: held at the file's value, the others refit from the final fit, the weighted RSS
    rises by less than ``BOUND_SIGMAS`` ** 2 (noise units) -> the data do not tell the bound from the file's
    value (the std, linearized at the bound, overstates what they say: a traction limit under closed-loop
    torques, I_c 0 +- 0.33 kg m^2 at the bound, the file's 1.3 only 7 units of chi2 worse). The entry as
    ``undetermined_on_bound``'s, or None."""
    n = b["parameter"]
    others = [m for m in final.names if m != n]
    held = refit(recordings, final.model.with_values({n: file_value}), others, max_nfev=PROFILE_NFEV)
    rise = sum(held.rss.values()) - sum(final.rss.values())
    if not rise < BOUND_SIGMAS ** 2:
        return None
    return {**b, "kind": "parameter", "name": n, "std": _finite_or_none(final.std.get(n)), "file": file_value,
            "chi2_rise": float(rise),
            "why": f"on its {b['side']} bound, but held at the file's {file_value:.4g} (the others refit) the fit is "
                   f"only {max(rise, 0.0):.3g} (chi2, noise units) worse, below {BOUND_SIGMAS ** 2:g}: the data do "
                   "not determine it",
            "record": PARAMETER_RECORD.get(n, "a richer excitation")}


def _finite_or_none(v):
    return float(v) if v is not None and np.isfinite(v) else None


def assess(recordings: list[DiagnosisData], holdout: list[DiagnosisData], final: FitResult,
           given: OtbotParams) -> Adequacy:
    """Judge the final model (see module doc)."""
    tests = []
    for label, recs, excess in (("fitting", recordings, EXCESS_FITTING), ("heldout", holdout, EXCESS_HELDOUT)):
        if recs:
            tests += residual_tests(_residuals(recs, final.model), excess, label)
    channels = failed(tests)
    # a held-out run that goes beyond the fitting runs' commands or speeds tests what they could not reveal:
    # its misfit is "not identifiable from these recordings", not evidence of a wrong model
    beyond = []
    for d in holdout:
        mine = [c for c in channels if c["set"] == "heldout" and c["recording"] == d.name]
        where = outside_range(recordings, d) if mine else []
        if where:
            channels = [c for c in channels if c not in mine]
            worst = max(mine, key=lambda c: c["z"])
            beyond.append({"kind": "range", "name": d.name, "channels": sorted({c["channel"] for c in mine}),
                           "why": f"the held-out run reaches beyond the fitting runs ({'; '.join(where[:3])}) and "
                                  f"the model fitted on them misses it there ({worst['channel']} "
                                  f"{worst['noise_ratio']:.2f} x noise): what acts there is not identifiable from "
                                  "the fitting recordings",
                           "record": "a fitting recording that covers the held-out run's commands and speeds (or "
                                     "diagnose with this run among the fitting recordings)"})
    bound = on_bound(final.values)
    undetermined = undetermined_on_bound(bound, final.std, {n: float(getattr(given, n)) for n in final.values
                                                            if hasattr(given, n)})
    bound = [b for b in bound if b["parameter"] not in {u["parameter"] for u in undetermined}]
    profiled = [u for u in (_profile_undetermined(recordings, final, b, float(getattr(given, b["parameter"])))
                            for b in bound if hasattr(given, b["parameter"])) if u]
    undetermined += profiled
    bound = [b for b in bound if b["parameter"] not in {u["parameter"] for u in profiled}]
    moved = implausible_shifts({n: v for n, v in final.values.items() if hasattr(given, n)}, given, final.std)
    adequate = not (channels or bound or moved)
    suspects: list[str] = []
    if not adequate:
        suspects += [m["parameter"] for m in moved] + [b["parameter"] for b in bound]
        for d in recordings:
            suspects += list(KNOWN[d.fixture])
        suspects = list(dict.fromkeys(s for s in suspects if hasattr(given, s)))
    steps = list(dict.fromkeys(REDO[s] for s in suspects if s in REDO))
    advice = ""
    if not adequate:
        advice = ("check the parameter file against the robot as it ran (the diagnosis refits "
                  f"{', '.join(n for n in final.names if hasattr(given, n)) or 'no nominal parameter'} and takes "
                  "the others as known), redo identification " + "; or ".join(steps[:3]) +
                  ", then diagnose again; if the parameters are right, the missing physics is outside the catalog")
    return Adequacy(adequate, channels, bound, moved, suspects, advice, len(tests),
                    not_identifiable=undetermined + beyond)
