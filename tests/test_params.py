"""Parameter file validation, the CLI's exit code on bad parameters, and loads (Steiner)."""
import subprocess
import sys

import numpy as np
import pytest
import yaml

from otbot_hw.cli import main
from otbot_hw.model import dynamics as dyn
from otbot_hw.model import compiled
from otbot_hw.model.fixtures import fixture_code
from otbot_hw.params import DEFAULT_PARAMS_FILE, OtbotParams, ParameterError, nominal

#: The paper's Table 3 (SI units).
TABLE3 = {"l1": 0.25, "l2": 0.20, "r": 0.10, "x_B": -0.13, "y_B": 0.0, "x_F": 0.0, "y_F": 0.0,
          "m_c": 109.14, "m_p": 21.95, "I_c": 1.30, "I_p": 2.22, "I_a": 1.04e-2, "b_w": 0.18, "b_p": 0.24}


def test_nominal_file_holds_table_3():
    p = nominal()
    for name, value in TABLE3.items():
        assert getattr(p, name) == value, name
    assert p.radius > 0
    assert len(p.as_array()) == 14


def nominal_dict():
    return yaml.safe_load(DEFAULT_PARAMS_FILE.read_text())


def set_in(d, path, value):
    keys = path.split(".")
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value


def del_in(d, path):
    keys = path.split(".")
    for k in keys[:-1]:
        d = d[k]
    del d[keys[-1]]


@pytest.mark.parametrize("edit, expected", [
    (("set", "chassis.m_c.value", -1.0), ["chassis.m_c", "must be > 0"]),
    (("set", "platform.m_p.value", 0), ["platform.m_p", "must be > 0"]),
    (("set", "platform.I_p.value", 0.0), ["platform.I_p", "must be > 0"]),
    (("set", "chassis.I_c.value", -2.0), ["chassis.I_c", "must be > 0"]),
    (("set", "wheel.I_a.value", -1e-3), ["wheel.I_a", "must be > 0"]),
    (("set", "geometry.l1.value", -0.25), ["geometry.l1", "must be > 0"]),
    (("set", "geometry.l2.value", 0.0), ["geometry.l2", "must be > 0"]),
    (("set", "geometry.r.value", -0.1), ["geometry.r", "must be > 0"]),
    (("set", "platform.radius.value", 0.0), ["platform.radius", "must be > 0"]),
    (("set", "friction.b_w.value", -0.1), ["friction.b_w", "must be >= 0"]),
    (("del", "platform.x_F"), ["missing key 'platform.x_F'"]),
    (("del", "wheel"), ["missing section 'wheel'"]),
    (("set", "chassis.mass", {"value": 3.0, "unit": "kg"}), ["unknown key", "mass", "section 'chassis'"]),
    (("set", "motors", {"k": {"value": 1, "unit": "A"}}), ["unknown section", "motors"]),
    (("set", "chassis.I_c.unit", "kg m2"), ["chassis.I_c", "unit must be 'kg m^2'", "'kg m2'"]),
    (("del", "geometry.r.unit"), ["geometry.r", "unit must be 'm'"]),
    (("set", "platform.m_p.value", "heavy"), ["platform.m_p", "must be a number", "'heavy'"]),
    (("set", "platform.m_p.value", True), ["platform.m_p", "must be a number"]),
    (("set", "chassis.x_B.value", float("nan")), ["chassis.x_B", "must be finite"]),
    (("set", "chassis.m_c", 109.14), ["chassis.m_c", "must be a mapping with 'value' and 'unit'"]),
    (("set", "chassis.m_c.sigma", 0.1), ["chassis.m_c", "unknown field", "sigma"]),
    (("set", "chassis.m_c.std", -0.1), ["chassis.m_c.std", ">= 0"]),
    (("set", "platform.x_F.value", 0.45), ["x_F, y_F", "outside the platform radius 0.5"]),
])
def test_bad_parameter_files_name_the_key_and_rule(tmp_path, edit, expected):
    d = nominal_dict()
    if edit[0] == "set":
        set_in(d, edit[1], edit[2])
    else:
        del_in(d, edit[1])
    if edit[1] == "platform.x_F.value":
        d["platform"]["y_F"]["value"] = 0.3  # |F| = 0.54 m > 0.5 m
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(ParameterError) as err:
        OtbotParams.load(path)
    msg = str(err.value)
    assert str(path) in msg
    for part in expected:
        assert part in msg, (part, msg)


@pytest.mark.parametrize("text, expected", [
    ("- 1\n- 2\n", "top level must be a mapping"),
    ("geometry: [1, 2\n", "not valid YAML"),
    ("geometry: 3\n", "unknown section|section 'geometry' must be a mapping"),
])
def test_malformed_yaml_is_rejected(tmp_path, text, expected):
    path = tmp_path / "p.yaml"
    path.write_text(text)
    with pytest.raises(ParameterError, match=expected):
        OtbotParams.load(path)


def test_missing_file_is_rejected(tmp_path):
    with pytest.raises(ParameterError, match="cannot read parameter file"):
        OtbotParams.load(tmp_path / "nope.yaml")


def test_replace_validates():
    with pytest.raises(ParameterError, match="m_c: must be > 0"):
        nominal().replace(m_c=-3.0)
    with pytest.raises(ParameterError, match="outside the platform radius"):
        nominal().replace(x_F=0.6)


def test_save_and_load_round_trip(tmp_path):
    p = nominal().replace(m_p=30.5, x_F=0.05)
    p = OtbotParams(**{**p.values(), "std": {"m_p": 0.2, "I_p": 0.01}})
    p.save(tmp_path / "id.yaml", header="identified\nby a test")
    back = OtbotParams.load(tmp_path / "id.yaml")
    assert back == p and dict(back.std) == {"m_p": 0.2, "I_p": 0.01}
    assert (tmp_path / "id.yaml").read_text().startswith("# identified\n# by a test\n")


# --- CLI ------------------------------------------------------------------------

def write_bad(tmp_path):
    d = nominal_dict()
    d["chassis"]["m_c"]["value"] = -5.0
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def test_cli_simulate_bad_params_exits_2_naming_the_key(tmp_path, capsys):
    rc = main(["simulate", "--params", str(write_bad(tmp_path)), "--duration", "0.1", "--json"])
    captured = capsys.readouterr()
    assert rc == 2
    assert "chassis.m_c" in captured.err and "must be > 0" in captured.err
    assert captured.out == ""


def test_cli_bad_params_exit_code_from_a_process(tmp_path):
    proc = subprocess.run([sys.executable, "-c", "import sys; from otbot_hw.cli import main; sys.exit(main())",
                           "simulate", "--params", str(write_bad(tmp_path))], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "chassis.m_c" in proc.stderr


# --- loads ----------------------------------------------------------------------

LOAD = dict(mass=8.0, x=0.2, y=-0.1, inertia=0.05)


def inertia_about(I_own, m, com, point):
    """Vertical inertia of a body about ``point`` (Steiner)."""
    return I_own + m * float(np.sum((np.asarray(com) - point) ** 2))


@pytest.mark.parametrize("point", [(0.0, 0.0), (0.3, 0.1), (-0.2, 0.4)])
def test_with_load_steiner(point):
    """Combined inertia about any point = sum of both bodies' inertias about it; masses and moments add."""
    p = nominal().replace(x_F=0.05, y_F=0.02)
    q = p.with_load(**LOAD)
    pt = np.array(point)
    combined = inertia_about(q.I_p, q.m_p, (q.x_F, q.y_F), pt)
    parts = (inertia_about(p.I_p, p.m_p, (p.x_F, p.y_F), pt)
             + inertia_about(LOAD["inertia"], LOAD["mass"], (LOAD["x"], LOAD["y"]), pt))
    assert combined == pytest.approx(parts, rel=1e-13)
    assert q.m_p == p.m_p + LOAD["mass"]
    assert q.m_p * q.x_F == pytest.approx(p.m_p * p.x_F + LOAD["mass"] * LOAD["x"], rel=1e-13)
    assert q.m_p * q.y_F == pytest.approx(p.m_p * p.y_F + LOAD["mass"] * LOAD["y"], rel=1e-13)
    assert (q.m_c, q.I_c, q.l1) == (p.m_c, p.I_c, p.l1)  # the chassis is untouched


def test_loaded_kinetic_energy_is_robot_plus_load(rng):
    """T(loaded params) = T(unloaded) + T of the load body moving with the platform."""
    p = nominal().replace(x_F=0.05, y_F=0.02)
    q_loaded = p.with_load(**LOAD)
    for _ in range(5):
        q, qd = rng.uniform(-3, 3, 6), rng.normal(size=6)
        a, ad = q[2], qd[2]
        rel = np.array([LOAD["x"] * np.cos(a) - LOAD["y"] * np.sin(a), LOAD["x"] * np.sin(a) + LOAD["y"] * np.cos(a)])
        v = qd[:2] + ad * np.array([-rel[1], rel[0]])
        t_load = 0.5 * LOAD["mass"] * v @ v + 0.5 * LOAD["inertia"] * ad ** 2
        assert dyn.kinetic_energy(q, qd, q_loaded) == pytest.approx(dyn.kinetic_energy(q, qd, p) + t_load, rel=1e-12)


def test_loaded_platform_accelerates_per_inertia_about_pivot():
    """Chassis held (locked wheels): phi_p_dd at rest = tau_p / (I_platform,P + I_load,P)."""
    p = nominal()
    q = p.with_load(**LOAD)
    tau = 2.0
    acc = compiled.derivative(np.zeros(12), np.array([0.0, 0.0, tau]), np.zeros(2), np.zeros(6),
                              q.as_array(), fixture_code("locked"))[11]
    i_pivot = inertia_about(p.I_p, p.m_p, (p.x_F, p.y_F), 0) + inertia_about(
        LOAD["inertia"], LOAD["mass"], (LOAD["x"], LOAD["y"]), 0)
    assert acc == pytest.approx(tau / i_pivot, rel=1e-13)


def test_with_load_rejects_bad_loads():
    p = nominal()
    assert p.with_load(0.0, 0.3, 0.3) is p
    with pytest.raises(ParameterError, match="load: mass and inertia must be >= 0"):
        p.with_load(-1.0, 0.0, 0.0)
    with pytest.raises(ParameterError, match="outside the platform radius"):
        p.with_load(200.0, 0.6, 0.0)  # the combined centre of mass leaves the platform

