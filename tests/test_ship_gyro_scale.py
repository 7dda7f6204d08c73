"""Gyro scale error in the ship graph: the preintegration model against exact integration, the factor against
GTSAM's AHRSFactor and its own numerical Jacobians, the graph option, and estimates as good as their sigma."""
from pathlib import Path

import gtsam
import numpy as np
import pytest
from scipy import stats

from factor_checks import assert_factor_jacobians, make_values
from selfcal.factors.ship import gyro_scale_rotation_factor
from selfcal.graphs.ship import (B_KEY, GYRO_SCALE_KEY, R_KEY, Keyframe, ShipGraph, ShipGraphOptions)
from selfcal.models import ship
from selfcal.core import so3
from selfcal.sim.ship import ShipScenario
from shared_data import SHARED_DATA

RI, RJ, B, S = gtsam.symbol("r", 0), gtsam.symbol("r", 1), gtsam.symbol("b", 0), gtsam.symbol("s", 0)
G = 9.80665
E_Z = np.array([0.0, 0.0, 1.0])


def exact_rotation(gyro_raw, dt, bias, scale):
    """body(start) <- body(end) from raw samples, every sample corrected exactly: w = (w_raw - b) / (1 + s)."""
    return so3.integrate_rates((gyro_raw - bias) / (1.0 + scale), dt)


def random_samples(rng, n=25, rate_rad_s=0.3):
    """A keyframe's worth of multi-axis rates (a hull rolling, pitching and turning), jittered sample times."""
    return rng.normal(0.0, rate_rad_s, (n, 3)), 0.02 + rng.uniform(-0.002, 0.002, n)


def pim_noise(gyro, dt, bias_hat, density=1e-3):
    params = gtsam.PreintegratedRotationParams()
    params.setGyroscopeCovariance(density**2 * np.eye(3))
    pim = gtsam.PreintegratedAhrsMeasurements(params, bias_hat)
    for w, d in zip(gyro, dt):
        pim.integrateMeasurement(w, float(d))
    return pim, gtsam.noiseModel.Gaussian.Covariance(pim.preintMeasCov())


# --- model ------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(3))
def test_jacobians_are_the_derivatives_of_exact_integration(seed):
    """J_bias and J_correction against central differences of the exact product of Exp's (h = 1e-6: truncation
    h^2 |d3| ~ 1e-12, rounding 1e-16 / h = 1e-10)."""
    rng = np.random.default_rng(seed)
    gyro, dt = random_samples(rng)
    b_hat = rng.normal(0.0, 0.02, 3)
    delta_R, J_b, J_c = ship.scaled_gyro_preintegration(gyro, dt, b_hat)
    np.testing.assert_allclose(delta_R, exact_rotation(gyro, dt, b_hat, 0.0), atol=1e-14)
    h = 1e-6
    for i in range(3):
        step = h * np.eye(3)[i]
        d_b = so3.log(delta_R.T @ exact_rotation(gyro, dt, b_hat + step, 0.0)) - so3.log(
            delta_R.T @ exact_rotation(gyro, dt, b_hat - step, 0.0))
        # correction c: w = (1 - c)(w_raw - b), i.e. the exact scale s = c / (1 - c)
        d_c = so3.log(delta_R.T @ exact_rotation(gyro, dt, b_hat, step / (1 - step))) - so3.log(
            delta_R.T @ exact_rotation(gyro, dt, b_hat, -step / (1 + step)))
        np.testing.assert_allclose(d_b / (2 * h), J_b[:, i], atol=1e-8)
        np.testing.assert_allclose(d_c / (2 * h), J_c[:, i], atol=1e-8)


def test_first_order_remainder_is_second_order_and_one_axis_rotation_is_exact():
    rng = np.random.default_rng(5)
    gyro, dt = random_samples(rng)
    scale = np.array([0.03, -0.02, 0.05])

    def remainder(s):
        delta_R, _, J_c = ship.scaled_gyro_preintegration(gyro, dt, np.zeros(3))
        c, _ = ship.gyro_scale_correction(s)
        return np.linalg.norm(so3.log((delta_R @ so3.exp(J_c @ c)).T @ exact_rotation(gyro, dt, 0.0, s)))

    first_order = np.linalg.norm(ship.scaled_gyro_preintegration(gyro, dt, np.zeros(3))[2]
                                 @ ship.gyro_scale_correction(scale)[0])
    # Taylor: the remainder quarters when s halves, and is far below the first-order term it leaves out
    assert 3.5 < remainder(scale) / remainder(scale / 2) < 4.5
    assert remainder(scale) < 0.05 * first_order
    # a turn about z alone (720 deg, 7 % scale: the MPU-6050 log's figures): the Exp's commute, exact in c
    turn = np.column_stack([np.zeros(200), np.zeros(200), np.full(200, 4 * np.pi / 20.0)])
    steps = np.full(200, 0.1)
    delta_R, _, J_c = ship.scaled_gyro_preintegration(turn * 1.07, steps, np.zeros(3))
    c, _ = ship.gyro_scale_correction(np.array([0.0, 0.0, 0.07]))
    np.testing.assert_allclose(delta_R @ so3.exp(J_c @ c), exact_rotation(turn * 1.07, steps, 0.0, 0.07), atol=1e-12)


# --- factor -----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(4))
def test_factor_is_the_ahrs_factor_at_zero_scale(seed):
    rng = np.random.default_rng(seed + 20)
    gyro, dt = random_samples(rng)
    b_hat = rng.normal(0.0, 0.02, 3)
    pim, noise = pim_noise(gyro, dt, b_hat)
    ahrs = gtsam.AHRSFactor(RI, RJ, B, pim)
    factor = gyro_scale_rotation_factor(noise, RI, RJ, B, S, gyro, dt, b_hat)
    values = make_values({RI: gtsam.Rot3.Expmap(rng.normal(0, 1, 3)), RJ: gtsam.Rot3.Expmap(rng.normal(0, 1, 3)),
                          B: b_hat + rng.normal(0.0, 0.01, 3), S: np.zeros(3)})
    np.testing.assert_allclose(factor.unwhitenedError(values), ahrs.unwhitenedError(values), atol=1e-12)
    np.testing.assert_allclose(factor.error(values), ahrs.error(values), rtol=1e-9)
    # the same linearisation on the attitudes and the bias (whitened: sigmas of 1e-4 rad scale rounding up)
    A_ahrs, b_ahrs = ahrs.linearize(values).jacobian()
    A_mine, b_mine = factor.linearize(values).jacobian()
    np.testing.assert_allclose(A_mine[:, :9], A_ahrs, atol=1e-9 * np.abs(A_ahrs).max())
    np.testing.assert_allclose(b_mine, b_ahrs, atol=1e-9 * np.abs(b_ahrs).max())


@pytest.mark.parametrize("seed", range(4))
def test_jacobians_at_random_points(seed):
    rng = np.random.default_rng(seed)
    gyro, dt = random_samples(rng)
    b_hat = rng.normal(0.0, 0.02, 3)
    factor = gyro_scale_rotation_factor(gtsam.noiseModel.Isotropic.Sigma(3, 0.01), RI, RJ, B, S, gyro, dt, b_hat)
    assert_factor_jacobians(factor, {RI: gtsam.Rot3.Expmap(rng.normal(0, 1, 3)),
                                     RJ: gtsam.Rot3.Expmap(rng.normal(0, 1, 3)),
                                     B: b_hat + rng.normal(0.0, 0.01, 3), S: rng.normal(0.0, 0.05, 3)}, atol=1e-5)


@pytest.mark.parametrize("seed", range(3))
def test_zero_error_on_exact_data(seed):
    """True rates about one body axis per keyframe (the first-order model is exact there) read by a gyro with a
    scale error and a bias; and, at scale 0, any motion."""
    rng = np.random.default_rng(seed + 30)
    R_i = gtsam.Rot3.Expmap(rng.normal(0, 1, 3))
    bias, scale = rng.normal(0.0, 0.02, 3), rng.normal(0.0, 0.05, 3)
    axis = rng.normal(size=3)
    axis[rng.integers(3)] *= 50.0
    axis = np.eye(3)[np.argmax(np.abs(axis))]  # one body axis
    dt = np.full(40, 0.01)
    w_true = np.outer(np.sin(np.linspace(0, 3, 40)) + 0.5, axis)  # a rate that varies, about that axis
    for w, s in ((w_true, scale), (random_samples(rng, 40)[0], np.zeros(3))):
        gyro = (1.0 + s) * w + bias
        R_j = R_i.compose(gtsam.Rot3(so3.integrate_rates(w, dt)))
        factor = gyro_scale_rotation_factor(gtsam.noiseModel.Isotropic.Sigma(3, 1e-4), RI, RJ, B, S, gyro, dt, bias)
        values = make_values({RI: R_i, RJ: R_j, B: bias, S: s})
        np.testing.assert_allclose(factor.unwhitenedError(values), 0.0, atol=1e-12)


# --- graph ------------------------------------------------------------------------------------------------------

def keyframes(seed, scale, sigma_tilt_rad, keyframe_s=0.5, duration_s=60.0, rate_hz=100.0, exact=False):
    """A short heave voyage (ShipScenario) with a gyro scale error and a constant bias; the tilt measured at each
    keyframe is the true up with white noise of ``sigma_tilt_rad`` per horizontal world axis (exactly the tilt
    factor's model), so every noise model in the graph is the true one.  Returns the keyframes, the gyro noise
    density, the scenario and the keyframes' true attitudes."""
    sc = ShipScenario("heave", duration_s=duration_s, rate_hz=rate_hz, seed=seed, lever_arm_m=(0.0, 0.0, 0.0),
                      gyro_bias_walk_deg_h_sqrt_h=0.0, gyro_scale=scale)
    data = (sc.exact_measurements() if exact else sc.perturbed_measurements(1000 + seed)).imu("imu0")
    t = data.t_s
    index = np.arange(0, len(t), int(round(keyframe_s * rate_hz)))
    R_W_S = sc.motion.R_W_S(t[index])
    rng = np.random.default_rng(2000 + seed)
    frames, previous = [], None
    for R, i in zip(R_W_S, index):
        up_W = so3.exp(np.append(rng.normal(0.0, sigma_tilt_rad, 2), 0.0)).T @ E_Z
        span = slice(previous, i) if previous is not None else slice(0, 0)
        frames.append(Keyframe(t_s=float(t[i]), gyro_rad_s=data.gyro_rad_s[span], dt_s=np.diff(t)[span],
                               accel_m_s2=G * R.T @ up_W, A_S=np.zeros((3, 3)), a_known_S=np.zeros(3),
                               has_speed=False, tilt_sigma_rad=sigma_tilt_rad))
        previous = i
    return frames, sc.noise.gyroscope_noise_density, sc, R_W_S


def build(frames, density, **options):
    options = ShipGraphOptions(**{"keyframe_s": 0.5, "bias_segment_s": 1e9, "estimate_lever_arm": False,
                                  "remove_known_acceleration": False, **options})
    builder = ShipGraph(options, G, density, 1e-6)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for frame in frames:
        g, v = builder.add(frame, values if builder.k >= 0 else None, propagate=False)
        graph.push_back(g)
        values.insert(v)
    return graph, values


def test_graph_option_off_is_the_ahrs_graph_and_on_agrees_at_zero_scale():
    frames, density, _, _ = keyframes(1, (0.0, 0.0, 0.0), 0.002, duration_s=10.0)
    plain, values = build(frames, density)
    kinds = {type(plain.at(i)).__name__ for i in range(plain.size())}
    assert "AHRSFactor" in kinds and not values.exists(GYRO_SCALE_KEY)
    scaled, scaled_values = build(frames, density, estimate_gyro_scale=True)
    assert "AHRSFactor" not in {type(scaled.at(i)).__name__ for i in range(scaled.size())}
    np.testing.assert_allclose(scaled_values.atVector(GYRO_SCALE_KEY), 0.0)
    # one more factor (the scale's prior), and at scale 0 the same error as the AHRSFactor graph
    assert scaled.size() == plain.size() + 1
    np.testing.assert_allclose(scaled.error(scaled_values), plain.error(values), rtol=1e-9)


def test_known_scale_option_corrects_the_samples():
    """A known scale (held, not estimated: the audit's held-out half) divides the raw rates.  Noise-free samples
    of a gyro reading 5 % high: at the true attitudes (and the bias in true-rate units, b / 1.05) the AHRS
    factors are then left with the zero-order hold's discretisation only, instead of 5 % of the waves."""
    truth = np.array([0.05, 0.05, 0.05])
    frames, density, sc, R_W_S = keyframes(2, truth, 0.002, duration_s=20.0, exact=True)

    def ahrs_error(**options):
        graph, _ = build(frames, density, **options)
        values = gtsam.Values()
        for k, R in enumerate(R_W_S):
            values.insert(R_KEY(k), gtsam.Rot3(R))
        values.insert(B_KEY(0), sc.gyro_bias0_rad_s / (1.0 + truth))
        return sum(graph.at(i).error(values) for i in range(graph.size())
                   if type(graph.at(i)).__name__ == "AHRSFactor")

    assert ahrs_error(gyro_scale=tuple(truth)) < 0.01 * ahrs_error()


def test_gyro_scale_estimates_scatter_as_their_sigma():
    """Monte Carlo: 20 forty-second heave voyages (roll and pitch of degrees at 5-20 s), a gyro reading 2 % high
    on x, 1.5 % low on y, 1 % high on z; tilt noise 2 mrad per keyframe, every noise model the true one.

    x and y: the waves determine them, and the graph is nearly linear-Gaussian, so the reported covariance is
    the Cramér–Rao bound: the NEES of (x, y) (2 dof) over the runs must have a mean inside the chi-square(2 x 20)
    99.9 % band / 20.  z: seen only through the waves' small heading swings, i.e. hardly at all, so its sigma
    stays near the 0.1 prior (its NEES is the prior's pull, not a chi-square, and is left out)."""
    truth = np.array([0.02, -0.015, 0.01])
    runs = 20
    nees, sigmas = [], []
    for run in range(runs):
        frames, density, _, _ = keyframes(100 + run, truth, 0.002, duration_s=40.0)
        graph, values = build(frames, density, estimate_gyro_scale=True)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        cov = gtsam.Marginals(graph, result).marginalCovariance(GYRO_SCALE_KEY)
        error = (result.atVector(GYRO_SCALE_KEY) - truth)[:2]
        nees.append(error @ np.linalg.solve(cov[:2, :2], error))
        sigmas.append(np.sqrt(np.diag(cov)))
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], 2 * runs) / runs
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)
    sigma = np.median(sigmas, axis=0)
    assert np.all(sigma[:2] < 0.02) and sigma[2] > 0.8 * ShipGraphOptions().gyro_scale_prior_sigma, sigma


# --- real data --------------------------------------------------------------------------------------------------

SUNSIDED = SHARED_DATA / "sunsided_mpu6050_hmc5883l_marg"
TURNS = {"rotate-ccw-around-x-pointing-forward": 0, "rotate-ccw-around-y-pointing-left": 1,
         "rotate-ccw-around-z-pointing-up": 2}


def magnetometer_scale(folder: Path, axis: int) -> tuple[float, float]:
    """The gyro's scale on ``axis`` against the HMC5883L logged with it (the independent heading reference of two
    hand-made turns): ``int w dt = (1 + s) theta_mag + b t + c`` by least squares, theta_mag the field's angle in
    the plane of the turn after a circle fit (hard iron).  Its sigma: the fit's residual (soft iron and tilt,
    periodic with the turn) spread over the total angle, ``rms / |theta_total|``."""
    mag = np.loadtxt(folder / "hmc5883l.csv.gz", delimiter=",", skiprows=1)
    imu = np.loadtxt(folder / "mpu6050.csv.gz", delimiter=",", skiprows=1)
    x, y = (mag[:, 1 + i] for i in range(3) if i != axis)
    centre = np.linalg.lstsq(np.column_stack([2 * x, 2 * y, np.ones_like(x)]), x**2 + y**2, rcond=None)[0]
    theta_mag = np.unwrap(np.arctan2(y - centre[1], x - centre[0]))
    w = np.radians(imu[:, 4 + axis])
    theta_gyro = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(imu[:, 0]))])
    inside = (mag[:, 0] >= imu[0, 0]) & (mag[:, 0] <= imu[-1, 0])
    t, theta = mag[inside, 0], theta_mag[inside]
    X = np.column_stack([theta, t - t[0], np.ones_like(t)])
    coef, *_ = np.linalg.lstsq(X, np.interp(t, imu[:, 0], theta_gyro), rcond=None)
    rms = np.std(np.interp(t, imu[:, 0], theta_gyro) - X @ coef)
    return abs(coef[0]) - 1.0, rms / abs(theta[-1] - theta[0])  # |slope|: the field turns against the board


@pytest.mark.skipif(not SUNSIDED.is_dir(), reason=f"{SUNSIDED} not present")
@pytest.mark.parametrize("log", sorted(TURNS))
def test_real_turns_scale_agrees_with_the_magnetometer(log):
    """MPU-6050, two hand-made turns about one axis (sunsided, EUPL: read in place).  The graph's scale on that
    axis (gyro + accelerometer only, with the lever arm of a hand-held board) against the magnetometer's, within
    3 combined sigmas.  x and y turns carry gravity round the board: the accelerometer sizes them to about 1 %;
    about z it sees the scale only through the board's small tilt while turning."""
    from selfcal.audit.ship import ShipAudit
    from selfcal.io.importers import import_sunsided_mpu6050
    from selfcal.pipelines.ship import ship_inputs
    axis = TURNS[log]
    audit = ShipAudit(ship_inputs(import_sunsided_mpu6050(SUNSIDED / log)))
    candidates = {c.effect: c for c in audit.candidates()}
    effects = (candidates["lever_arm"], candidates["gyro_scale"])
    fit = audit.fit(effects)
    estimate, std = audit.estimate(fit, candidates["gyro_scale"])
    scale, sigma = estimate["scale"][axis], std["scale"][axis]
    reference, reference_sigma = magnetometer_scale(SUNSIDED / log, axis)
    assert abs(scale - reference) < 3 * np.hypot(sigma, reference_sigma), (scale, sigma, reference, reference_sigma)
    assert sigma < 0.05  # the data, not the 0.1 prior, size the scale on the axis turned about
