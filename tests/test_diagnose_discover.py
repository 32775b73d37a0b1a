"""Beyond the catalog: grouped sparse regression of the residual torques (otbot_hw/diagnose/discover.py), the
discovered law stepped, written with --out and simulated."""
import importlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from otbot_hw.cli import main
from otbot_hw.params import nominal
from otbot_hw.recording import write_recording
from otbot_hw.simulation.concealed import concealed_recording

ROOT = Path(__file__).resolve().parent.parent
P = nominal()


def _write(path, values, kind, duration, seed):
    write_recording(path, concealed_recording(P, values, kind, duration, seed=seed))
    return path


def test_dead_zone_is_discovered_written_stepped_and_simulated(tmp_path, capsys):
    """A 0.5 N m dead zone in the pivot drive (no catalog effect has one): the diagnosis says "model
    inadequate", discovers the dead zone on the pivot within 10 %, writes it with --out; the file re-simulates
    the held-out recording far closer than the nominal model, and ``otbot simulate --params`` steps it (a
    0.4 N m pivot command moves nothing)."""
    from otbot_hw.diagnose.data import load
    from otbot_hw.diagnose.simulated_run import simulation_residual
    from otbot_hw.model.effects import ExtendedModel

    fit = _write(tmp_path / "fit.mcap", {"dz_p": 0.5}, "multisine", 5.0, 11)
    held = _write(tmp_path / "held.mcap", {"dz_p": 0.5}, "tracking", 5.0, 12)
    out = tmp_path / "model.yaml"
    with pytest.raises(SystemExit) as exc:
        main(["diagnose", str(fit), "--holdout", str(held), "--out", str(out), "--json"])
    assert exc.value.code == 1
    cap = capsys.readouterr()
    r = json.loads(cap.out)
    assert r["model_adequate"] is False and r["effects"] == []
    laws = r["discovered"]["laws"]
    assert [lw["kind"] for lw in laws] == ["dead_zone"] and laws[0]["joint"] == "p", laws
    dz = laws[0]["refit"]["dz_p"]
    assert abs(dz["value"] - 0.5) < 0.05 and 0 < dz["std"] < 0.05, dz
    assert r["discovered"]["improves"] and r["model_file"] == str(out) and "dead zone" in r["verdict"]
    model = ExtendedModel.load(out)
    assert abs(model.get("dz_p") - 0.5) < 0.05
    hd = load([held])[0]
    before = simulation_residual(hd, ExtendedModel.paper(P))["w_p"]
    after = simulation_residual(hd, model)["w_p"]
    assert np.sqrt(np.mean(after ** 2)) < 0.5 * np.sqrt(np.mean(before ** 2))
    for params, moves in ((None, True), (out, False)):
        argv = ["simulate", "--torques", "0,0,0.4", "--duration", "1", "--noise", "none", "--json"]
        assert main(argv + (["--params", str(params)] if params else [])) in (0, None)
        w_p = json.loads(capsys.readouterr().out)["qd"][5]
        assert (abs(w_p) > 0.05) == moves, w_p


def test_clean_recording_discovers_nothing():
    """Discovery run on clean recordings (nothing outside the model) finds no law: the gates hold."""
    from otbot_hw.diagnose.data import from_recording
    from otbot_hw.diagnose.discover import discover
    from otbot_hw.diagnose.refit import refit
    from otbot_hw.diagnose.select import free_nominal
    from otbot_hw.model.effects import ExtendedModel

    fit = [from_recording(concealed_recording(P, {}, "multisine", 5.0, seed=21), "fit")]
    held = [from_recording(concealed_recording(P, {}, "tracking", 5.0, seed=22), "held")]
    base = refit(fit, ExtendedModel.paper(P), free_nominal(fit))
    r = discover(fit, held, base.model)
    assert r["laws"] == [], r["laws"]
    assert r["tried"] and all(t["p_value"] > 1e-3 or t["heldout_gain"] < 0.03 for t in r["tried"])


@pytest.fixture(scope="module")
def ir():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    return importlib.import_module("independent_robot")


def test_cogging_on_one_wheel_of_the_independent_robot_is_discovered(ir, tmp_path):
    """Cogging 0.3 N m sin(4 phi_r) on the right wheel of the independent robot (its own dynamics and effect
    form): the regression names cogging at 4 cycles per turn on that wheel with about its size, and the
    held-out right-wheel torque residual shrinks by more than half."""
    from otbot_hw.diagnose.data import load
    from otbot_hw.diagnose.discover import discover
    from otbot_hw.diagnose.refit import refit
    from otbot_hw.diagnose.select import free_nominal
    from otbot_hw.model.effects import ExtendedModel

    world = ir.World(cogging=(0.3, 4))
    for kind, seed in (("piecewise", 31), ("smooth", 32)):
        ir.record(tmp_path / f"{kind}.mcap", world, kind, seed)
    fit, hold = load([tmp_path / "piecewise.mcap"]), load([tmp_path / "smooth.mcap"])
    base = refit(fit, ExtendedModel.paper(nominal()), free_nominal(fit))
    r = discover(fit, hold, base.model)
    cog = [lw for lw in r["laws"] if lw["kind"] == "cogging"]
    assert cog and cog[0]["joint"] == "r" and cog[0]["effect"]["cogn_r"] == 4, r["laws"]
    assert 0.2 < cog[0]["effect"]["cog_r"] < 0.4 and abs(cog[0]["effect"]["cogph_r"]) < 0.3, cog
    assert r["heldout"]["r"]["after_rms"] < 0.5 * r["heldout"]["r"]["before_rms"], r["heldout"]
