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
