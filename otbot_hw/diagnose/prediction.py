"""The extended model as the shared identification fitter sees it.

``otbot_hw.identification.prediction_error.fit_parameters`` fits any *prediction
model* (``otbot_hw.identification.model``): ``names``, ``channels`` and
``predict(thetas (m, P), experiment) -> (m, n_samples, n_channels)``. This module
gives the extended model (``otbot_hw.model.effects.ExtendedModel``) that interface and
turns diagnosis recordings into the fitter's ``Experiment`` objects, so every fit of the
diagnosis runs through the same fitter as the identification.

* Parameter vector: the paper's ``PARAM_NAMES`` (SI), then the effect vector
  ``EFFECT_PARAM_NAMES``, then the requested tied catalog parameters (e.g. ``c_w``,
  which sets ``c_r`` and ``c_l`` together). A vector is resolved by
  ``ExtendedModel.with_values`` in that order, so a tied parameter overrides its members
  (free either the tied name or its members, never both).
* Channels: the diagnosis channels (encoder rates ``w_r, w_l, w_p`` rad/s, IMU ``a_x,
  a_y`` m/s^2, gyro z rad/s); the gyro is called ``omega_z`` as in the identification
  (``g_z`` in the diagnosis).
* Prediction: ``simulated_run.simulate_outputs`` -- the whole run simulated from the initial
  state estimated from the encoders *with the candidate parameters* (encoder scale,
  radius asymmetry and slip change it), with the experiment's RK4 ``substeps``.
  A simulation that fails or diverges predicts ``FAILED_OUTPUT`` (a large finite value,
  so the fitter's finite differences stay finite and steer away from it).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from otbot_hw.diagnose.data import CHANNELS as DIAGNOSIS_CHANNELS
from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.simulated_run import diagnosis_substeps, initial_state, simulate_outputs
from otbot_hw.identification.experiment import Experiment
from otbot_hw.identification.model import map_prediction_rows
from otbot_hw.model.effects import EFFECT_PARAM_NAMES, TIED_PARAMS, ExtendedModel
from otbot_hw.params import PARAM_NAMES

#: diagnosis channel -> identification channel name
FITTER_CHANNEL: dict[str, str] = {ch: ("omega_z" if ch == "g_z" else ch) for ch in DIAGNOSIS_CHANNELS}
DIAGNOSIS_CHANNEL: dict[str, str] = {v: k for k, v in FITTER_CHANNEL.items()}
FAILED_OUTPUT = 1e6
JACOBIAN_STEP = 1e-3  # relative: a batch of rows this close to its median is a finite-difference Jacobian


@dataclass
class DiagnosisExperiment(Experiment):
    """An identification ``Experiment`` that also carries its diagnosis recording (encoders for x0)."""

    data: DiagnosisData | None = None


class ExtendedPredictionModel:
    """Prediction model (identification interface) of ``ExtendedModel`` around ``base``.

    ``tied``: tied catalog parameters (``TIED_PARAMS``) to append to the vector.
    """

    channels: tuple[str, ...] = tuple(FITTER_CHANNEL[c] for c in DIAGNOSIS_CHANNELS)

    def __init__(self, base: ExtendedModel, tied: Sequence[str] = ()):
        unknown = [n for n in tied if n not in TIED_PARAMS]
        if unknown:
            raise ValueError(f"not tied parameters: {', '.join(unknown)} (tied: {', '.join(TIED_PARAMS)})")
        self.base = base
        self.names: tuple[str, ...] = tuple(PARAM_NAMES) + tuple(EFFECT_PARAM_NAMES) + tuple(tied)

    def vector(self, model: ExtendedModel | None = None) -> np.ndarray:
        """Full parameter vector (``names`` order) of ``model`` (default: the base model)."""
        m = self.base if model is None else model
        return np.array([m.get(n) for n in self.names], dtype=float)

    def resolve(self, theta: np.ndarray) -> ExtendedModel:
        """The extended model of a full parameter vector (raises ValueError for invalid values)."""
        return self.base.with_values(dict(zip(self.names, map(float, theta))))

    def _one(self, theta: np.ndarray, data: DiagnosisData, substeps: int,
             centre: ExtendedModel | None = None) -> np.ndarray:
        try:
            m = self.resolve(theta)
            x0 = None if centre is None else initial_state(data, m, rates_from=centre)
            # the step of this parameter row (a friction level sets it: ``diagnosis_substeps``), never coarser
            # than the experiment's
            sub = max(substeps, diagnosis_substeps(data.dt, data.fixture, m.eff, m.params))
            sim = simulate_outputs(data, m, x0, substeps=sub)
            y = np.column_stack([sim[c] for c in DIAGNOSIS_CHANNELS])
        except (ValueError, ZeroDivisionError, FloatingPointError, np.linalg.LinAlgError):
            return np.full((len(data), len(DIAGNOSIS_CHANNELS)), FAILED_OUTPUT)
        # a diverged simulation: non-finite, or beyond any physical output (its squares overflow the fitter's cost)
        return np.where(np.isfinite(y) & (np.abs(y) < FAILED_OUTPUT), y, FAILED_OUTPUT)

    def predict(self, thetas: np.ndarray, experiment: DiagnosisExperiment) -> np.ndarray:
        """Predicted outputs (m, n_samples, 6) in ``channels`` order for parameter rows ``thetas`` (m, P)."""
        P = np.atleast_2d(np.asarray(thetas, dtype=float))
        if P.shape[1] != len(self.names):
            raise ValueError(f"parameter rows must have {len(self.names)} entries ({', '.join(self.names)})")
        data = experiment.data
        if data is None:
            raise ValueError(f"{experiment.name}: not a diagnosis experiment (no recording attached)")
        centre = self._centre(P)
        rows = map_prediction_rows(lambda i: self._one(P[i], data, experiment.substeps, centre), len(P))
        return np.stack(rows)

    def _centre(self, P: np.ndarray) -> ExtendedModel | None:
        """The model at the centre of a finite-difference batch (rows that each differ from the entry-wise median
        in at most one entry, by at most ``JACOBIAN_STEP`` relative): its fitted initial rates serve every row
        (``simulated_run.initial_state``'s ``rates_from``). None for any other batch, or fewer than 3 rows."""
        if len(P) < 3:
            return None
        c = np.median(P, axis=0)
        d = np.abs(P - c[None, :]) > JACOBIAN_STEP * np.maximum(np.abs(c), 1.0)[None, :]
        off = P != c[None, :]
        if d.any() or np.any(off.sum(axis=1) > 1):
            return None
        try:
            return self.resolve(c)
        except ValueError:
            return None


def diagnosis_experiments(recordings: Sequence[DiagnosisData], model: ExtendedModel,
                          sigmas: dict[tuple[str, str], float]) -> list[DiagnosisExperiment]:
    """One fitter experiment per recording: its usable channels, weighted by ``sigmas[(name, channel)]``
    (units of the channel), x0 from the encoders under ``model``; the RK4 step is each parameter row's own
    (``simulated_run.diagnosis_substeps``, in ``ExtendedPredictionModel``: a friction level sets it), so the
    experiments' ``substeps`` is 1 (a larger one set later, as the fitter's integration check does, is a floor)."""
    out = []
    for d in recordings:
        chans = d.channels()
        out.append(DiagnosisExperiment(
            name=d.name, t=d.t, torque=d.u, fixture=d.fixture, data=d,
            measured={FITTER_CHANNEL[c]: np.asarray(d.measured(c), dtype=float) for c in chans},
            sigma={FITTER_CHANNEL[c]: float(sigmas[(d.name, c)]) for c in chans},
            sigma_source={FITTER_CHANNEL[c]: "given" for c in chans},
            x0=initial_state(d, model), substeps=1))
    return out
