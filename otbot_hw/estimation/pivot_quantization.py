"""The pivot encoder's quantization error e_p as a state of the pose EKF (state ``EP``).

e_p = reading - true pivot angle is no white noise: it stays while the pivot reading stays (on
every straight of the corridor), and a white model would let repeated readings of one quantized
angle shrink alpha's variance far below its error. So it is a state: it moves by minus the pivot's
motion while the reading stays (``kernels.pivot_error_step``, a trapezoid around the prediction),
jumps with the reading (``motion``), and is kept inside the count (``count``). A reading that jumps by
more than one count in a sample (the pivot turning fast: the new fraction of a count is independent
of the old) re-draws e_p from the uniform's moments (``redraw``).
"""
from __future__ import annotations

import math

import numpy as np

from otbot_hw.estimation import kernels
from otbot_hw.estimation.ekf_state import A, EP, KAPPA, N_STATE, X, Y


class PivotQuantization:
    """e_p of a pivot encoder with ``pivot_angle_sigma`` (rad, one count / sqrt(12)) at arm ``l1`` (m)."""

    def __init__(self, pivot_angle_sigma: float, l1: float):
        self.l1 = l1
        self.var = pivot_angle_sigma ** 2  # the quantization variance (rad^2)
        self.half_width = math.sqrt(3.0) * pivot_angle_sigma  # half a count: the reading's error bound
        self.count = 2 * self.half_width
        #: what an improbable pivot count constraint may still correct: the angles and the position
        self.corrects = np.zeros(N_STATE, dtype=np.bool_)
        self.corrects[[X, Y, A, KAPPA, EP]] = True

    def half_step(self, x: np.ndarray, P: np.ndarray, phi_p: float, dt: float) -> None:
        """Half of the trapezoid: e_p moves by minus the pivot's motion over dt/2 (reading ``phi_p`` rad)."""
        kernels.pivot_error_step(x, P, phi_p, self.l1, 0.5 * dt)

    def motion(self, x: np.ndarray, P: np.ndarray, phi_p_old: float, phi_p: float, dt: float) -> float:
        """The second half of the trapezoid (the rates after the prediction), then the jump of the
        reading from ``phi_p_old`` to ``phi_p`` (rad): returned, 0 when e_p was re-drawn."""
        self.half_step(x, P, phi_p_old, dt)
        jump = phi_p - phi_p_old
        x[EP] += jump
        if abs(jump) > 1.5 * self.count:
            self.redraw(x, P)
            return 0.0
        return jump

    def constrain(self, x: np.ndarray, P: np.ndarray, jump: float, gate_probability: float) -> bool:
        """The count constraint |e_p| <= h = sqrt(3) pivot_angle_sigma (half a count), applied after the
        sample's measurements, when it is new information: the reading changed (an edge crossed slowly pins
        e_p near that edge) or the mean left the count. Then the Gaussian is truncated to [-h, h] and its
        moments matched (``kernels.truncate``; the other states follow by their regression on e_p). While
        the reading stays with the mean inside, the constraint is the one already used: applying it again
        at every sample -- by truncation, or by capping e_p's variance at the uniform's -- counts it again
        and shrinks every state correlated with e_p (kappa, alpha) without information (measured: pose
        NEES 10-14 on some seeds where it is 3-7 without). A mean that left the count so far that the
        interval holds no probability (model error) re-draws e_p. Returns whether it changed x and P."""
        h = self.half_width
        if jump == 0.0 and abs(x[EP]) <= h:
            return False
        if not kernels.truncate(x, P, EP, -h, h, self.corrects, 1.0 - gate_probability):
            self.redraw(x, P)
        return True

    def redraw(self, x: np.ndarray, P: np.ndarray) -> None:
        """e_p drawn afresh: zero mean, the uniform's variance, uncorrelated."""
        P[EP, :] = 0.0
        P[:, EP] = 0.0
        P[EP, EP] = self.var
        x[EP] = 0.0
