"""The catalog's traction limit as physics: above the limit the chassis is pushed by exactly t_trac per wheel
(the spinning wheel's own inertia is the wheel's business, not the ground's), and the spin rate follows from
the wheel's balance with its rolling inertia (``effect_physics._force_accel_into``)."""
import numpy as np
import pytest

from otbot_hw.model import compiled
from otbot_hw.model import effect_physics as phys
from otbot_hw.model import effects as fx


def test_above_the_traction_limit_the_ground_passes_t_trac(params):
    """Both wheels commanded 6 N m from rest with a 3 N m traction limit: the body accelerates as a robot
    whose wheels put exactly 3 N m on the ground and have no inertia of their own. The law before this
    (wheel inertia left out of the slip split) gave the chassis t_trac - I_a psi_dd, and a spin rate off by
    I_a psi_dd / b_w (about 0.5 rad/s at 10 rad/s^2)."""
    T = 3.0
    x = np.zeros(12)
    eff = fx.effect_vector({"k_slip": 0.02, "t_trac": T})
    acc = phys.ext_accelerations(x, np.array([6.0, 6.0, 0.0]), np.zeros(2), eff, params.as_array(), compiled.FLOOR)
    massless = params.as_array()
    massless[phys._IA] = 0.0  # wheels without inertia (the parameter check refuses it; the model does not)
    ref = phys.ext_accelerations(x, np.array([T, T, 0.0]), np.zeros(2), fx.effect_vector(), massless,
                                 compiled.FLOOR)
    assert np.abs(ref[:3]).max() > 0.1  # the robot does accelerate
    assert acc[[0, 1, 2, 5]] == pytest.approx(ref[[0, 1, 2, 5]], rel=1e-4)  # the old law: 2-3 % off
    # the spin rate: (tau - T - I_a psi_dd) / b_w with the wheel's rolling acceleration (at rest: no friction)
    z = np.zeros(14)
    dz = np.empty(14)
    phys.ext_derivative_into(z, np.array([6.0, 6.0, 0.0]), np.zeros(2), eff, params.as_array(), compiled.FLOOR,
                             dz, np.empty(6), np.empty(6), np.empty(6), np.empty(2))
    expected = (6.0 - T - params.I_a * acc[3]) / params.b_w
    assert dz[12] == pytest.approx(expected, rel=1e-3)
