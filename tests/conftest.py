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
