"""The estimation error block, one computation for every command: alpha's difference wrapped."""
import math

import numpy as np
import pytest

from otbot_hw.estimation.errors import describe_estimation_error, estimation_error


def test_alpha_difference_across_pi_is_wrapped_and_the_summary_is_max_and_rms():
    truth = np.array([[0.0, 0.0, -math.pi + 0.01], [1.0, 2.0, 0.5]])
    est = np.array([[0.003, -0.004, math.pi - 0.01], [1.0, 2.0, 0.5 + 2 * math.pi + 0.002]])
    e = estimation_error(est, truth)
    assert e["max"]["alpha"] == pytest.approx(0.02, abs=1e-9)
    assert e["rms"]["alpha"] == pytest.approx(math.sqrt((0.02 ** 2 + 0.002 ** 2) / 2), abs=1e-9)
    assert e["max"]["x"] == pytest.approx(0.003) and e["max"]["y"] == pytest.approx(0.004)
    assert e["rms"]["y"] == pytest.approx(0.004 / math.sqrt(2))
    line = describe_estimation_error(e)
    assert "x 3.00 (2.12) mm" in line and "alpha 20.000" in line
