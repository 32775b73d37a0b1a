"""The selection rules of ``select`` and their thresholds: pure functions of nested-fit candidates,
pinned by ``tests/test_diagnose_rules.py`` (and mutated by ``benchmarks/diagnose_rule_mutations.py``).

* ``shortlist``: which screened effects get a nested fit;
* ``has_evidence``: BIC beats the base by ``ACCEPT_DBIC`` *effective* samples (divided by the residual
  correlation factor kappa = N / N_eff, ``refit.correlation_factor``) and the held-out recordings are
  not predicted worse;
* ``ambiguous_group``: candidates within ``AMBIGUOUS_DBIC`` effective samples of the best (a candidate
  that only adds parameters to another is not a look-alike);
* ``matters``: the effect's physical significance (``significance.py``) -- torque, drift, odometry,
  delay -- not a channel's fit %;
* ``pair_adds``: a second effect fitted beside the best adds evidence of its own;
* ``white``: residuals white (kappa <= ``KAPPA_WHITE``): nothing left to search for.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import zip_longest

import numpy as np

from otbot_hw.diagnose.refit import FitResult

SCREEN_DBIC = 10.0
ACCEPT_DBIC = 10.0
AMBIGUOUS_DBIC = 10.0
MAX_CANDIDATES = 3
SHORTLIST_FRACTION = 0.1
LATER_ROUND_FACTOR = 5.0
MAX_NESTED = 4  # nested fits per round, taken alternately from the two screenings' shortlists
MAX_LOOKALIKES = 2  # catalog look-alikes of the best candidate fitted beside it before it is named
MAX_PAIR_TRIES = 2  # second candidates fitted beside a best that leaves correlated residuals
MAX_ROUNDS = 3  # rounds of screening + nested fits (each adds one effect, group or small detection)
NOMINAL_NFEV = 60  # evaluations of the nominal fit: beyond them it crawls along a model that misses an effect (a
# traction limit under constant torques: 240, half of the diagnosis's CPU); continued when nothing is found
FINAL_NFEV = 20  # iterations of the final fit (and of a refinement's fit), started from the last nested fit
NESTED_NFEV = 10  # iterations (function evaluations) of a nested fit
QUICK_NFEV = 4  # ... after which a candidate without BIC evidence is given up
KAPPA_WHITE = 1.2  # residual correlation factor of white residuals: nothing left for a further effect
NESTED_TOL = 1e-5  # relative cost/step tolerance of a nested fit (1e-5 of a cost ~ N: < 0.1 BIC)


def information_criteria(fit_rss: dict, n_samples: dict, k: int) -> tuple[float, float]:
    """(AIC, BIC) from per-channel concentrated Gaussian likelihoods; k free parameters."""
    n_tot = sum(n_samples.values())
    ll = sum(n * np.log(max(fit_rss[key], 1e-300) / n) for key, n in n_samples.items())
    return float(ll + 2 * k), float(ll + k * np.log(n_tot))


@dataclass
class Candidate:
    """A nested fit of one effect: the fit, its BIC gain over the base model, its held-out gain, the
    correlation factor of its residuals (``refit.correlation_factor``) and its physical significance."""

    effect: str
    fit: FitResult
    dbic: float
    daic: float
    dholdout: float
    screen_dbic: float
    sim_screen_dbic: float = float("nan")
    kappa: float = 1.0
    significance: dict = field(default_factory=dict)
    parameters: tuple[str, ...] = ()

    @property
    def evidence(self) -> float:
        """BIC gain in effective samples: Delta BIC / kappa (negative = evidence for the effect)."""
        return self.dbic / max(self.kappa, 1.0)


def shortlist(equation_gains: dict[str, float], simulation_gains: dict[str, float], round_index: int) -> list[str]:
    """Effects worth a nested fit: from each screening (equation residuals, simulation score test) the
    ``MAX_CANDIDATES`` best whose BIC gain beats the bar (``SCREEN_DBIC``, ``LATER_ROUND_FACTOR`` times
    that after the first round: residuals are then smaller and relatively more correlated) and reaches
    ``SHORTLIST_FRACTION`` of that screening's best gain; merged alternately, at most ``MAX_NESTED``."""
    bar = SCREEN_DBIC * (1 if round_index == 0 else LATER_ROUND_FACTOR)
    lists = []
    for gains in (equation_gains, simulation_gains):
        ranked = sorted((d, e) for e, d in gains.items() if d < -bar)
        lists.append([e for d, e in ranked[:MAX_CANDIDATES] if d <= SHORTLIST_FRACTION * ranked[0][0]])
    out: list[str] = []
    for pair in zip_longest(*lists):  # alternately, so both screenings are heard within MAX_NESTED
        for e in pair:
            if e is not None and e not in out:
                out.append(e)
    return out[:MAX_NESTED]


def has_evidence(c: Candidate) -> bool:
    """Accepted by evidence: the BIC gain in effective samples beats ``ACCEPT_DBIC`` and held-out
    recordings (if any) are not predicted worse."""
    return c.evidence < -ACCEPT_DBIC and not (c.dholdout > 0)


def ambiguous_group(best: Candidate, others: list[Candidate]) -> list[Candidate]:
    """The best candidate and those the data cannot tell from it: BIC within ``AMBIGUOUS_DBIC``
    effective samples (the best fit's correlation factor deflates the difference). A candidate that
    only adds parameters to another one in the group (wheel slip with a traction limit vs wheel slip)
    is not a look-alike but the same explanation with an unneeded parameter: the simpler one stands
    for both."""
    near = [best] + [c for c in others if c is not best
                     and (c.dbic - best.dbic) / max(best.kappa, 1.0) < AMBIGUOUS_DBIC]
    keep = [c for c in near if not any(set(o.parameters) < set(c.parameters) for o in near)]
    lead = best if best in keep else min(keep, key=lambda c: c.dbic)
    return [lead] + [c for c in keep if c is not lead]


def matters(c: Candidate) -> bool:
    """Whether an effect with evidence matters physically (``significance.significance``)."""
    return bool(c.significance.get("matters"))


def fitting_evidence(c: Candidate) -> bool:
    """BIC evidence on the fitting recordings alone (``has_evidence`` without the held-out test)."""
    return c.evidence < -ACCEPT_DBIC


def pair_adds(pair: Candidate, first: Candidate) -> bool:
    """A second effect fitted beside ``first`` adds evidence: the pair's BIC beats the first alone by
    ``ACCEPT_DBIC`` effective samples, and it predicts the held-out runs no worse than the first alone."""
    return (pair.dbic - first.dbic) / max(pair.kappa, 1.0) < -ACCEPT_DBIC and not (pair.dholdout > first.dholdout)


def white(c: Candidate) -> bool:
    """The candidate's residuals are white (``KAPPA_WHITE``): the model explains the data to the noise."""
    return c.kappa <= KAPPA_WHITE

