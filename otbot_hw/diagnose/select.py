"""Choosing effects by evidence: screening (``screening.py``), then nested fits judged by the rules
(``rules.py``).

1. **Screening**: the catalog effects ranked by how much of the equation and simulation residuals
   they explain (``screening.screen``, ``screening.screen_simulation``); the shortlist is the union.
2. **Nested fits**: the shortlisted candidates (``shortlist``) are re-identified jointly with
   the free nominal parameters by simulation output error through ``refit.refit`` (a quick
   look of ``QUICK_NFEV`` iterations, continued only with evidence) and judged by the rules of
   ``rules.py`` (evidence, ambiguity, physical significance, pairs, white residuals).

   Before a name is given, the best candidate's catalog look-alikes get a nested fit too. The
   search goes on after an accepted effect, an ambiguous group or a small detection, up to
   ``MAX_ROUNDS`` rounds (``choose``).

Length: one search (``_Search``) whose rounds, look-alike checks, convergence and pair tries share its
state (the fits so far, the reference, progress); the rules and the screening are modules of their own.
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

import numpy as np

from otbot_hw.diagnose import catalog as cat
from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.refit import FitResult, channel_sigmas, correlation_factor, refit, weighted_residuals
from otbot_hw.diagnose.rules import (ACCEPT_DBIC, AMBIGUOUS_DBIC, MAX_LOOKALIKES, MAX_PAIR_TRIES, MAX_ROUNDS,
                                     NESTED_NFEV, NESTED_TOL, QUICK_NFEV, SCREEN_DBIC, Candidate, ambiguous_group,
                                     fitting_evidence, has_evidence, information_criteria, matters, pair_adds,
                                     shortlist, white)
from otbot_hw.diagnose.screening import Screening, screen, screen_simulation
from otbot_hw.identification.model import map_prediction_rows
from otbot_hw.model.effects import ExtendedModel, parameter_bounds

#: what a nested fit raises when the simulation diverges at a trial point (NaN in the Jacobian's SVD)
FIT_FAILURES = (ValueError, FloatingPointError, np.linalg.LinAlgError)

FLOOR_NOMINAL = ("m_c", "I_c", "x_B", "y_B", "I_p", "b_w", "b_p")
STAND_NOMINAL = ("I_a", "b_w", "I_p", "b_p")
LOCKED_NOMINAL = ("I_p", "b_p")


def free_nominal(recordings: list[DiagnosisData]) -> list[str]:
    """Nominal parameters the data can identify (paper §4.2 steps): bench runs free the wheel
    inertia and frictions, floor runs the chassis; platform mass and centre are taken as known."""
    out: list[str] = []
    for d in recordings:
        names = {"floor": FLOOR_NOMINAL, "stand": STAND_NOMINAL, "locked": LOCKED_NOMINAL}[d.fixture]
        out += [n for n in names if n not in out]
    return out



def holdout_cost(holdout: list[DiagnosisData], model: ExtendedModel) -> float:
    """Sum over held-out channels of N ln(RSS / N) (noise-weighted): lower predicts better."""
    if not holdout:
        return float("nan")
    res = weighted_residuals(holdout, model, channel_sigmas(holdout))
    return float(sum(len(v) * np.log(max(v @ v, 1e-300) / len(v)) for v in res.values()))



@dataclass
class Selection:
    """Accepted effects (in order), ambiguous groups, effects detected but too small to matter, every
    candidate tried and the final fit."""

    accepted: list[Candidate]
    ambiguous: list[list[Candidate]]
    tried: list[Candidate]
    screenings: list[Screening]
    base_fit: FitResult
    final_fit: FitResult
    sim_screenings: list[dict[str, float]] = field(default_factory=list)
    small: list[Candidate] = field(default_factory=list)
    effects: dict[str, cat.Effect] = field(default_factory=dict)  # the catalog entries as applied
    #: {effect: (chi2, k, n, magnitude)}: signature energy of each effect's catalog step on the base model
    energy: dict = field(default_factory=dict)


HELD_DELAY_SPACING = 0.008  # s: the first scan's spacing over a held delay's range (``mid_interval_delays``)


def mid_interval_delays(periods: list[float], lo: float, hi: float, spacing: float = 0.0) -> list[float]:
    """Delays s in (lo, hi) inside a sample interval of every period in ``periods`` (s, ascending):
    (k + 1/2) dt of the finest, those within a quarter of it from a multiple of a coarser one dropped; with
    ``spacing`` s, only every ceil(spacing / dt)-th of them."""
    dt = periods[0]
    k0, k1 = int(np.floor(lo / dt)), int(np.ceil(hi / dt))
    out = [(k + 0.5) * dt for k in range(k0, k1 + 1) if lo < (k + 0.5) * dt < hi]
    out = [v for v in out if all(abs(v / q - round(v / q)) * q >= 0.25 * dt for q in periods[1:])]
    stride = max(1, int(np.ceil(spacing / dt - 1e-9)))
    return out[::stride]


def _effect_guess(e: cat.Effect, screening: Screening, sim_guess: dict | None = None,
                  model: ExtendedModel | None = None) -> dict[str, float]:
    """Start values: the simulation screening's step when it has one, else the equation screening's,
    else half the catalog step, else (a position) the model's value."""
    g = dict(screening.guesses.get(e.name, {}))
    g.update(sim_guess or {})
    out = {}
    for p in e.parameters:
        lo, hi = parameter_bounds(p)
        default = e.magnitudes[0][p] * 0.5 if p in e.magnitudes[0] else (model.get(p) if model is not None else 0.0)
        v = g.get(p, default)
        span = hi - lo
        out[p] = float(np.clip(v, lo + 1e-3 * span, hi - 1e-3 * span))
    return out



def _kappa(recordings: list[DiagnosisData], fit: FitResult) -> float:
    return correlation_factor(weighted_residuals(recordings, fit.model, fit.sigma))



class _Search:
    """State of one selection: the data, the base the next candidates are fitted on, what was found."""

    def __init__(self, recordings, holdout, base_fit, nominal_free, progress, casters_configured, given=None,
                 wandered=False):
        self.recordings, self.holdout, self.progress = recordings, holdout, progress
        self.given = given  # the parameter file's model (``choose``)
        self.wandered = wandered  # the nominal fit moved implausibly far from it
        self.nominal_free = nominal_free
        effects = cat.applicable({d.fixture for d in recordings}, casters_configured)
        self.effects = effects
        self.by_name = {e.name: e for e in effects}
        self.current = base_fit
        self.accepted: list[Candidate] = []
        self.ambiguous: list[list[Candidate]] = []
        self.small: list[Candidate] = []
        self.tried: list[Candidate] = []
        self.screenings: list[Screening] = []
        self.sim_screens: list[dict[str, float]] = []
        self.used: set[str] = set()
        self.energy: dict = {}  # first round's signature energies (``screen_simulation``)

    @functools.cached_property
    def sigmas(self) -> dict:
        """Noise levels of the fitting channels (``refit.channel_sigmas``), once per search (``_better_start``)."""
        return channel_sigmas(self.recordings)

    def reference(self, fit: FitResult) -> tuple[float, float, float]:
        aic, bic = information_criteria(fit.rss, fit.n_samples, fit.n_params)
        return aic, bic, holdout_cost(self.holdout, fit.model)

    def nested(self, name: str, on: FitResult, ref: tuple, guess: dict, screen_gains=(np.nan, np.nan),
               beside: float | None = None) -> Candidate:
        """Fit effect ``name`` beside the model of ``on``; evidence against the reference (AIC, BIC, held-out).
        The fit goes on after the quick look only while it shows BIC evidence -- against the reference, or
        against ``beside`` (the BIC gain of the effect already in ``on``) for a second effect."""
        e = self.by_name[name]
        names = list(on.names) + [p for p in e.parameters if p not in on.names]
        if len(names) == len(on.names):
            # every parameter already free beside it (wheel slip's k_slip in a traction limit): the "fit" would
            # only continue the one it stands on, and its gain be read as a second effect's evidence
            self.progress(f"[diagnose]   {name}: its parameters are already fitted; not a candidate")
            return Candidate(name, on, np.inf, np.inf, np.inf, screen_gains[0], screen_gains[1],
                             parameters=tuple(e.parameters))
        guess = self._better_start(e, on.model, guess)
        self.progress(f"[diagnose] nested fit: + {name} (start {guess})")
        try:
            fit = refit(self.recordings, on.model, names, guess=guess, max_nfev=QUICK_NFEV, tol=NESTED_TOL)
        except FIT_FAILURES as exc:  # the simulation diverged at a trial point: no evidence for this effect
            self.progress(f"[diagnose]   {name}: the fit failed ({type(exc).__name__}: {exc}); not a candidate")
            return Candidate(name, on, np.inf, np.inf, np.inf, screen_gains[0], screen_gains[1],
                             parameters=tuple(e.parameters))
        aic, bic = information_criteria(fit.rss, fit.n_samples, fit.n_params)
        bar = ref[1] + (beside if beside is not None else 0.0)
        if fit.nfev >= QUICK_NFEV and bic - bar < -ACCEPT_DBIC:  # promising and not converged yet: go on
            try:
                fit = refit(self.recordings, fit.model, names, max_nfev=NESTED_NFEV - QUICK_NFEV, tol=NESTED_TOL,
                            scale=fit.scale)
            except FIT_FAILURES as exc:  # keep the quick look
                self.progress(f"[diagnose]   {name}: the continued fit failed ({type(exc).__name__}); quick look kept")
            aic, bic = information_criteria(fit.rss, fit.n_samples, fit.n_params)
        c = Candidate(name, fit, bic - ref[1], aic - ref[0], holdout_cost(self.holdout, fit.model) - ref[2],
                      screen_gains[0], screen_gains[1], parameters=tuple(e.parameters))
        if c.dbic < -ACCEPT_DBIC:
            c.kappa = _kappa(self.recordings, fit)
        self.progress(f"[diagnose]   {name}: dBIC {c.dbic:.1f} (kappa {c.kappa:.1f}), held-out d(cost) {c.dholdout:.1f}")
        self.tried.append(c)
        return c

    def round(self, on: FitResult, ref: tuple, round_index: int, exclude: set[str]) -> list[Candidate]:
        """Screen from the model of ``on`` and fit the shortlist beside it."""
        sc = screen(self.recordings, on.model, self.nominal_free, self.effects, exclude=exclude)
        self.screenings.append(sc)
        ss = screen_simulation(self.recordings, on.model, self.nominal_free, self.effects, exclude=exclude,
                               energy=self.energy if round_index == 0 else None)
        self.sim_screens.append({e: d for e, (d, _) in ss.items()})
        names = shortlist(sc.single, {e: d for e, (d, _) in ss.items()}, round_index)
        starts = {}
        if round_index == 0 and self.given is not None:
            # the nominal fit may have absorbed an effect into the nominal values (a traction limit under
            # constant torques: I_p on its bound; air drag into b_w), and the screening about that fit, a local
            # score test, misses it: screened about the file's values too, the effect that explains most from
            # there is fitted from there as well when it beats everything the first screening saw
            sf_all = screen_simulation(self.recordings, self.given, self.nominal_free, self.effects, exclude=exclude)
            if self.wandered:  # the nominal fit is implausible: the shortlist's nested fits start from the file too
                for n in names:
                    if n in sf_all:
                        ss[n] = sf_all[n]
                        starts[n] = dataclasses.replace(on, model=self.given)
            sf = {e: v for e, v in sf_all.items() if e not in names}
            top = min(sf, key=lambda e: sf[e][0], default=None)
            best_here = min([d for d, _ in ss.values()] + [0.0])
            if top is not None and sf[top][0] < min(best_here, -SCREEN_DBIC):
                self.progress(f"[diagnose] screening about the file's values: {top} (dBIC {sf[top][0]:.0f}, "
                              f"about the nominal fit {ss.get(top, (np.nan,))[0]:.0f})")
                names.append(top)
                ss[top] = sf[top]
                starts[top] = dataclasses.replace(on, model=self.given)
        if not names:
            self.progress("[diagnose] screening: no further effect explains the equation or simulation residuals")
            return []
        self.progress(f"[diagnose] screening shortlist: {', '.join(names)}")
        return [self.nested(n, starts.get(n, on), ref,
                            _effect_guess(self.by_name[n], sc, ss.get(n, (0.0, {}))[1], starts.get(n, on).model),
                            (sc.single.get(n, np.nan), ss.get(n, (np.nan, {}))[0])) for n in names]

    def lookalikes(self, best: Candidate, cands: list[Candidate], on: FitResult, ref: tuple,
                   exclude: set[str]) -> list[Candidate]:
        """Fit the best candidate's catalog look-alikes (up to ``MAX_LOOKALIKES``) that the screening did not
        shortlist, beside the same model: before a name is given, the effects it is known to be mistaken
        for get the same chance (e.g. a gain error of the other motor, an encoder scale for a radius)."""
        done = {c.effect for c in cands} | exclude
        out = []
        for name in [n for n in self.by_name[best.effect].lookalikes if n in self.by_name and n not in done][
                :MAX_LOOKALIKES]:
            e = self.by_name[name]
            out.append(self.nested(name, on, ref, {p: e.magnitudes[0].get(p, on.model.get(p)) * 0.5
                                                   for p in e.parameters}))
        return out

    def polish(self, good: list[Candidate], cands: list[Candidate], ref: tuple) -> tuple:
        """Guard against an under-converged base fit: refit the base from the best candidate's nominal
        values; the gains must survive against this polished base (returns the new reference)."""
        best0 = min(good, key=lambda c: c.dbic)
        names = self.current.names
        start = self.current.model.with_values({n: best0.fit.values[n] for n in names})
        polished = refit(self.recordings, start, names, max_nfev=NESTED_NFEV, tol=NESTED_TOL)
        new = self.reference(polished)
        if new[1] < ref[1] - 0.1:
            self.progress(f"[diagnose] base refit from the candidate's nominal values gains {ref[1] - new[1]:.1f} BIC")
            for c in cands:
                c.dbic += ref[1] - new[1]
                c.daic += ref[0] - new[0]
                if np.isfinite(ref[2]) and np.isfinite(new[2]):
                    c.dholdout += ref[2] - new[2]
            self.current = polished
            return new
        return ref

    def judge(self, c: Candidate) -> None:
        from otbot_hw.diagnose.significance import significance

        vals = {p: c.fit.values[p] for p in c.parameters}
        # what the effect does over every run at hand, held-out ones included (their speeds and torques)
        c.significance = significance(c.effect, vals, {p: c.fit.std.get(p, float("nan")) for p in c.parameters},
                                      c.fit.model, self.recordings + self.holdout)

    def take(self, best: Candidate, others: list[Candidate], group: list[Candidate] | None = None) -> None:
        """Add ``best`` (with the candidates the data cannot tell from it: ``group``, default
        ``ambiguous_group(best, others)``) to the findings."""
        group = group or ambiguous_group(best, others)
        best = group[0]  # the simplest of nested explanations leads
        for c in group:
            self.judge(c)
        self.used.update(c.effect for c in group)
        if not matters(best):
            self.progress(f"[diagnose] {best.effect}: detected, small ({best.significance['statement']})")
            self.small.append(best)
            return
        if len(group) > 1:
            self.ambiguous.append(group)
            self.progress(f"[diagnose] ambiguous: {', '.join(c.effect for c in group)}; the search goes on with "
                          f"{best.effect}")
        else:
            self.accepted.append(best)
        self.current = best.fit

    def _better_start(self, e: cat.Effect, model: ExtendedModel, guess: dict) -> dict:
        """The screening's guess or the catalog's smallest step, whichever the simulation fits better (two
        simulations): a linear step's coefficient is a poor guess of a nonlinear parameter (a traction limit's
        creep slope read 0.26 rad/(s N m) for a true 0.02; the fit from there stopped on its budget at kappa 46)."""
        step = {p: e.magnitudes[0][p] for p in e.parameters if p in e.magnitudes[0]}
        alt = {**guess, **step}

        def cost(g):
            try:
                res = weighted_residuals(self.recordings, model.with_values(g), self.sigmas)
            except (ValueError, ZeroDivisionError, FloatingPointError):
                return np.inf
            return float(sum(v @ v for v in res.values()))

        if e.held_delays:
            return self._held_delay_start(e, guess, cost)
        if not step or all(np.isclose(alt[p], guess.get(p, np.nan)) for p in step):
            return guess
        return alt if cost(alt) < cost(guess) else guess

    def _held_delay_start(self, e: cat.Effect, guess: dict, cost) -> dict:
        """A held delay's start: the best of a scan over mid-interval delays (``mid_interval_delays``), coarse
        then fine around the best. Its readings jump where the delay crosses a whole sample period, so a fit
        started on a multiple of the period (a PRBS's IMU latency from the catalog's 20 ms at 100 Hz) has no
        slope to follow and one started inside an interval stops at the jump into the next."""
        periods = sorted({round(float(d.dt), 12) for d in self.recordings})
        out = dict(guess)
        for p in e.held_delays:
            lo, hi = parameter_bounds(p)
            coarse = mid_interval_delays(periods, lo, hi, HELD_DELAY_SPACING)
            costs = map_prediction_rows(lambda i: cost({**out, p: coarse[i]}), len(coarse))
            best = coarse[int(np.argmin(costs))]
            width = max(HELD_DELAY_SPACING, periods[0])
            fine = [v for v in mid_interval_delays(periods, max(lo, best - width), min(hi, best + width))
                    if not np.any(np.isclose(v, coarse))]
            fine_costs = map_prediction_rows(lambda i: cost({**out, p: fine[i]}), len(fine))
            cands, allc = list(coarse) + fine, list(costs) + list(fine_costs)
            out[p] = float(cands[int(np.argmin(allc))])
            self.progress(f"[diagnose]   {p}: start {1e3 * out[p]:.1f} ms of {len(cands)} mid-interval delays")
        return out

    def converge(self, c: Candidate, ref: tuple, nominal_from: Candidate | None = None) -> Candidate:
        """``c`` with its nested fit continued (``NESTED_NFEV`` more iterations) when it stopped on the
        budget rather than converged: before a second effect is fitted beside it, its own residual
        structure must be its own, not iterations it did not take (a traction limit stopped at kappa 46
        "gained" 22000 BIC from an encoder scale error that then fitted to zero). Evidence recomputed.
        ``nominal_from``: continued from that candidate's nominal values instead (a look-alike against the best:
        both from the same place), even when it had converged."""
        if c.fit.success and nominal_from is None:
            return c
        start = c.fit.model
        if nominal_from is not None:
            start = start.with_values({n: nominal_from.fit.values[n] for n in self.current.names
                                       if n in nominal_from.fit.values})
        try:  # from the best's nominal values a quick look's budget: the look-alike is then a step away
            fit = refit(self.recordings, start, c.fit.names, max_nfev=QUICK_NFEV if nominal_from else NESTED_NFEV,
                        tol=NESTED_TOL, scale=None if nominal_from else c.fit.scale)
        except FIT_FAILURES:
            return c
        aic, bic = information_criteria(fit.rss, fit.n_samples, fit.n_params)
        if bic >= ref[1] + c.dbic:
            return c
        out = dataclasses.replace(c, fit=fit, dbic=bic - ref[1], daic=aic - ref[0],
                                  dholdout=holdout_cost(self.holdout, fit.model) - ref[2])
        out.kappa = _kappa(self.recordings, fit)
        self.progress(f"[diagnose]   {c.effect} converged: dBIC {out.dbic:.1f} (kappa {out.kappa:.1f}), "
                      f"held-out d(cost) {out.dholdout:.1f}")
        self.tried = [out if t is c else t for t in self.tried]
        return out

    def second_beside(self, first: Candidate, cands: list[Candidate], ref: tuple) -> Candidate | None:
        """Fit a second candidate with fitting evidence beside ``first`` (two effects at once) and return the
        pair's candidate when it adds evidence (``pair_adds``). Tried in order: candidates that are not
        catalog look-alikes of ``first`` (other physics, likely the rest of the residual), then its
        look-alikes, each by BIC gain; at most ``MAX_PAIR_TRIES``. Before this, nothing is grouped as
        ambiguous: two effects that each leave correlated residuals may both be there."""
        look = set(self.by_name[first.effect].lookalikes)
        others = sorted((c for c in cands if c is not first and fitting_evidence(c)
                         and not set(c.parameters) & set(first.parameters)),
                        key=lambda c: (c.effect in look, c.dbic))
        for second in others[:MAX_PAIR_TRIES]:
            guess = {p: second.fit.values[p] for p in second.parameters}
            pair = self.nested(second.effect, first.fit, ref, guess, (second.screen_dbic, second.sim_screen_dbic),
                               beside=first.dbic)
            if pair.dbic < -ACCEPT_DBIC and pair.kappa == 1.0:
                pair.kappa = _kappa(self.recordings, pair.fit)
            if pair_adds(pair, first):
                return pair
        return None



def choose(recordings: list[DiagnosisData], holdout: list[DiagnosisData], base_fit: FitResult,
           nominal_free: list[str], progress=lambda msg: None, casters_configured: bool = True,
           given: ExtendedModel | None = None, wandered: bool = False) -> Selection:
    """Greedy forward selection of effects: screen, nested fits, accept by evidence, judge by physics.

    Each round adds the best candidate with evidence (``has_evidence``): alone, or as an ambiguous
    group (carried on with its best member, its members excluded from later rounds), or -- when it
    does not matter physically -- listed as detected but small and left out of the model. Two effects
    at once: when a second candidate also has evidence, it is fitted beside the best and kept when the
    pair adds evidence (``pair_adds``); when the best has evidence on the fitting data but predicts the
    held-out runs worse (a second effect it cannot stand in for), it is carried provisionally for one
    round and kept only if an effect beside it passes both tests. The search goes on after each of
    these, up to ``MAX_ROUNDS`` rounds. ``given``: the parameter file's model: the first round also screens
    about it (the nominal fit may have absorbed an effect, and a score test about that fit is local) and fits
    an effect from there when that screening finds it stronger; ``wandered``: the nominal fit moved
    implausibly far from the file (it absorbed an effect), and the first round's nested fits all start from
    the file's values."""
    S = _Search(recordings, holdout, base_fit, nominal_free, progress, casters_configured, given, wandered)
    provisional: Candidate | None = None
    ref = S.reference(S.current)
    for round_index in range(MAX_ROUNDS):
        on = provisional.fit if provisional else S.current
        exclude = S.used | ({provisional.effect} if provisional else set())  # unchanged until the round's decision
        cands = S.round(on, ref, round_index, exclude)
        good = [c for c in cands if has_evidence(c)]
        if good:
            ref = S.polish(good, cands, ref)
            good = [c for c in cands if has_evidence(c)]
        if good:
            # the look-alikes of the best and of those tied with it (each would be named in its group): gain_right
            # tied with saturation_right to 1e-5 BIC, and only the latter's look-alikes were fitted -- a left-wheel
            # gain under constant torques went unfitted, named as right and pivot gains beside a rescaled chassis
            for lead in ambiguous_group(min(good, key=lambda c: c.dbic), good):
                cands += S.lookalikes(lead, cands, on, ref, exclude)
            good = [c for c in cands if has_evidence(c)]
        fit_only = [c for c in cands if fitting_evidence(c)]
        if not good and fit_only:
            # the best explains the fitting data but predicts the held-out runs worse: its look-alikes may explain
            # both (a wheel friction asymmetry stands in for a wheel gain at one constant torque; the held-out
            # run's other torques tell them apart -- the gain was never fitted)
            cands += S.lookalikes(min(fit_only, key=lambda c: c.dbic), cands, on, ref, exclude)
            good = [c for c in cands if has_evidence(c)]
        fit_only = [c for c in cands if fitting_evidence(c)]
        if not good and fit_only:
            # a fit stopped on its budget may predict the held-out runs worse only because it stopped: the best
            # is converged before it is judged (a wheel slip "beside" a closed-loop traction limit, the same k_slip,
            # was its continuation and passed; converged outright, that traction limit still predicts worse)
            lead = min(fit_only, key=lambda c: c.dbic)
            conv = S.converge(lead, ref)
            cands = [conv if c is lead else c for c in cands]
            good = [c for c in cands if has_evidence(c)]
        if not good:
            # the first round's best explains the fitting data but predicts the held-out runs worse: a
            # second effect it cannot stand in for may be at work
            fit_only = [c for c in cands if fitting_evidence(c)]
            if provisional is None and fit_only and round_index == 0:
                provisional = min(fit_only, key=lambda c: c.dbic)
                progress(f"[diagnose] {provisional.effect} explains the fitting data but not the held-out runs: "
                         "carried provisionally, to try a second effect beside it")
                continue
            break
        good.sort(key=lambda c: c.dbic)
        # the best's look-alikes are refit from the best's nominal values before the data are said to tell them
        # apart (rolling resistance, fitted from the nominal fit, "lost" by 280 BIC to wheel Coulomb friction,
        # fitted from the file's values: the same model under constant torques, c_rr exact from there)
        look = set(S.by_name[good[0].effect].lookalikes)
        conv = {id(c): S.converge(c, ref, good[0]) for c in good[1:]
                if c.effect in look or good[0].effect in S.by_name[c.effect].lookalikes}
        cands = [conv.get(id(c), c) for c in cands]
        good = sorted((conv.get(id(c), c) for c in good), key=lambda c: c.dbic)
        # the best candidate that matters physically leads; better-evidenced ones that do not matter are listed
        # as detected but small; when none matters, nothing on this model does: the search ends
        for c in good:
            S.judge(c)
        lead = next((c for c in good if matters(c)), None)
        for c in good[:good.index(lead) if lead is not None else len(good)]:
            progress(f"[diagnose] {c.effect}: detected, small ({c.significance['statement']})")
            S.small.append(c)
            S.used.add(c.effect)
        if lead is None:
            break
        good = good[good.index(lead):]
        best = lead
        if provisional is not None:
            # the pair passed where the provisional effect alone did not: both are findings
            first = dataclasses.replace(provisional, fit=best.fit, dbic=provisional.dbic,
                                        dholdout=min(provisional.dholdout, best.dholdout))
            S.take(first, [])
            S.used.add(first.effect)
            provisional = None
            S.take(best, good[1:])
            ref = S.reference(S.current)
            continue
        # a second effect beside the best only when the best, converged, leaves structure (correlated residuals)
        if round_index + 1 < MAX_ROUNDS and not white(best):
            conv = S.converge(best, ref)
            if conv is not best:
                cands = [conv if c is best else c for c in cands]
                good = [conv if c is best else c for c in good]
                S.judge(conv)
                best = conv
        pair = S.second_beside(best, cands, ref) if round_index + 1 < MAX_ROUNDS and not white(best) else None
        if pair is not None:
            single = next(c for c in cands if c.effect == pair.effect)
            # the second effect's look-alikes (as hard to tell from it alone) get their own fit beside the first
            alike = [c for c in good if c is not best and c is not single
                     and abs(c.dbic - single.dbic) / max(single.kappa, 1.0) < AMBIGUOUS_DBIC
                     and not set(c.parameters) & set(best.parameters)]
            beside = [S.nested(c.effect, best.fit, ref, {p: c.fit.values[p] for p in c.parameters},
                               (c.screen_dbic, c.sim_screen_dbic), beside=best.dbic) for c in alike]
            for c in [pair] + beside:
                c.dbic -= best.dbic  # each second effect's own evidence, beside the first
            progress(f"[diagnose] {pair.effect} beside {best.effect}: the pair adds {-pair.dbic:.0f} BIC")
            # the first's look-alikes are judged with the correlation the pair leaves (the second effect's
            # residual inflated every single fit's alike)
            S.take(dataclasses.replace(best, fit=pair.fit, kappa=pair.kappa),
                   [c for c in good[1:] if c.effect != pair.effect])
            S.take(pair, beside)
        else:
            S.take(best, good[1:])
        last = pair or best
        if white(last) and S.current is last.fit:
            progress(f"[diagnose] residuals white after {last.effect} (kappa {last.kappa:.2f}): search done")
            break
        ref = S.reference(S.current)
    return Selection(S.accepted, S.ambiguous, S.tried, S.screenings, base_fit, S.current, S.sim_screens, S.small,
                     S.by_name, S.energy)
