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


def test_a_traction_limit_under_constant_torques_is_named_and_its_creep_slope_not_identifiable():
    """The paper's kind of run, one constant torque per motor far above a 3 N m traction limit: the wheels spin
    from the start. The nominal fit absorbs the spin into I_p on its bound and the screening about that fit
    missed the effect ("model inadequate", nothing named); screened about the file's values too it is named,
    t_trac measured, and the creep slope, which never acts here, is "not identifiable" with what to record."""
    from otbot_hw.diagnose.data import from_recording
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.params import nominal
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import extended_recording

    P = nominal()
    model = fx.ExtendedModel(P, fx.effect_vector()).with_values({"k_slip": 0.02, "t_trac": 3.0})
    U = np.tile([6.45, -6.9, 1.4], (300, 1))
    rec = extended_recording(model, U, 0.01, NoiseModel.paper(), seed=3, fixture="floor")
    r = diagnose([from_recording(rec, "constant")], P)
    assert r["model_adequate"], r["verdict"]
    named = [e["name"] for e in r["effects"]] + [g["candidates"][0]["name"] for g in r["ambiguous"]]
    assert named == ["traction_limit"], r["verdict"]
    entry = next(e for e in r["effects"] if e["name"] == "traction_limit")
    assert entry["parameters"]["t_trac"]["value"] == pytest.approx(3.0, rel=0.2)
    assert entry["parameters"]["t_trac"]["std"] is not None  # determined, while the creep slope is not
    slope = [x for x in r["not_identifiable"] if x["kind"] == "parameter" and x["name"] == "k_slip"]
    assert slope and slope[0]["effect"] == "traction_limit" and "below the traction limit" in slope[0]["record"]


def test_only_the_parameter_without_information_loses_its_std():
    """A fit whose covariance is singular in one direction: the parameters spanning it get std NaN, the others
    keep theirs (before, one undetermined creep slope made every std of the fit NaN, t_trac's included)."""
    from otbot_hw.diagnose.refit import _determined, _undetermined

    cov = np.diag([4.0, 1e-6, 0.0])  # the third: no variance at all (a zero Jacobian column)
    assert not _determined(cov)
    assert list(_undetermined(cov)) == [False, False, True]
    c = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]])  # the first two only together
    assert list(_undetermined(c)) == [True, True, False]
    nan = np.diag([1.0, np.nan, 1.0])
    assert list(_undetermined(nan)) == [False, True, False]


def test_undetermined_parameters_of_a_found_effect_are_not_identifiable_with_what_to_record():
    from otbot_hw.diagnose.identifiability import undetermined_effect_parameters

    effects = [{"name": "traction_limit", "parameters": {"k_slip": {"value": 1e-4, "std": None},
                                                         "t_trac": {"value": 3.0, "std": 0.001}}},
               {"name": "air_drag", "parameters": {"c_air": {"value": 10.0, "std": 20.0}}},
               {"name": "imu_bias", "parameters": {"b_gz": {"value": 0.005, "std": 0.0005}}}]
    out = undetermined_effect_parameters(effects, {"k_slip": 0.02, "t_trac": 3.0, "c_air": 15.0, "b_gz": 0.005})
    assert [(x["effect"], x["name"]) for x in out] == [("traction_limit", "k_slip"), ("air_drag", "c_air")]
    assert all(x["kind"] == "parameter" and x["record"] and x["why"] for x in out)
    assert "below the traction limit" in out[0]["record"] and "typical size 15" in out[1]["why"]


def test_a_tanh_traction_curve_is_named_with_its_creep_slope_and_knee():
    """The traction knee is a modelling assumption: a robot whose tyres saturate as T tanh(y) (the project's
    simulator with kn_trac = 1, T tanh y) under random piecewise-constant torques above and below a
    3 N m limit. With the catalog's magic-formula knee alone the fit reads k_slip 0.011 (-45 %: the data see
    the knee, not the creep slope); the knee refinement (``catalog.SHAPE_REFINEMENTS``) is kept and k_slip,
    t_trac and the knee come out right."""
    from otbot_hw.diagnose.data import from_recording
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.params import nominal
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import extended_recording

    P = nominal()
    model = fx.ExtendedModel(P, fx.effect_vector()).with_values({"k_slip": 0.02, "t_trac": 3.0, "kn_trac": 1.0})
    rng = np.random.default_rng(1)
    U = np.repeat(rng.uniform(-8, 8, (13, 3)) * [1, 1, 0.3], 50, axis=0)[:600]
    rec = extended_recording(model, U, 0.01, NoiseModel.paper(), seed=1, fixture="floor")
    r = diagnose([from_recording(rec, "tanh")], P)
    assert r["model_adequate"], r["verdict"]
    assert [e["name"] for e in r["effects"]] == ["traction_limit"] and not r["ambiguous"], r["verdict"]
    got = r["effects"][0]["parameters"]
    assert got["k_slip"]["value"] == pytest.approx(0.02, rel=0.2)
    assert got["t_trac"]["value"] == pytest.approx(3.0, rel=0.2)
    assert got["kn_trac"]["value"] == pytest.approx(1.0, abs=0.3)
    (tried,) = r["shape_refinements"]
    assert tried["parameter"] == "kn_trac" and tried["kept"] and tried["delta_bic"] < -10
