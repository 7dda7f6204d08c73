"""Custom IMU factors: Jacobians at seeded random points, zero error on exact data, both code paths."""
import gtsam
import numpy as np
import pytest

from factor_checks import assert_factor_jacobians
from selfcal.core import inertial
from selfcal.factors import imu as fimu
from selfcal.models import imu
from selfcal.core import so3

G = 9.81
SEEDS = [1, 2, 3, 4]


def random_unit(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def random_accel(rng):
    M = imu.upper_triangular([1.01, 0.003, -0.002, 0.99, 0.004, 1.02]) + 0.01 * np.triu(rng.normal(size=(3, 3)))
    return imu.AccelIntrinsics(M=M, bias=0.1 * rng.normal(size=3))


def random_gyro(rng):
    return imu.GyroIntrinsics(M=np.eye(3) + 0.02 * rng.normal(size=(3, 3)), bias=0.01 * rng.normal(size=3),
                              A=1e-3 * rng.normal(size=(3, 3)))


def unit_noise(dim):
    return gtsam.noiseModel.Isotropic.Sigma(dim, 0.01)


@pytest.mark.parametrize("seed", SEEDS)
def test_static_accel_factor_jacobians_and_exact_zero(seed):
    rng = np.random.default_rng(seed)
    cal = random_accel(rng)
    up = random_unit(rng)
    a_raw = cal.raw_from_specific_force(G * up[None])[0]
    keys = fimu.AccelKeys(bias=2, M=3)
    factor = fimu.static_accel_factor(unit_noise(3), a_raw, G, 1, keys, imu.AccelIntrinsics())
    truth = {1: gtsam.Unit3(up), 2: cal.bias, 3: imu.upper_triangular_entries(cal.M)}
    assert np.max(np.abs(factor.unwhitenedError(_values(truth)))) < 1e-12
    perturbed = {1: gtsam.Unit3(random_unit(rng)), 2: rng.normal(size=3), 3: rng.normal(size=6)}
    assert_factor_jacobians(factor, perturbed)


@pytest.mark.parametrize("seed", SEEDS)
def test_static_gyro_factor_jacobians_and_exact_zero(seed):
    rng = np.random.default_rng(seed)
    cal = random_gyro(rng)
    up = random_unit(rng)
    w_raw = cal.raw_from_rate(np.zeros((1, 3)), G * up[None])[0]
    keys = fimu.GyroKeys(bias=2, A=3)
    factor = fimu.static_gyro_factor(unit_noise(3), w_raw, G, 1, keys, imu.GyroIntrinsics())
    truth = {1: gtsam.Unit3(up), 2: cal.bias, 3: cal.A.ravel()}
    assert np.max(np.abs(factor.unwhitenedError(_values(truth)))) < 1e-12
    assert_factor_jacobians(factor, {1: gtsam.Unit3(random_unit(rng)), 2: rng.normal(size=3),
                                     3: 0.01 * rng.normal(size=9)})


def _motion(rng, n=150, rate_hz=100.0):
    """A smooth rotation sampled at rate_hz; truth defined by the same zero-order-hold integration."""
    t = np.arange(n) / rate_hz
    w_S = np.stack([np.sin(2 * np.pi * t / t[-1] * k + rng.uniform(0, 6)) * rng.uniform(0.5, 2)
                    for k in (1, 2, 3)], axis=1)
    dt = np.full(n, 1.0 / rate_hz)
    return w_S, dt


@pytest.mark.parametrize("seed", SEEDS)
def test_gyro_motion_factor_jacobians_and_exact_zero(seed):
    rng = np.random.default_rng(seed)
    cal = random_gyro(rng)
    w_S, dt = _motion(rng)
    f_S = G * np.tile(random_unit(rng), (len(w_S), 1)) + rng.normal(size=w_S.shape)
    w_raw = cal.raw_from_rate(w_S, f_S)
    delta_R = so3.integrate_rates(w_S, dt)
    u_start = random_unit(rng)
    u_end = delta_R.T @ u_start
    keys = fimu.GyroKeys(bias=3, M=4, A=5)
    factor = fimu.gyro_motion_factor(unit_noise(3), w_raw, f_S, dt, 1, 2, keys, imu.GyroIntrinsics())
    truth = {1: gtsam.Unit3(u_start), 2: gtsam.Unit3(u_end), 3: cal.bias, 4: cal.M.ravel(), 5: cal.A.ravel()}
    assert np.max(np.abs(factor.unwhitenedError(_values(truth)))) < 1e-10
    perturbed = {1: gtsam.Unit3(random_unit(rng)), 2: gtsam.Unit3(random_unit(rng)),
                 3: 0.01 * rng.normal(size=3), 4: np.eye(3).ravel() + 0.02 * rng.normal(size=9),
                 5: 1e-3 * rng.normal(size=9)}
    assert_factor_jacobians(factor, perturbed, atol=1e-5)


def _random_rot3(rng):
    return gtsam.Rot3.Expmap(rng.normal(size=3))


@pytest.mark.parametrize("seed", SEEDS)
def test_static_pair_factor(seed):
    rng = np.random.default_rng(seed)
    R = _random_rot3(rng)
    d = 0.05 * rng.normal(size=3)
    v1 = G * random_unit(rng)
    v0 = R.matrix() @ v1 + d
    factor = fimu.static_pair_factor(unit_noise(3), v0, v1, 1, 2)
    assert np.max(np.abs(factor.unwhitenedError(_values({1: R, 2: d})))) < 1e-12
    assert_factor_jacobians(factor, {1: _random_rot3(rng), 2: rng.normal(size=3)})


@pytest.mark.parametrize("seed", SEEDS)
def test_dynamic_pair_factor(seed):
    """Exact data: imu1 sampled on its own clock, lever arm and relative bias; zero error at the truth."""
    rng = np.random.default_rng(seed)
    R = _random_rot3(rng)
    r_m = 0.1 * rng.normal(size=3)
    d = 0.05 * rng.normal(size=3)
    dt_true = 0.0123
    # imu1's signal must be linear between its samples for interpolation to be exact: use a piecewise-linear
    # specific force in imu0's frame and rates with zero lever-arm effect off the samples (w, w_dot constant).
    t1 = np.arange(0, 2.0, 0.01)
    f1_in_0 = np.cumsum(rng.normal(size=(len(t1), 3)), axis=0) * 0.1   # specific force at imu1, imu0 frame
    signal1 = fimu.Signal(t1, f1_in_0 @ R.matrix())                        # rows: R^T f
    t0 = np.sort(rng.uniform(0.2, 1.8, size=40))
    w0 = rng.normal(size=(40, 3))
    w_dot0 = rng.normal(size=(40, 3))
    f1_at = fimu.Signal(t1, f1_in_0).at(t0 - dt_true)[0]
    v0 = f1_at - np.einsum("nij,j->ni", inertial.lever_arm_jacobian(w0, w_dot0), r_m) + d
    factor = fimu.dynamic_pair_factor(unit_noise(3 * 40), t0, v0, signal1, 1, 2, 3, 4, w0, w_dot0)
    truth = {1: R, 2: np.array([dt_true]), 3: d, 4: r_m}
    assert np.max(np.abs(factor.unwhitenedError(_values(truth)))) < 1e-10
    assert_factor_jacobians(factor, {1: _random_rot3(rng), 2: np.array([0.0071]), 3: rng.normal(size=3),
                                     4: rng.normal(size=3)}, delta=1e-7, atol=1e-4)


def _values(variables):
    values = gtsam.Values()
    for key, value in variables.items():
        values.insert(key, value)
    return values


@pytest.mark.parametrize("seed", SEEDS)
def test_partial_blocks_and_channel_slopes(seed):
    """Subsets of M (scale only / misalignment only) and auxiliary-channel bias slopes: exact zero, Jacobians."""
    rng = np.random.default_rng(seed)
    acc, gyr = random_accel(rng), random_gyro(rng)
    slope_a, slope_g = 0.01 * rng.normal(size=3), 1e-3 * rng.normal(size=3)
    up = random_unit(rng)
    dev = float(rng.normal() * 5)
    a_raw = acc.raw_from_specific_force(G * up[None])[0] + slope_a * dev
    nominal = imu.AccelIntrinsics(M=acc.M.copy())
    free = (0, 3, 5)  # the diagonal: scale only, misalignment held at its nominal value
    keys = fimu.AccelKeys(bias=2, M=3, M_free=free, channels=(("temperature", 4),))
    factor = fimu.static_accel_factor(unit_noise(3), a_raw, G, 1, keys, nominal, {"temperature": dev})
    truth = {1: gtsam.Unit3(up), 2: acc.bias, 3: imu.upper_triangular_entries(acc.M)[list(free)], 4: slope_a}
    assert np.max(np.abs(factor.unwhitenedError(_values(truth)))) < 1e-12
    assert_factor_jacobians(factor, {1: gtsam.Unit3(random_unit(rng)), 2: rng.normal(size=3),
                                     3: 1 + 0.1 * rng.normal(size=3), 4: rng.normal(size=3)})

    w_raw = gyr.raw_from_rate(np.zeros((1, 3)), G * up[None])[0] + slope_g * dev
    gkeys = fimu.GyroKeys(bias=2, A=3, channels=(("supply", 4),))
    factor = fimu.static_gyro_factor(unit_noise(3), w_raw, G, 1, gkeys, imu.GyroIntrinsics(), {"supply": dev})
    assert np.max(np.abs(factor.unwhitenedError(_values({1: gtsam.Unit3(up), 2: gyr.bias, 3: gyr.A.ravel(),
                                                         4: slope_g})))) < 1e-12
    assert_factor_jacobians(factor, {1: gtsam.Unit3(random_unit(rng)), 2: rng.normal(size=3),
                                     3: 0.01 * rng.normal(size=9), 4: rng.normal(size=3)})

    w_S, dt = _motion(rng)
    f_S = G * np.tile(random_unit(rng), (len(w_S), 1))
    devs = np.linspace(-1, 1, len(w_S)) * 3
    w_raw = gyr.raw_from_rate(w_S, f_S) + np.outer(devs, slope_g)
    off_diagonal = (1, 2, 3, 5, 6, 7)
    mkeys = fimu.GyroKeys(bias=3, M=4, M_free=off_diagonal, channels=(("supply", 5),))
    nominal_g = imu.GyroIntrinsics(M=gyr.M.copy(), A=gyr.A.copy())
    factor = fimu.gyro_motion_factor(unit_noise(3), w_raw, f_S, dt, 1, 2, mkeys, nominal_g, {"supply": devs})
    u_start = random_unit(rng)
    u_end = so3.integrate_rates(w_S, dt).T @ u_start
    truth = {1: gtsam.Unit3(u_start), 2: gtsam.Unit3(u_end), 3: gyr.bias, 4: gyr.M.ravel()[list(off_diagonal)],
             5: slope_g}
    assert np.max(np.abs(factor.unwhitenedError(_values(truth)))) < 1e-10
    assert_factor_jacobians(factor, {1: gtsam.Unit3(random_unit(rng)), 2: gtsam.Unit3(random_unit(rng)),
                                     3: 0.01 * rng.normal(size=3), 4: 0.02 * rng.normal(size=6),
                                     5: 1e-3 * rng.normal(size=3)}, atol=1e-5)


@pytest.mark.parametrize("seed", SEEDS)
def test_pair_factors_with_relative_gain(seed):
    """imu1 with its own scale and non-orthogonality (symmetric gain): exact zero and Jacobians."""
    rng = np.random.default_rng(seed)
    R = _random_rot3(rng)
    s6 = 0.01 * rng.normal(size=6)
    G = fimu.symmetric_gain(s6)
    np.testing.assert_allclose(G, G.T)
    v1 = G_GRAVITY * random_unit(rng)
    v0 = R.matrix() @ G @ v1
    factor = fimu.static_pair_factor(unit_noise(3), v0, v1, 1, gain_key=2)
    assert np.max(np.abs(factor.unwhitenedError(_values({1: R, 2: s6})))) < 1e-12
    assert_factor_jacobians(factor, {1: _random_rot3(rng), 2: 0.05 * rng.normal(size=6)})
    t1 = np.arange(0, 2.0, 0.01)
    x1 = np.cumsum(rng.normal(size=(len(t1), 3)), axis=0)
    t0 = np.sort(rng.uniform(0.2, 1.8, size=30))
    factor = fimu.dynamic_pair_factor(unit_noise(90), t0, rng.normal(size=(30, 3)), fimu.Signal(t1, x1), 1, 2,
                                      gain_key=3)
    assert_factor_jacobians(factor, {1: _random_rot3(rng), 2: np.array([0.0043]), 3: 0.05 * rng.normal(size=6)},
                            delta=1e-7, atol=1e-4)


G_GRAVITY = 9.81


@pytest.mark.parametrize("seed", SEEDS)
def test_linear_bias_factor(seed):
    rng = np.random.default_rng(seed)
    b, k1, k2 = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    dev = {"temperature": float(rng.normal()), "time_s": float(rng.normal() * 100)}
    mean = b + k1 * dev["temperature"] + k2 * dev["time_s"]
    factor = fimu.linear_bias_factor(unit_noise(3), mean, 1, [("temperature", 2), ("time_s", 3)], dev)
    assert np.max(np.abs(factor.unwhitenedError(_values({1: b, 2: k1, 3: k2})))) < 1e-12
    assert_factor_jacobians(factor, {1: rng.normal(size=3), 2: rng.normal(size=3), 3: rng.normal(size=3)})


@pytest.mark.parametrize("seed", SEEDS)
def test_dynamic_pair_factor_offset_channels(seed):
    """The audit's generic terms: a relative offset varying as k phi(t); zero error at the truth, Jacobians."""
    rng = np.random.default_rng(seed)
    R = _random_rot3(rng)
    t1 = np.arange(0, 2.0, 0.01)
    x1 = np.cumsum(rng.normal(size=(len(t1), 3)), axis=0) * 0.1
    signal1 = fimu.Signal(t1, x1)
    t0 = np.sort(rng.uniform(0.2, 1.8, size=30))
    phi_a, phi_b = np.sin(3 * t0), t0**2 - 1
    k_a, k_b, d = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    v0 = signal1.at(t0)[0] @ R.matrix().T + d + np.outer(phi_a, k_a) + np.outer(phi_b, k_b)
    factor = fimu.dynamic_pair_factor(unit_noise(90), t0, v0, signal1, 1, offset_key=2,
                                      offset_channels=[(3, phi_a), (4, phi_b)])
    assert np.max(np.abs(factor.unwhitenedError(_values({1: R, 2: d, 3: k_a, 4: k_b})))) < 1e-10
    assert_factor_jacobians(factor, {1: _random_rot3(rng), 2: rng.normal(size=3), 3: rng.normal(size=3),
                                     4: rng.normal(size=3)})


@pytest.mark.parametrize("seed", SEEDS)
def test_pair_factors_with_axis_rotation(seed):
    """imu1's accelerometer triad rotated by a small rho relative to its gyro triad: ``v0 = R (I + S + [rho]x) v1``
    exactly (the model is first order in rho by definition); zero error at the truth and Jacobians, with the gain."""
    rng = np.random.default_rng(seed)
    R, s6, rho = _random_rot3(rng), 0.01 * rng.normal(size=6), 3e-3 * rng.normal(size=3)
    v1 = G_GRAVITY * random_unit(rng)
    v0 = R.matrix() @ (fimu.symmetric_gain(s6) + so3.hat(rho)) @ v1
    factor = fimu.static_pair_factor(unit_noise(3), v0, v1, 1, gain_key=2, axis_rotation_key=3)
    assert np.max(np.abs(factor.unwhitenedError(_values({1: R, 2: s6, 3: rho})))) < 1e-12
    t1 = np.arange(0, 2.0, 0.01)
    x1 = np.cumsum(rng.normal(size=(len(t1), 3)), axis=0)
    t0 = np.sort(rng.uniform(0.2, 1.8, size=30))
    factor = fimu.dynamic_pair_factor(unit_noise(90), t0, rng.normal(size=(30, 3)), fimu.Signal(t1, x1), 1, 2,
                                      gain_key=3, axis_rotation_key=4)
    assert_factor_jacobians(factor, {1: _random_rot3(rng), 2: np.array([0.0043]), 3: 0.05 * rng.normal(size=6),
                                     4: 0.01 * rng.normal(size=3)}, delta=1e-7, atol=1e-4)
