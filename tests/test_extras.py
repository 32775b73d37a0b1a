"""Optional extras: a command whose extra is missing stops with one line naming it (exit 2)."""
from __future__ import annotations

import sys

import pytest

from otbot_hw.cli import main
from otbot_hw.extras import EXTRAS, MissingExtraError, require


def test_require_names_the_extra_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "casadi", None)  # import casadi now raises ImportError
    with pytest.raises(MissingExtraError, match=r"pip install 'otbot-hw\[planner\]'"):
        require("casadi")


def test_every_extra_is_declared_in_pyproject():
    import tomllib
    from pathlib import Path

    extras = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())[
        "project"]["optional-dependencies"]
    for module, (extra, _) in EXTRAS.items():
        if extra in extras:
            assert any(dep.startswith(module) for dep in extras[extra]), (extra, module)


def test_plan_without_the_planner_extra_is_one_line_exit_2(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "casadi", None)
    rc = main(["plan", "--out", str(tmp_path / "traj.csv")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and "otbot-hw[planner]" in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "traj.csv").exists()


def test_a_cluster_without_the_cluster_extra_is_one_line_exit_2(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)
    rc = main(["sweep", "--scheduler", "tcp://127.0.0.1:1", "--points", "2", "--seeds", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "otbot-hw[cluster]" in err[0], err


def test_a_reader_that_closes_the_pipe_early_gets_no_traceback():
    import subprocess

    proc = subprocess.Popen([sys.executable, "-m", "otbot_hw", "simulate", "--torques", "1,1,1", "--duration", "0.1",
                             "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.stdout.close()  # the reader is gone long before the command has imported anything
    err = proc.stderr.read()
    assert proc.wait(timeout=120) == 1
    assert "Traceback" not in err and err.strip().endswith("output closed by the reader"), err
