"""What a recording can and cannot reveal: "not identifiable from this recording".

Two questions, both answered from the information the fitter already has:

1. **Effects** (``effect_identifiability``): would an effect of the catalog's smallest size
   (``Effect.magnitudes[0]``) show in this recording? Its *signature energy* is the change of the
   noise-weighted simulation outputs it causes, after projecting out what the free nominal
   parameters can absorb: chi2 = ||P A 1||^2, with A the effect's sensitivity columns at the catalog
   step (``screening.screen_simulation``; the Fisher information of the catalog step, in units of
   the noise) and P the projection orthogonal to the nominal parameters' columns. A nested fit of
   the effect gains about chi2 of BIC and pays k ln N for its k parameters, so it can be accepted
   (``rules.has_evidence``: ``ACCEPT_DBIC`` of evidence) only when chi2 >= ``ACCEPT_DBIC`` + k ln N
   (``needed_chi2``). Below that the recording cannot reveal the effect at that size: "not identifiable
   from this recording", with what to record instead (``EFFECT_RECORD``). For a linear parameter chi2
   grows with the square of the size, so the size it could reveal is quoted as well.
2. **Parameters on a bound** (``undetermined_on_bound``): a free nominal parameter that the fit pushed
   onto a bound of its range is evidence of a wrong model only when the data determine it. When its
   std says they do not -- NaN, or the file's value within ``BOUND_SIGMAS`` std of the bound (the fit
   could sit at the file's value as well) -- it is "not identifiable from this recording" with the
   experiment that determines it (``PARAMETER_RECORD``), not "model inadequate".
"""
from __future__ import annotations

import numpy as np

from otbot_hw.diagnose.rules import ACCEPT_DBIC

BOUND_SIGMAS = 3.0  # file value within this many std of the bound: the data do not determine the parameter

#: what to record so that the effect shows (excitation that makes its signature large against the noise)
EFFECT_RECORD = {
    "coulomb_wheels": "wheel direction reversals and slow wheel speeds (torques of both signs, several amplitudes)",
    "coulomb_pivot": "pivot direction reversals (pivot torques of both signs at several amplitudes)",
    "stribeck_wheels": "slow ramps of the wheel speed through zero (stand or floor), several times",
    "rolling_resistance": "a floor run of several seconds with wheel reversals, then the same on the stand",
    "caster_drag": "a floor run that turns the chassis both ways and drives in several directions",
    "wheel_slip": "a floor run with hard wheel accelerations (large torque steps of both signs)",
    "traction_limit": "a floor run with wheel torques near the drives' limit (large steps of both signs)",
    "floor_slope": "a floor run of several seconds that turns the chassis through a full revolution",
    "air_drag": "a floor run at higher platform speed (1 m/s or more) for several seconds",
    "gain_right": "a run with large torque steps of the right wheel motor, held long enough to accelerate",
    "gain_left": "a run with large torque steps of the left wheel motor, held long enough to accelerate",
    "gain_pivot": "a run with large pivot torque steps, held long enough to accelerate the platform",
    "torque_saturation": "a run whose commands reach near the drives' limit",
    "saturation_right": "a run whose right-wheel commands reach near the drive's limit",
    "saturation_left": "a run whose left-wheel commands reach near the drive's limit",
    "saturation_pivot": "a run whose pivot commands reach near the drive's limit",
    "current_lag": "fast torque steps or a chirp up to several Hz",
    "imu_bias": "a run of several seconds with stops (standstill lets the bias show against the encoders)",
    "imu_lever_arm": "a run with fast platform turns (high and changing turn rate)",
    "imu_misalignment": "a floor run with straight accelerations in several directions",
    "imu_latency": "fast torque steps or a chirp up to several Hz at a high IMU rate",
    "encoder_scale": "a floor run that drives straight and turns, several seconds",
    "wheel_friction_asymmetry": "a run at steady wheel speeds of both signs (coast-downs on the stand)",
    "wheel_radii": "a floor run that drives straight and turns in place, several seconds",
}

#: what to record so that a nominal parameter is determined (the identification step that isolates it)
PARAMETER_RECORD = {
    "m_c": "a floor run with straight accelerations of both signs (otbot identify chassis)",
    "I_c": "a floor run that turns the chassis (wheels in opposite directions) for several seconds, "
           "or otbot identify chassis",
    "x_B": "a floor run that turns the chassis while driving (otbot identify chassis)",
    "y_B": "a floor run that turns the chassis while driving (otbot identify chassis)",
    "I_p": "pivot torque steps with the wheels locked (otbot identify pivot)",
    "I_a": "wheel torque steps on the stand (otbot identify wheel)",
    "b_w": "wheels spun on the stand at several steady speeds (otbot identify wheel)",
    "b_p": "pivot turned at several steady speeds with the wheels locked (otbot identify pivot)",
}


def needed_chi2(k: int, n: int) -> float:
    """Signature energy (chi2 in noise units) an effect with ``k`` parameters needs over ``n`` weighted
    samples to be accepted: ``ACCEPT_DBIC`` of BIC evidence after its penalty k ln n."""
    return float(ACCEPT_DBIC + k * np.log(max(n, 2)))


def effect_identifiability(energy: dict[str, tuple[float, int, int, dict]]) -> dict[str, dict]:
    """{effect: {signature_chi2, needed_chi2, identifiable, magnitude, revealable_factor}} from the
    screening's signature energies ``{effect: (chi2, k, n, magnitude)}``. ``revealable_factor``: the
    size, as a multiple of the catalog step, at which the signature would reach the need (chi2 grows
    with the square of a linear parameter)."""
    out = {}
    for name, (chi2, k, n, magnitude) in energy.items():
        need = needed_chi2(k, n)
        factor = float(np.sqrt(need / chi2)) if chi2 > 0 else float("inf")
        out[name] = {"signature_chi2": float(chi2), "needed_chi2": need, "identifiable": bool(chi2 >= need),
                     "magnitude": {p: float(v) for p, v in magnitude.items()}, "revealable_factor": factor}
    return out


def not_identifiable_effects(ident: dict[str, dict], found: set[str], titles: dict[str, str]) -> list[dict]:
    """Entries of "not identifiable from this recording" for the effects the recording cannot reveal at the
    catalog's smallest size (found ones excluded: what was found was evidently revealed)."""
    out = []
    for name, v in ident.items():
        if v["identifiable"] or name in found:
            continue
        size = ", ".join(f"{p} = {x:.3g}" for p, x in v["magnitude"].items())
        out.append({"kind": "effect", "name": name, "title": titles.get(name, name),
                    "why": f"an effect of {size} would change the outputs by chi2 {v['signature_chi2']:.3g} "
                           f"(noise units, after what the nominal refit absorbs); {v['needed_chi2']:.3g} needed",
                    "record": EFFECT_RECORD.get(name, "a longer, richer excitation")})
    return out


def undetermined_on_bound(bound: list[dict], std: dict[str, float], file_values: dict[str, float]) -> list[dict]:
    """The entries of ``bound`` (``adequacy.on_bound``) for nominal parameters (those in ``file_values``)
    that the data do not determine: std NaN, or the file's value within ``BOUND_SIGMAS`` std of the bound.
    Each gets {std, file, why, record}."""
    out = []
    for b in bound:
        n = b["parameter"]
        if n not in file_values:
            continue
        s = std.get(n, float("nan"))
        ref = file_values[n]
        if s is None or not np.isfinite(s) or abs(ref - b["bound"]) < BOUND_SIGMAS * s:
            why = ("std not identifiable" if s is None or not np.isfinite(s) else
                   f"std {s:.3g}: the file's {ref:.4g} is within {BOUND_SIGMAS:g} std of the {b['side']} bound "
                   f"{b['bound']:.4g}")
            out.append({**b, "kind": "parameter", "name": n, "std": None if s is None or not np.isfinite(s)
                        else float(s), "file": float(ref), "why": f"on its {b['side']} bound, {why}: "
                        "the data do not determine it", "record": PARAMETER_RECORD.get(n, "a richer excitation")})
    return out


def signature_chi2(recordings, model, nominal_free: list[str], values: dict[str, float]) -> tuple[float, int]:
    """(chi2, n): the signature energy in ``recordings`` of the effect ``values`` switched on in ``model`` --
    the change of the noise-weighted simulation outputs with the free nominal parameters' sensitivities
    projected out, as ``screening.screen_simulation`` computes it at the catalog step -- and the number of
    weighted samples. For studies that know the true effect (``benchmarks/diagnose_independent.py``): the
    Fisher criterion at the truth is ``chi2 >= needed_chi2(k, n)``."""
    from otbot_hw.diagnose.refit import channel_sigmas, weighted_residuals

    sig = channel_sigmas(recordings)

    def vec(m):
        res = weighted_residuals(recordings, m, sig)
        return np.concatenate([res[k] for k in sorted(res)])

    r0 = vec(model)
    cols = [vec(model.with_values({n: model.get(n) + 1e-4 * max(abs(model.get(n)), 1e-2)})) - r0 for n in nominal_free]
    d = vec(model.with_values(values)) - r0
    if cols:
        q, rr = np.linalg.qr(np.column_stack(cols))
        q = q[:, np.abs(np.diag(rr)) > 1e-8 * np.max(np.abs(np.diag(rr)))]
        d = d - q @ (q.T @ d)
    return float(d @ d), len(r0)


#: what to record so that a parameter of a found effect is determined (its part of the law acts)
EFFECT_PARAMETER_RECORD = {
    "k_slip": "wheel torques that stay below the traction limit, or ramp slowly through it (the creep slope "
              "shows only below the limit)",
    "t_trac": "a hard start with wheel torques above the traction limit",
    "v_s": "slow ramps of the wheel speed through zero (stand or floor), several times",
    "s_w": "slow ramps of the wheel speed through zero (stand or floor), several times",
}


def undetermined_effect_parameters(effects: list[dict], typical: dict[str, float] | None = None) -> list[dict]:
    """Entries of "not identifiable from this recording" for parameters of found effects that the data do not
    determine: std NaN in the final fit (the Fisher information of that parameter is singular), or a std above
    the parameter's ``typical`` size (the catalog's smallest step: the data cannot tell that size from none)
    -- e.g. the creep slope of a traction limit under constant torques far above the limit, where the wheels
    spin from the first sample on. ``effects``: the diagnosis's effect entries (``parameters`` {value, std}).
    The effect is found; the value reported for that parameter is not a measurement."""
    typical = typical or {}
    out = []
    for e in effects:
        for n, v in e["parameters"].items():
            s = v.get("std")
            if s is None or (n in typical and s > abs(typical[n])):
                out.append({"kind": "parameter", "name": n, "effect": e["name"], "value": v["value"],
                            "why": f"{e['name']} is found, but this recording does not determine its {n} ("
                                   + ("std not identifiable: its information in the data is nil" if s is None else
                                      f"std {s:.3g}, above its typical size {abs(typical[n]):.3g}") + ")",
                            "record": EFFECT_PARAMETER_RECORD.get(n, "a richer excitation of that effect")})
    return out


RANGE_MARGIN = 0.02  # of the fitting recordings' span: a held-out run beyond it is outside their range
RANGE_CHANNELS = (("u_r", "N m"), ("u_l", "N m"), ("u_p", "N m"), ("w_r", "rad/s"), ("w_l", "rad/s"),
                  ("w_p", "rad/s"))


def _ranges(d) -> dict[str, tuple[float, float]]:
    out = {}
    for j, (name, _) in enumerate(RANGE_CHANNELS[:3]):
        out[name] = (float(np.min(d.u[:, j])), float(np.max(d.u[:, j])))
    for name, _ in RANGE_CHANNELS[3:]:
        y = d.measured(name)
        if y is not None and np.any(np.isfinite(y)):
            out[name] = (float(np.nanmin(y)), float(np.nanmax(y)))
    return out


def outside_range(fitting, held) -> list[str]:
    """What the held-out recording ``held`` reaches beyond the fitting recordings' range (commands u_*,
    joint rates w_*: beyond their [min, max] by more than ``RANGE_MARGIN`` of the span), as phrases
    ("u_r up to 4.1 N m, the fitting runs 3.0 N m"); empty when it stays within."""
    fit = [_ranges(d) for d in fitting]
    units = dict(RANGE_CHANNELS)
    out = []
    for name, (lo, hi) in _ranges(held).items():
        got = [f[name] for f in fit if name in f]
        if not got:
            continue
        flo, fhi = min(g[0] for g in got), max(g[1] for g in got)
        m = RANGE_MARGIN * max(fhi - flo, 1e-9)
        if hi > fhi + m:
            out.append(f"{name} up to {hi:.3g} {units[name]}, the fitting runs {fhi:.3g}")
        if lo < flo - m:
            out.append(f"{name} down to {lo:.3g} {units[name]}, the fitting runs {flo:.3g}")
    return out


def saturation_not_identifiable(fitting, effects, found: set[str]) -> list[dict]:
    """Saturation levels above the largest recorded command of the motor(s) never act in the fitting
    recordings: "not identifiable from this recording" above that level, for each saturation effect not
    found (``effects``: the applicable catalog entries)."""
    motors = {"torque_saturation": (0, 1, 2), "saturation_right": (0,), "saturation_left": (1,),
              "saturation_pivot": (2,)}
    out = []
    for e in effects:
        if e.name not in motors or e.name in found:
            continue
        top = max(float(np.max(np.abs(d.u[:, list(motors[e.name])]))) for d in fitting)
        out.append({"kind": "effect", "name": e.name, "title": e.title,
                    "why": f"a level above the largest recorded command ({top:.3g} N m) never acts in this recording",
                    "record": EFFECT_RECORD[e.name]})
    return out
