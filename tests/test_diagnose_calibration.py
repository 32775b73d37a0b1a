"""Clean recordings the diagnosis was not tuned on are judged clean (small fast version of
benchmarks/diagnose_calibration.py), and recordings that cannot test anything are refused (exit 2)."""
import importlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def calibration():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    return importlib.import_module("diagnose_calibration")


def test_issue_20_clean_case_is_clean_and_its_cause_is_the_initial_pivot_rate(calibration, tmp_path):
    """10 s floor run of the independent simulator, piecewise-constant torques +-8 N m held 0.4-1.2 s, 100 Hz:
    the first pivot-rate reading is beyond 3 sigma, which used to set the initial pivot rate (judged
    "model inadequate", w_p 2.1 x noise); the initial rates fitted to the first 0.25 s give a start at rest."""
    from otbot_hw.diagnose import simulated_run as R
    from otbot_hw.diagnose.data import load
    from otbot_hw.model.effects import ExtendedModel
    from otbot_hw.params import nominal

    spec = calibration.Spec(0, "independent", "piecewise_long", 10.0, 100.0, "floor", 10)
    d = load([calibration.record(spec, tmp_path)])[0]
    m = ExtendedModel.paper(nominal())
    assert abs(R.encoder_state(d, m)[11]) > 0.02  # what one noisy sample said: 0.029 rad/s
    assert np.all(R.initial_state(d, m)[6:] == 0.0)  # at rest
    row = calibration.run_one(spec)
    assert row["outcome"] == "clean", row


@pytest.mark.parametrize("spec", [("project", "multisine", 2.0, 200.0, "stand", 3),
                                  ("project", "prbs", 2.0, 100.0, "locked", 4),
                                  ("independent", "chirp", 2.0, 100.0, "floor", 5),
                                  ("bus", "sim_bus", 1.0, 100.0, "floor", 6, "prbs"),
                                  ("independent", "closed_loop_independent", 3.0, 200.0, "floor", 7)])
def test_clean_recordings_of_other_families_fixtures_and_rates_find_nothing(calibration, spec):
    row = calibration.run_one(calibration.Spec(0, *spec))
    assert row["outcome"] == "clean", row


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "otbot_hw", "diagnose", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("case", ["quiet", "short"])
def test_a_recording_that_cannot_test_anything_is_refused_with_what_to_record(case, tmp_path):
    from otbot_hw.params import nominal
    from otbot_hw.recording import write_recording
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    n, dt = (300, 0.01) if case == "quiet" else (100, 0.001)
    U = np.zeros((n, 3)) if case == "quiet" else np.tile([3.0, -3.0, 1.0], (n, 1))
    path = tmp_path / f"{case}.mcap"
    write_recording(path, simulated_recording(nominal(), U, dt, NoiseModel.paper(), seed=1))
    r = _cli(path)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert ("too quiet" if case == "quiet" else "too short") in lines[0] and "record at least 1 s" in lines[0]
    assert "model inadequate" not in r.stderr


def test_one_second_under_one_constant_torque_is_not_identifiable_not_model_inadequate(calibration, tmp_path):
    """Calibration case #187 (project simulator, floor, 1 s at 100 Hz, one constant torque): I_c ends on its
    lower bound with a std of about the file's value -- the record does not determine it. That is "not
    identifiable from this recording" with what to record, not "model inadequate"; and the Fisher criterion
    says which effects this run cannot reveal: a gain error of the left motor, which pushes 0.06 N m, but not
    of the right one, which pushes 1.8 N m."""
    from otbot_hw.diagnose.data import load
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.params import nominal

    spec = calibration.Spec(187, "project", "piecewise_slow", 1.0, 100.0, "floor", 187)
    U = calibration.excitation(spec.family, spec.duration, 1 / spec.rate, spec.seed)
    assert np.all(U == U[0]) and abs(U[0, 1]) < 0.1 < 1.0 < abs(U[0, 0])
    r = diagnose(load([calibration.record(spec, tmp_path)]), nominal())
    assert r["model_adequate"] and r["effects"] == [] and "inadequate" not in r["verdict"], r["verdict"]
    params = {x["name"]: x for x in r["not_identifiable"] if x["kind"] == "parameter"}
    assert "I_c" in params and params["I_c"]["std"] > 0.3 and params["I_c"]["record"]
    assert "Not identifiable from this recording: I_c" in r["verdict"]
    effects = {x["name"] for x in r["not_identifiable"] if x["kind"] == "effect"}
    assert "gain_left" in effects and "gain_right" not in effects
    assert not r["identifiability"]["gain_left"]["identifiable"] and r["identifiability"]["gain_right"]["identifiable"]
