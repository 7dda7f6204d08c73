"""Ship tilt factor (lever arm, speed-log scale): Jacobians, exact data, and estimates as good as their sigma."""
import gtsam
import numpy as np
import pytest

from selfcal.core import inertial
from selfcal.factors.ship import tilt_factor
from selfcal.models import ship
from factor_checks import assert_factor_jacobians

R, L, K = gtsam.symbol("r", 0), gtsam.symbol("l", 0), gtsam.symbol("k", 0)
G = 9.80665


def random_case(rng):
    R_W_S = gtsam.Rot3.Expmap(rng.normal(0, 0.2, 3))
    w, w_dot = rng.normal(0, 0.1, 3), rng.normal(0, 0.1, 3)
    return R_W_S, inertial.lever_arm_jacobian(w, w_dot), rng.normal(0, 0.3, 3), rng.normal(0, 3, 3), rng.normal(0, 0.1, 1)


@pytest.mark.parametrize("seed", range(4))
def test_jacobians_at_random_points(seed):
    rng = np.random.default_rng(seed)
    R_W_S, A, a_known, r, k = random_case(rng)
    f = rng.normal(0, 0.5, 3) + np.array([0.0, 0.0, G])  # not consistent with R: a non-zero residual
    factor = tilt_factor(gtsam.noiseModel.Isotropic.Sigma(2, 0.01), R, f, A, a_known, L, K)
    assert_factor_jacobians(factor, {R: R_W_S, L: r, K: k}, atol=1e-5)


@pytest.mark.parametrize("seed", range(3))
def test_zero_error_on_exact_data(seed):
    rng = np.random.default_rng(seed + 10)
    R_W_S, A, a_known, r, k = random_case(rng)
    f_centre = R_W_S.matrix().T @ np.array([0.0, 0.0, G])
    f_measured = f_centre + A @ r + (1 + k[0]) * a_known  # lever arm and the hull's (scaled) acceleration
    factor = tilt_factor(gtsam.noiseModel.Isotropic.Sigma(2, 0.01), R, f_measured, A, a_known, L, K)
    values = gtsam.Values()
    values.insert(R, R_W_S)
    values.insert(L, r)
    values.insert(K, k)
    np.testing.assert_allclose(factor.unwhitenedError(values), 0.0, atol=1e-12)
    # without a lever-arm key the known lever arm is used: the same measurement
    known = tilt_factor(gtsam.noiseModel.Isotropic.Sigma(2, 0.01), R, f_measured, A, a_known, None, K,
                        lever_arm_m=r)
    np.testing.assert_allclose(known.unwhitenedError(values), 0.0, atol=1e-12)


def test_lever_arm_estimates_scatter_as_their_sigma():
    """Monte Carlo: 40 keyframes of known attitude with white tilt noise; the lever arm's error over 150 runs
    must give a mean NEES within the chi-square(3 x 150) 99.9 % band divided by 150 (the Cramér–Rao bound of
    this linear-Gaussian problem is the reported covariance)."""
    rng = np.random.default_rng(7)
    sigma, n_frames, runs = 0.002, 40, 150
    truth_r = np.array([2.0, 0.5, 5.0])
    frames = []
    for _ in range(n_frames):
        R_W_S = gtsam.Rot3.Ypr(rng.uniform(-np.pi, np.pi), rng.normal(0, 0.05), rng.normal(0, 0.1))
        A = inertial.lever_arm_jacobian(rng.normal(0, 0.1, 3), rng.normal(0, 0.1, 3))
        frames.append((R_W_S, A))
    nees = []
    for _ in range(runs):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for j, (R_W_S, A) in enumerate(frames):
            u = R_W_S.matrix().T @ np.array([0.0, 0.0, 1.0])
            u_noisy = gtsam.Rot3.Expmap(np.append(rng.normal(0, sigma, 2), 0.0)).matrix().T @ np.array([0, 0, 1.0])
            f = G * (R_W_S.matrix().T @ u_noisy) + A @ truth_r  # tilt noise in the world's horizontal plane
            graph.add(tilt_factor(gtsam.noiseModel.Isotropic.Sigma(2, sigma), gtsam.symbol("r", j), f, A, np.zeros(3), L))
            graph.add(gtsam.PriorFactorRot3(gtsam.symbol("r", j), R_W_S, gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
            values.insert(gtsam.symbol("r", j), R_W_S)
        values.insert(L, np.zeros(3))
        result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        cov = gtsam.Marginals(graph, result).marginalCovariance(L)
        e = result.atVector(L) - truth_r
        nees.append(e @ np.linalg.solve(cov, e))
    from scipy import stats
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], 3 * runs) / runs
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)


V = gtsam.symbol("v", 0)


@pytest.mark.parametrize("seed", range(4))
def test_unknown_speed_jacobians_and_exact_data(seed):
    """Without a speed source the factor takes the speed (m/s) as a key and the acceleration per unit speed,
    ``(0, yaw rate, 0)``: Jacobians at a random point, and zero error where the force carries ``v x yaw rate``."""
    rng = np.random.default_rng(seed + 20)
    R_W_S, A, _, r, _ = random_case(rng)
    yaw_rate, speed = rng.normal(0, 0.05), rng.uniform(3.0, 15.0, 1)
    per_speed = ship.known_acceleration_S(1.0, 0.0, yaw_rate)
    noise = gtsam.noiseModel.Isotropic.Sigma(2, 0.01)
    f = rng.normal(0, 0.5, 3) + np.array([0.0, 0.0, G])
    assert_factor_jacobians(tilt_factor(noise, R, f, A, per_speed, L, speed_key=V), {R: R_W_S, L: r, V: speed},
                            atol=1e-5)
    f_exact = R_W_S.matrix().T @ np.array([0.0, 0.0, G]) + A @ r + speed[0] * per_speed
    values = gtsam.Values()
    values.insert(R, R_W_S)
    values.insert(L, r)
    values.insert(V, speed)
    factor = tilt_factor(noise, R, f_exact, A, per_speed, L, speed_key=V)
    np.testing.assert_allclose(factor.unwhitenedError(values), 0.0, atol=1e-12)
    with pytest.raises(ValueError):
        tilt_factor(noise, R, f_exact, A, per_speed, L, K, speed_key=V)


def test_unknown_speed_estimates_scatter_as_their_sigma():
    """Monte Carlo: a turn seen by 50 keyframes of known attitude (yaw rates 1-4 deg/s, white tilt noise); the
    speed's error over 200 runs must give a mean NEES within the chi-square(200) 99.9 % band divided by 200 (the
    reported variance is this linear-Gaussian problem's Cramér–Rao bound, ``g^2 sigma^2 / sum(w^2)`` to first
    order), and the empirical spread must match that closed form within the same band."""
    from scipy import stats
    rng = np.random.default_rng(11)
    sigma, n_frames, runs, truth_v = 0.002, 50, 200, 9.3
    frames = [(gtsam.Rot3.Ypr(rng.uniform(-np.pi, np.pi), rng.normal(0, 0.02), rng.normal(0, 0.05)),
               np.radians(rng.uniform(1.0, 4.0)) * rng.choice([-1.0, 1.0])) for _ in range(n_frames)]
    nees, errors = [], []
    for _ in range(runs):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for j, (R_W_S, yaw_rate) in enumerate(frames):
            per_speed = ship.known_acceleration_S(1.0, 0.0, yaw_rate)
            u_noisy = gtsam.Rot3.Expmap(np.append(rng.normal(0, sigma, 2), 0.0)).matrix().T @ np.array([0, 0, 1.0])
            f = G * (R_W_S.matrix().T @ u_noisy) + truth_v * per_speed
            key = gtsam.symbol("r", j)
            graph.add(tilt_factor(gtsam.noiseModel.Isotropic.Sigma(2, sigma), key, f, np.zeros((3, 3)), per_speed,
                                  speed_key=V))
            graph.add(gtsam.PriorFactorRot3(key, R_W_S, gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
            values.insert(key, R_W_S)
        values.insert(V, np.array([0.0]))
        result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        variance = gtsam.Marginals(graph, result).marginalCovariance(V)[0, 0]
        e = result.atVector(V)[0] - truth_v
        nees.append(e**2 / variance)
        errors.append(e)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], runs) / runs
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)
    crb = G**2 * sigma**2 / sum(w**2 for _, w in frames)
    assert lo < np.mean(np.square(errors)) / crb < hi, (np.mean(np.square(errors)), crb)
