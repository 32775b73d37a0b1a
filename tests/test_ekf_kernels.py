"""The pose EKF's compiled hot path against filterpy's ExtendedKalmanFilter and against the EKF before
its cycle became one compiled call (``otbot_hw.estimation.imu_cycle``)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter

from otbot_hw.estimation import EstimatorConfig, PoseEKF, kernels
from otbot_hw.estimation.ekf_state import BAX, BAY, N_STATE
from otbot_hw.params import nominal

DATA = Path(__file__).resolve().parent / "data"


def _random_state(rng):
    x = rng.normal(size=N_STATE) * np.array([1, 1, 3, .5, .5, 1, .01, .05, .05, .1, .002, 1, .05, .05])
    A = rng.normal(size=(N_STATE, N_STATE)) * rng.uniform(0.01, 1.0, N_STATE)
    P = A @ A.T + 1e-6 * np.eye(N_STATE)
    return x, P


@pytest.mark.parametrize("seed", range(20))
def test_prediction_covariance_equals_filterpy(seed):
    """``kernels.predict_imu`` on a random state: its covariance is filterpy's F P F^T + Q with the F, Q
    it returns, and that F is the Jacobian of its state transition (finite differences) up to the terms of
    order dt^3 it leaves out (d's and alpha_dot's share in the mid-step heading of the position)."""
    rng = np.random.default_rng(seed)
    x, P = _random_state(rng)
    fx, fy, add = rng.normal(size=3)
    dt = rng.uniform(1e-4, 0.02)
    args = (fx, fy, add, dt, 0.3, 1e-6, 1e-4, 0.5)
    F, Q = np.empty((N_STATE, N_STATE)), np.empty((N_STATE, N_STATE))
    xk, Pk = x.copy(), P.copy()
    kernels.predict_imu(xk, Pk, *args, F, Q)
    kf = ExtendedKalmanFilter(dim_x=N_STATE, dim_z=3)
    kf.x, kf.P, kf.F, kf.Q = x.copy(), P.copy(), F.copy(), Q.copy()
    kf.predict()
    assert np.abs(Pk - kf.P).max() <= 1e-12 * max(1.0, np.abs(kf.P).max())
    J = np.empty((N_STATE, N_STATE))
    h = 1e-6
    for j in range(N_STATE):
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        for v in (xp, xm):
            kernels.predict_imu(v, P.copy(), *args, np.empty_like(F), np.empty_like(Q))
        J[:, j] = (xp - xm) / (2 * h)
    assert np.abs(J - F).max() < 10 * dt ** 3 + 1e-7


@pytest.mark.parametrize("seed", range(20))
@pytest.mark.parametrize("m", [1, 2, 3])
def test_update_equals_filterpy(seed, m):
    """``kernels.gated_update`` (forced, every state corrected) is filterpy's ``update`` (Joseph form) to
    1e-12; with the accelerometer biases considered (Schmidt) their state stays and the covariance is
    the general-gain formula's; a gate the NIS exceeds leaves x and P untouched."""
    rng = np.random.default_rng(100 + seed)
    x, P = _random_state(rng)
    H = rng.normal(size=(m, N_STATE))
    R = np.diag(rng.uniform(0.01, 1.0, m))
    nu = rng.normal(size=m)
    xk, Pk = x.copy(), P.copy()
    d2, ok = kernels.gated_update(xk, Pk, nu, H, R, 0.0, True, True)
    assert ok
    kf = ExtendedKalmanFilter(dim_x=N_STATE, dim_z=m)
    kf.x, kf.P, kf.R = x.copy(), P.copy(), R.copy()
    kf.update(np.zeros(m), lambda _x: H, lambda _x: -nu)  # residual z - Hx = nu
    scale = max(1.0, np.abs(kf.P).max())
    assert np.abs(xk - kf.x).max() <= 1e-12 * max(1.0, np.abs(kf.x).max())
    assert np.abs(Pk - kf.P).max() <= 1e-12 * scale
    assert d2 == pytest.approx(float(nu @ np.linalg.solve(kf.S, nu)), rel=1e-10)
    # Schmidt: zero gain on the accelerometer biases
    xs, Ps = x.copy(), P.copy()
    kernels.gated_update(xs, Ps, nu, H, R, 0.0, True, False)
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    K[[BAX, BAY]] = 0.0
    assert xs[BAX] == x[BAX] and xs[BAY] == x[BAY]
    assert np.abs(Ps - (P - K @ H @ P - P @ H.T @ K.T + K @ S @ K.T)).max() <= 1e-12 * scale
    # gated out
    xg, Pg = x.copy(), P.copy()
    _, ok = kernels.gated_update(xg, Pg, nu, H, R, 0.5 * d2, False, True)
    assert not ok and np.array_equal(xg, x) and np.array_equal(Pg, P)


def test_a_recorded_run_gives_the_estimates_of_the_ekf_before():
    """A 6 s sensed run (slip bursts that reject the wheels and re-anchor the heading, a gyro bias, the IMU
    held over several samples, pose fixes) through today's EKF: every sample's pose, twist, std, gyro
    bias, variances and NIS equal (1e-9) those the EKF of main at b6993cc -- before its cycle became
    one compiled call -- computed (``tests/data/make_ekf_reference.py``); same gate counts."""
    sys.path.insert(0, str(DATA))
    try:
        import make_ekf_reference as ref
    finally:
        sys.path.remove(str(DATA))
    d = dict(np.load(DATA / "ekf_reference.npz"))
    out = ref.run(d, PoseEKF(nominal(), float(d["period"]), EstimatorConfig()))
    assert d["ref_rejected"][0] > 10 and d["ref_rejected"][1] >= 1  # the run does exercise the rare paths
    for k in ("pose", "twist", "std", "gyro_bias", "var", "nis"):
        assert np.array_equal(np.isnan(out[k]), np.isnan(d[f"ref_{k}"])), k
        assert np.nanmax(np.abs(out[k] - d[f"ref_{k}"])) <= 1e-9, k
    assert out["rejected"].tolist() == d["ref_rejected"].tolist()
    assert out["updates"].tolist() == d["ref_updates"].tolist()
