"""The laws beyond the catalog as steppable effects (model/effect_physics.py): each does what its entry says,
and all zero is the paper's model."""
import numpy as np

from otbot_hw.model import compiled
from otbot_hw.model import effect_physics as phys
from otbot_hw.model.effects import ExtendedModel, effect_vector
from otbot_hw.params import nominal

P = nominal()


def test_dead_zone_and_soft_limit_shape_the_delivered_torque():
    eff = effect_vector({"dz_p": 0.5, "ts_r": 2.0, "k_l": 0.1, "dz_l": 0.2})
    out = phys.actuated_torque(np.array([3.0, -1.0, 0.4]), eff)
    assert np.isclose(out[0], 2.0 * np.tanh(1.5)) and np.isclose(out[1], -1.1 + 0.2) and out[2] == 0.0
    assert np.isclose(phys.actuated_torque(np.array([0.0, 0.0, -0.8]), eff)[2], -0.3)


def test_cogging_and_linear_drag_forces():
    eff = effect_vector({"cog_r": 0.3, "cogn_r": 4.0, "cogph_r": 0.2, "cog_p": 0.1, "cogn_p": 2.0, "c_lin": 12.0})
    x = np.zeros(12)
    x[3], x[5], x[6], x[7] = 0.7, -0.4, 0.5, -0.2
    gen = phys.effect_force(x, np.zeros(3), eff, P.as_array(), compiled.FLOOR)
    assert np.allclose(gen[:2], [-6.0, 2.4])
    assert np.isclose(gen[3], -0.3 * np.sin(4 * 0.7 + 0.2))
    assert np.isclose(gen[5], -0.1 * np.sin(2 * -0.4))
    # off the floor no drag; the cogging stays
    gen = phys.effect_force(x, np.zeros(3), eff, P.as_array(), compiled.STAND)
    assert np.allclose(gen[:2], 0.0) and np.isclose(gen[3], -0.3 * np.sin(4 * 0.7 + 0.2))


def test_cogging_needs_a_whole_harmonic_and_the_file_round_trips(tmp_path):
    import pytest

    with pytest.raises(ValueError, match="cogn_r"):
        effect_vector({"cog_r": 0.3})
    m = ExtendedModel.paper(P).with_values({"cog_l": 0.2, "cogn_l": 3.0, "cogph_l": 1.0, "dz_p": 0.4, "c_lin": 9.0})
    m.save(tmp_path / "m.yaml")
    back = ExtendedModel.load(tmp_path / "m.yaml")
    assert np.array_equal(back.eff, m.eff)
    assert set(back.active_effects()) == {"cog_l", "cogn_l", "cogph_l", "dz_p", "c_lin"}


def test_the_controller_compensation_undoes_dead_zone_and_soft_limit():
    """``compensated_command``: the drives then deliver the wanted torque (dead zone and soft limit inverted)."""
    eff = effect_vector({"dz_p": 0.5, "ts_r": 4.0, "k_l": 0.1, "dz_l": 0.3})
    x = np.zeros(12)
    for want in (np.array([2.0, -1.5, 0.8]), np.array([-3.0, 0.6, -2.0])):
        u = phys.compensated_command(x, want, eff, P.as_array(), compiled.STAND)
        assert np.allclose(phys.actuated_torque(u, eff), want, atol=1e-6), (u, want)
