import numpy as np
import pytest

from otbot_hw.params import nominal


@pytest.fixture(scope="session")
def params():
    """Nominal parameters with an off-centre platform and chassis, so no term vanishes."""
    return nominal().replace(x_F=0.12, y_F=-0.07, y_B=0.03)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def otbot_cli(capsys):
    """Run ``otbot argv`` in-process: returns (exit code, stdout, stderr)."""
    from otbot_hw.cli import main

    def run(argv):
        try:
            rc = main(list(argv))
        except SystemExit as exc:  # commands may exit 1 themselves; --help exits 0
            rc = exc.code
        out = capsys.readouterr()
        return rc, out.out, out.err

    return run


@pytest.fixture
def robot_yaml(tmp_path):
    """The one set-up of a hardware configuration copy: ``make(replace=None, folder=None)`` writes
    config/robot.yaml with each old -> new text of ``replace`` substituted (each must occur) and its EDS
    files beside it, into ``folder`` (default ``tmp_path``); returns the robot.yaml path."""
    from otbot_hw.runtime.daemon_process import config_copy

    def make(replace: dict[str, str] | None = None, folder=None):
        return config_copy(tmp_path if folder is None else folder, replace)

    return make
