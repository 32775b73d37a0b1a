"""Sensor models: IMU noise level, measured noise statistics, seeding, IMU physics, encoder counts."""
import numpy as np
import pytest

from otbot_hw.sensors import GRAVITY, NoiseModel, imu_sigma, measure
from otbot_hw.simulation.runs import simulated_recording
from otbot_hw.simulation.simulator import ForceSchedule, PivotForce, simulate


def test_imu_sigma_is_noise_density_times_root_sample_rate():
    """Paper §4.3.2: ND = 1.37e-3 m s^-2 Hz^-1/2, SR = 100 Hz -> sigma = 13.7e-3 m/s^2 (printed 13.73e-3)."""
    assert imu_sigma() == pytest.approx(13.7e-3, rel=1e-12)
    assert imu_sigma() == pytest.approx(13.73e-3, rel=3e-3)
    assert imu_sigma(2e-3, 400.0) == pytest.approx(0.04, rel=1e-12)
    assert imu_sigma(1.37e-3, 400.0) == pytest.approx(2 * imu_sigma(), rel=1e-12)
    paper = NoiseModel.paper()
    assert paper.accel == imu_sigma() and paper.gyro == imu_sigma()


def test_measured_noise_has_the_configured_statistics(params):
    """Over 20000 samples of a robot at rest: zero-mean noise with the configured std, channels independent."""
    n = 20000
    noise = NoiseModel(accel=imu_sigma(), gyro=0.02, enc_angle=1e-3, enc_rate=0.01)
    x, u, f = np.zeros((n, 12)), np.zeros((n, 3)), np.zeros((n, 2))
    s = measure(x, u, f, params, noise, np.random.default_rng(11))
    residuals = {
        "accel": s.imu_accel - [0.0, 0.0, GRAVITY], "gyro": s.imu_gyro,
        "enc_angle": s.joint_pos, "enc_rate": s.joint_vel,
    }
    for name, r in residuals.items():
        sigma = getattr(noise, name)
        assert np.all(np.abs(r.std(axis=0) / sigma - 1) < 0.03), name  # 6 standard errors
        assert np.all(np.abs(r.mean(axis=0)) < 4 * sigma / np.sqrt(n)), name
    allr = np.hstack([r / getattr(noise, k) for k, r in residuals.items()])
    corr = np.corrcoef(allr.T) - np.eye(12)
    assert np.abs(corr).max() < 0.04


def test_noiseless_model_reads_truth(params):
    traj = simulate(params, np.tile([3.0, -2.0, 1.0], (20, 1)), 0.01)
    s = measure(traj.x, traj.u, traj.f, params, NoiseModel())
    assert np.array_equal(s.joint_pos, traj.q[:, 3:])
    assert np.array_equal(s.joint_vel, traj.qd[:, 3:])
    assert np.array_equal(s.imu_gyro[:, 2], traj.qd[:, 2]) and np.all(s.imu_gyro[:, :2] == 0)
    assert np.all(s.imu_accel[:, 2] == GRAVITY)


def test_seeded_runs_are_reproducible(params):
    U = np.tile([6.0, -10.0, 6.0], (50, 1))
    a = simulated_recording(params, U, 0.01, NoiseModel.paper(), seed=3)
    b = simulated_recording(params, U, 0.01, NoiseModel.paper(), seed=3)
    c = simulated_recording(params, U, 0.01, NoiseModel.paper(), seed=4)
    for name in ("joint_pos", "joint_vel", "imu_accel", "imu_gyro"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert not np.array_equal(a.imu_accel, c.imu_accel)
    assert np.array_equal(a.truth_q, c.truth_q)  # noise never touches the truth
    assert a.metadata["seed"] == 3 and a.metadata["noise"]["accel"] == imu_sigma()


def test_imu_reads_pivot_acceleration_in_platform_frame(params):
    """IMU accel (x'', y'') = pivot acceleration projected on the platform axes 1'', 2''.

    The acceleration is taken from finite differences of the simulated pivot velocity
    in the ground frame (independent of the model's acceleration output), on a run with
    time-varying torques and a pivot force. Torques change every 50 fine samples; at the
    first sample of a block the IMU must see the new command (sample k uses u_k).
    """
    h, block, nb = 1e-3, 50, 12
    rng = np.random.default_rng(8)
    Ub = rng.uniform(-8, 8, size=(nb, 3))
    U = np.repeat(Ub, block, axis=0)
    forces = ForceSchedule([PivotForce(0.15, 0.2, 30.0, -20.0)])
    rec = simulated_recording(params, U, h, NoiseModel(), forces=forces)
    v = rec.truth_qd[:, :2]
    alpha = rec.truth_q[:, 2]
    e1 = np.column_stack([np.cos(alpha), np.sin(alpha)])  # platform axis 1'' in the ground frame
    e2 = np.column_stack([-np.sin(alpha), np.cos(alpha)])  # axis 2''
    k = np.arange(len(rec) - 2)
    inner = k[(k % block != 0) & (k > 0)]
    starts = k[k % block == 0]
    a_fd = np.full((len(rec), 2), np.nan)
    a_fd[inner] = (v[inner + 1] - v[inner - 1]) / (2 * h)
    a_fd[starts] = (-3 * v[starts] + 4 * v[starts + 1] - v[starts + 2]) / (2 * h)
    checked = np.concatenate([inner, starts])
    expect = np.column_stack([np.einsum("ij,ij->i", a_fd, e1), np.einsum("ij,ij->i", a_fd, e2)])[checked]
    assert np.abs(expect).max() > 0.3  # a real signal
    assert np.abs(rec.imu_accel[checked, :2] - expect).max() < 2e-5
    assert np.all(rec.imu_accel[:, 2] == GRAVITY)
    # with the old command the reading at a block start would be visibly different
    prev = (v[starts[1:]] - v[starts[1:] - 1]) / h
    assert np.abs(np.einsum("ij,ij->i", prev, e1[starts[1:]]) - rec.imu_accel[starts[1:], 0]).max() > 1e-2
    # gyro: the platform yaw rate, against a finite difference of alpha
    rate_fd = (alpha[inner + 1] - alpha[inner - 1]) / (2 * h)
    assert np.abs(rec.imu_gyro[inner, 2] - rate_fd).max() < 1e-5


def test_imu_reads_zero_horizontal_acceleration_on_the_stand(params):
    """On the stand the pivot does not move: only gravity and the platform's turn rate."""
    traj = simulate(params, np.tile([2.0, -1.0, 3.0], (30, 1)), 0.01, fixture="stand")
    s = measure(traj.x, traj.u, traj.f, params, NoiseModel(), fixture="stand")
    assert np.all(s.imu_accel[:, :2] == 0)
    assert np.allclose(s.imu_gyro[:, 2], traj.qd[:, 5]) and traj.qd[-1, 5] > 0.1


@pytest.mark.parametrize("counts", [1000, 4096])
def test_encoder_angles_quantize_to_whole_counts(counts):
    rng = np.random.default_rng(counts)
    x = np.zeros((500, 12))
    x[:, 3:6] = rng.uniform(-50, 50, size=(500, 3))
    x[:, 9:12] = rng.normal(size=(500, 3))
    x[0, 3:6] = [0.0, -1e-6, 2 * np.pi]  # at and just below a count edge
    from otbot_hw.params import nominal

    s = measure(x, np.zeros((500, 3)), np.zeros((500, 2)), nominal(), NoiseModel(counts_per_rev=counts))
    step = 2 * np.pi / counts
    n = s.joint_pos / step
    assert np.abs(n - np.round(n)).max() < 1e-6  # whole counts
    err = x[:, 3:6] - s.joint_pos
    assert err.min() >= -1e-9 and err.max() < step  # floor: never above the true angle, within one count
    assert np.round(n[0]).tolist() == [0.0, -1.0, float(counts)]
    assert np.array_equal(s.joint_vel, x[:, 9:12])  # rates are not quantized


def test_measure_in_blocks_gives_the_same_readings(monkeypatch):
    """``measure`` evaluates the sensor model in blocks of rows (Ctrl-C between them): bit for bit the
    readings of one block."""
    import otbot_hw.sensors as sensors
    from otbot_hw.params import nominal
    from otbot_hw.simulation.simulator import simulate

    rng = np.random.default_rng(5)
    traj = simulate(nominal(), rng.uniform(-8, 8, (101, 3)), 0.01)
    one = sensors.measure(traj.x, traj.u, traj.f, nominal(), sensors.NoiseModel.paper(), np.random.default_rng(1))
    monkeypatch.setattr(sensors, "MEASURE_BLOCK", 7)
    blocks = sensors.measure(traj.x, traj.u, traj.f, nominal(), sensors.NoiseModel.paper(), np.random.default_rng(1))
    for name in ("joint_pos", "joint_vel", "imu_accel", "imu_gyro"):
        assert np.array_equal(getattr(one, name), getattr(blocks, name)), name
