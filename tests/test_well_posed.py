"""``otbot_hw.model.well_posed``: a parameter set whose values each pass their rule but together make
the task-space mass matrix singular is refused at load, by name; every set the compiled simulator
cannot integrate (it divides by an exact zero) is among the refused; robots with every parameter
perturbed pass."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from otbot_hw.model.effects import ExtendedModel
from otbot_hw.model.well_posed import MAX_CONDITION, check_well_posed, load_params, worst_condition
from otbot_hw.params import SCHEMA, OtbotParams, ParameterError, nominal
from otbot_hw.simulation.simulator import simulate

ROOT_PARAMS = OtbotParams.load()


def test_the_nominal_robot_is_far_from_singular():
    cond, _, _ = worst_condition(nominal())
    assert 1.0 <= cond < 10.0


def test_a_mass_written_with_a_wrong_exponent_is_refused_by_name():
    with pytest.raises(ParameterError) as e:
        check_well_posed(ROOT_PARAMS.replace(m_c=1e30), "robot.yaml")
    msg = str(e.value)
    assert msg.startswith("robot.yaml: these parameters make the model singular")
    assert "largest m_c = 1e+30 kg" in msg and "\n" not in msg


def test_the_refusal_holds_at_the_boundary():
    """The same rule both ways: a set just inside the bound passes, the worst condition it reports is
    within it; scaling the culprit up pushes the number past the bound and the set is refused."""
    p = ROOT_PARAMS
    passing = None
    for mc in (1e4, 1e6, 1e8, 1e10, 1e12, 1e14, 1e16):
        q = p.replace(m_c=mc)
        cond, _, _ = worst_condition(q)
        if cond <= MAX_CONDITION:
            assert check_well_posed(q) is q
            passing = mc
        else:
            with pytest.raises(ParameterError):
                check_well_posed(q)
    assert passing is not None and passing < 1e16


@pytest.mark.parametrize("seed", [0, 1])
def test_every_set_the_compiled_model_cannot_integrate_is_refused(seed):
    """Random robots, each value within 1e-6..1e6 of its SI unit (half of them at an end): where the
    compiled simulator divides by zero, the check refused the set first."""
    rng = np.random.default_rng(seed)
    refused = crashed = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for _ in range(40):
            vals = {}
            for _, name, _, rule in SCHEMA:
                if name in ("radius", "x_F", "y_F"):
                    continue
                e = float(rng.choice([1e-6, 1e6, 10 ** rng.uniform(-6, 6)]))
                vals[name] = (e * rng.choice([-1.0, 1.0]) * rng.choice([0.0, 1.0]) if rule == "finite"
                              else e * rng.choice([0.0, 1.0]) if rule == "nonnegative" else e)
            q = ROOT_PARAMS.replace(x_F=0.0, y_F=0.0, **vals)
            try:
                check_well_posed(q)
                ok = True
            except ParameterError:
                ok = False
                refused += 1
            for u in ((1.0, -1.0, 0.5), (-1e3, 1e3, 0.0)):
                try:
                    simulate(q, np.tile(u, (20, 1)), 0.01)
                except ZeroDivisionError:
                    crashed += 1
                    assert not ok, f"accepted, yet the simulator divided by zero: {vals}"
    assert refused > 0 and crashed > 0  # the sample reached both kinds


def test_robots_with_every_parameter_perturbed_pass():
    rng = np.random.default_rng(3)
    for _ in range(20):
        changes = {name: getattr(ROOT_PARAMS, name) * float(rng.uniform(0.3, 3.0))
                   for _, name, _, _ in SCHEMA if name not in ("x_F", "y_F", "radius")}
        q = ROOT_PARAMS.replace(**changes)
        assert check_well_posed(q) is q


def test_model_files_are_checked_on_load(tmp_path):
    import yaml

    src = ExtendedModel.load().params.to_dict()
    src["chassis"]["m_c"]["value"] = 1e30
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(src))
    with pytest.raises(ParameterError, match="singular"):
        ExtendedModel.load(path)
    with pytest.raises(ParameterError, match="singular"):
        load_params(path)
