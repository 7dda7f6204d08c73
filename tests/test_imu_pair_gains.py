"""imu1 with its own (uncalibrated) scale and non-orthogonality: `gains=True` recovers R and the relative gains."""
import numpy as np
from scipy.stats import chi2

from selfcal.factors.imu import symmetric_gain
from selfcal.models import imu
from selfcal.core import so3
from selfcal.pipelines.imu_pair import calibrate_imu_pair
from selfcal.core.inertial import ImuNoise
from selfcal.sim.imu import ImuPairScenario
from selfcal.sim.trajectories import HandheldTrajectory

NOISE = ImuNoise(accelerometer_random_walk=0.0, gyroscope_random_walk=0.0)


def scenario(seed):
    rng = np.random.default_rng(seed)
    S_accel, S_gyro = 0.01 * rng.normal(size=6), 0.01 * rng.normal(size=6)  # 1 % class gain errors
    # imu1 reports G^-1 times the vector in its frame, so that v_imu0 = R G v_imu1_raw
    sc = ImuPairScenario.random(HandheldTrajectory(duration_s=60, seed=seed), seed=seed, intrinsics=False,
                                noise0=NOISE, noise1=NOISE, rate_hz=100,
                                accel1=imu.AccelIntrinsics(M=symmetric_gain(S_accel)),
                                gyro1=imu.GyroIntrinsics(M=symmetric_gain(S_gyro)))
    return sc, {"accel": symmetric_gain(S_accel), "gyro": symmetric_gain(S_gyro)}


def test_relative_gains_recovered_and_rotation_consistent():
    for seed in (0, 3):
        sc, truth = scenario(seed)
        rec = sc.perturbed_measurements(seed + 10)
        est = calibrate_imu_pair(rec, "imu0", "imu1", gains=True).estimate
        e = so3.log(sc.R_imu0_imu1.T @ est.R_imu0_imu1)
        # rotation error against its own covariance: chi2(3), 99.9 %
        assert e @ np.linalg.solve(est.rotation_cov_rad2, e) < chi2.ppf(0.999, 3)
        for name, G_true in truth.items():
            G, sigma = est.gains[name]
            z = (G - G_true)[np.triu_indices(3)] / sigma  # the 6 entries of S, each within 4 of its sigma
            assert np.all(np.abs(z) < 4), (name, z)


def test_ignoring_the_gains_is_visibly_worse():
    """Without the gain block the same data give a rotation off by many of its own sigmas (seed 0: ~0.2 deg)."""
    sc, _ = scenario(0)
    rec = sc.perturbed_measurements(10)
    est = calibrate_imu_pair(rec, "imu0", "imu1", gains=False).estimate
    e = so3.log(sc.R_imu0_imu1.T @ est.R_imu0_imu1)
    assert e @ np.linalg.solve(est.rotation_cov_rad2, e) > chi2.ppf(0.999, 3)
