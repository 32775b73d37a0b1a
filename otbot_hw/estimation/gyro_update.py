"""The pose EKF's gyro update and the adaptation of the unmodelled yaw walk it drives (a mixin of
``otbot_hw.estimation.ekf.PoseEKF``: it works on the filter's state ``kf``, its gates and counters).

The gyro measures alpha_dot + b_g (rad/s) at every new IMU reading. Its normalized innovations drive a
covariance matching of the variance of d's walk (the alpha_dd the model does not know): a model whose
alpha row is wrong (an unknown load) shows as gyro innovations larger than the filter expects.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.stats import chi2

from otbot_hw.estimation.ekf_state import BG, REANCHOR_AFTER, VA

#: Largest factor by which the adaptation may multiply the variance of d's walk (walk x 1000).
WALK_SCALE_MAX = 1e6
#: The yaw states whose covariance the adaptation inflates: alpha_dot, d (alpha too let a joint-rate update
#: throw it by 0.1 rad on a 280 kg load; its error is re-anchored on the wheel heading instead).
_YAW = [5, 11]


class GyroUpdate:
    """The gyro methods of ``PoseEKF`` (see the module docstring)."""

    def _update_gyro(self, t: float) -> None:
        """The gyro: alpha_dot + b_g. Its NIS drives the adaptation of d's walk (``_adapt_walk``). The gyro
        does not slip: rejected for ``REANCHOR_AFTER``, it is the yaw prediction that is lost (a model that
        is wrong), so alpha_dot's variance grows by the innovation squared and alpha_dot re-anchors on the
        gyro -- the gate cannot starve the filter of its yaw rate. A single outlier is still rejected."""
        x = self.kf.x
        nu = np.array([self._gyro[2] - x[VA] - x[BG]])
        ok = self._update("gyro", t, nu, self._H_gyro, self._R_gyro)
        self._adapt_walk(t, self._nis["gyro"])
        if self._rejected_long("_gyro_off_since", t, ok):
            self.kf.P[VA, VA] += nu[0] * nu[0]
            self._update("gyro", t, nu, self._H_gyro, self._R_gyro, force=True)

    def _rejected_long(self, since: str, t: float, ok: bool) -> bool:
        """Whether an update kind rejected at t (``ok`` False) has been for ``REANCHOR_AFTER`` s (then it
        re-anchors); ``since``: the attribute holding since when (None while accepted; reset by True)."""
        if ok:
            setattr(self, since, None)
            return False
        t0 = getattr(self, since)
        if t0 is None:
            t0 = self._t_prev
            setattr(self, since, t0)
        if t - t0 >= REANCHOR_AFTER - 1e-9:
            setattr(self, since, None)
            return True
        return False

    def _adapt_walk(self, t: float, nis: float) -> None:
        """Covariance matching on the gyro (Mehra 1972; Mohamed & Schwarz 1999): the gyro's NIS averaged
        exponentially over ``walk_adaptation_window`` has expectation 1 for a consistent filter; above its
        chi-square bound at ``gate_probability`` (the average of n_eff = (2 - w) / w readings, w the
        averaging weight) the alpha_dot prediction is worse than the filter believes -- the model's alpha
        row is wrong -- and the variance of d's walk is multiplied by that average, at every reading,
        until the innovations fit (at most ``WALK_SCALE_MAX``). The step relaxes it back."""
        cfg = self.config
        if cfg.walk_adaptation_window <= 0:
            return
        dt = t - self._gyro_t if self._gyro_t is not None else self.period
        self._gyro_t = t
        w = round(1.0 - math.exp(-dt / cfg.walk_adaptation_window), 6)
        if not w > 0:
            return
        bound = self._nis_bounds.get(w)
        if bound is None:
            n_eff = (2.0 - w) / w
            bound = self._nis_bounds[w] = float(chi2.ppf(cfg.gate_probability, n_eff) / n_eff)
        self._gyro_nis_avg += w * (nis - self._gyro_nis_avg)
        avg = self._gyro_nis_avg
        self._gyro_disagrees = avg > bound
        if avg > bound:
            self.walk_scale = min(self.walk_scale * avg, WALK_SCALE_MAX)
            # fading memory on the yaw states: the error the wrong model already put into alpha, alpha_dot
            # and d is as much larger than their covariance says (P -> T P T, T = sqrt(avg) on their rows)
            g = math.sqrt(avg)
            P = self.kf.P
            P[_YAW, :] *= g
            P[:, _YAW] *= g
