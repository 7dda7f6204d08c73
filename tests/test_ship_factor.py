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
    """(R, A, (surge m/s^2, v w_S), r, k): a hull at 3-15 m/s turning and rolling at random."""
    R_W_S = gtsam.Rot3.Expmap(rng.normal(0, 0.2, 3))
    w, w_dot = rng.normal(0, 0.1, 3), rng.normal(0, 0.1, 3)
    hull = (rng.normal(0, 0.3), rng.uniform(3.0, 15.0) * w)
    return R_W_S, inertial.lever_arm_jacobian(w, w_dot), hull, rng.normal(0, 3, 3), rng.normal(0, 0.1, 1)


def smoothed_hull(rng, a_known):
    """The scale's regressor: the hull acceleration's (surge, v w_S) as a smoothing would leave them."""
    return a_known[0] + rng.normal(0, 0.05), a_known[1] + rng.normal(0, 0.02, 3)


@pytest.mark.parametrize("smoothed", [False, True])
@pytest.mark.parametrize("along_track_ratio", [0.0, 3.0])
@pytest.mark.parametrize("seed", range(4))
def test_jacobians_at_random_points(seed, along_track_ratio, smoothed):
    rng = np.random.default_rng(seed)
    R_W_S, A, a_known, r, k = random_case(rng)
    f = rng.normal(0, 0.5, 3) + np.array([0.0, 0.0, G])  # not consistent with R: a non-zero residual
    factor = tilt_factor(gtsam.noiseModel.Isotropic.Sigma(2, 0.01), R, f, A, *a_known, L, K,
                         along_track_ratio=along_track_ratio,
                         scale_regressor=smoothed_hull(rng, a_known) if smoothed else None)
    assert_factor_jacobians(factor, {R: R_W_S, L: r, K: k}, atol=1e-5)


@pytest.mark.parametrize("smoothed", [False, True])
@pytest.mark.parametrize("seed", range(3))
def test_zero_error_on_exact_data(seed, smoothed):
    """The force of the hull's acceleration plus k times the regressor's (the regressor's own acceleration when
    none is given)."""
    rng = np.random.default_rng(seed + 10)
    R_W_S, A, a_known, r, k = random_case(rng)
    regressor = smoothed_hull(rng, a_known) if smoothed else a_known
    f_centre = R_W_S.matrix().T @ np.array([0.0, 0.0, G])
    a_W = ship.hull_acceleration_W(R_W_S.matrix(), *a_known)[0]
    a_k = ship.hull_acceleration_W(R_W_S.matrix(), *regressor)[0]
    f_measured = f_centre + A @ r + R_W_S.matrix().T @ (a_W + k[0] * a_k)  # lever arm, the hull's (scaled) acceleration
    factor = tilt_factor(gtsam.noiseModel.Isotropic.Sigma(2, 0.01), R, f_measured, A, *a_known, L, K,
                         scale_regressor=regressor if smoothed else None)
    values = gtsam.Values()
    values.insert(R, R_W_S)
    values.insert(L, r)
    values.insert(K, k)
    np.testing.assert_allclose(factor.unwhitenedError(values), 0.0, atol=1e-12)
    if smoothed:
        return
    # without a lever-arm key the known lever arm is used: the same measurement
    known = tilt_factor(gtsam.noiseModel.Isotropic.Sigma(2, 0.01), R, f_measured, A, *a_known, None, K,
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
            graph.add(tilt_factor(gtsam.noiseModel.Isotropic.Sigma(2, sigma), gtsam.symbol("r", j), f, A, 0.0,
                                  np.zeros(3), L))
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


def test_along_track_weighting_gives_estimates_as_good_as_their_sigma():
    """Monte Carlo: the speed log's rate errs along the heading only (sigma_a = 4 sigma), so each keyframe's tilt
    error is sigma across the track and sqrt(sigma^2 + sigma_a^2) along it.  Weighed down along the heading
    (``along_track_ratio``), the lever arm's error over 150 runs gives a mean NEES within the chi-square(3 x 150)
    99.9 % band divided by 150 (the reported covariance is this linear-Gaussian problem's Cramer-Rao bound), and
    a mean squared error below the isotropic fit's (sigma_a in both axes: the old tilt sigma) by at least a
    third: the cross-track axis keeps its precision."""
    from scipy import stats
    rng = np.random.default_rng(17)
    sigma, ratio, n_frames, runs = 0.002, 4.0, 40, 150
    truth_r = np.array([2.0, 0.5, 5.0])
    frames = []
    for _ in range(n_frames):
        R_W_S = gtsam.Rot3.Ypr(rng.uniform(-np.pi, np.pi), rng.normal(0, 0.05), rng.normal(0, 0.1))
        frames.append((R_W_S, inertial.lever_arm_jacobian(rng.normal(0, 0.1, 3), rng.normal(0, 0.1, 3))))
    nees, squared = [], {True: [], False: []}
    for _ in range(runs):
        noisy = []
        for R_W_S, A in frames:
            psi = R_W_S.yaw()
            h, h_perp = np.array([np.cos(psi), np.sin(psi)]), np.array([-np.sin(psi), np.cos(psi)])
            tilt = (h * rng.normal(0, sigma * np.sqrt(1 + ratio**2)) + h_perp * rng.normal(0, sigma))
            up = np.array([tilt[0], tilt[1], np.sqrt(1.0 - tilt @ tilt)])
            noisy.append(G * R_W_S.matrix().T @ up + A @ truth_r)
        for weighted in (True, False):
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            for j, ((R_W_S, A), f) in enumerate(zip(frames, noisy)):
                key = gtsam.symbol("r", j)
                noise = gtsam.noiseModel.Isotropic.Sigma(2, sigma if weighted else sigma * np.sqrt(1 + ratio**2))
                graph.add(tilt_factor(noise, key, f, A, 0.0, np.zeros(3), L,
                                      along_track_ratio=ratio if weighted else 0.0))
                graph.add(gtsam.PriorFactorRot3(key, R_W_S, gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
                values.insert(key, R_W_S)
            values.insert(L, np.zeros(3))
            result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
            e = result.atVector(L) - truth_r
            squared[weighted].append(e @ e)
            if weighted:
                cov = gtsam.Marginals(graph, result).marginalCovariance(L)
                nees.append(e @ np.linalg.solve(cov, e))
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], 3 * runs) / runs
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)
    assert np.mean(squared[True]) < 2.0 / 3.0 * np.mean(squared[False]), (np.mean(squared[True]),
                                                                          np.mean(squared[False]))


V = gtsam.symbol("v", 0)


@pytest.mark.parametrize("seed", range(4))
def test_unknown_speed_jacobians_and_exact_data(seed):
    """Without a speed source the factor takes the speed (m/s) as a key and the acceleration per unit speed,
    (no surge, the body rate): Jacobians at a random point, and zero error where the force carries ``v psi_dot``."""
    rng = np.random.default_rng(seed + 20)
    R_W_S, A, _, r, _ = random_case(rng)
    w_S, speed = rng.normal(0, 0.05, 3), rng.uniform(3.0, 15.0, 1)
    per_speed = (0.0, w_S)
    noise = gtsam.noiseModel.Isotropic.Sigma(2, 0.01)
    f = rng.normal(0, 0.5, 3) + np.array([0.0, 0.0, G])
    assert_factor_jacobians(tilt_factor(noise, R, f, A, *per_speed, L, speed_key=V), {R: R_W_S, L: r, V: speed},
                            atol=1e-5)
    a_W = ship.hull_acceleration_W(R_W_S.matrix(), 0.0, speed[0] * w_S)[0]
    f_exact = R_W_S.matrix().T @ (np.array([0.0, 0.0, G]) + a_W) + A @ r
    values = gtsam.Values()
    values.insert(R, R_W_S)
    values.insert(L, r)
    values.insert(V, speed)
    factor = tilt_factor(noise, R, f_exact, A, *per_speed, L, speed_key=V)
    np.testing.assert_allclose(factor.unwhitenedError(values), 0.0, atol=1e-12)
    with pytest.raises(ValueError):
        tilt_factor(noise, R, f_exact, A, *per_speed, L, K, speed_key=V)


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
            w_S = R_W_S.matrix().T @ np.array([0.0, 0.0, yaw_rate])  # turning about the world's vertical
            u_noisy = gtsam.Rot3.Expmap(np.append(rng.normal(0, sigma, 2), 0.0)).matrix().T @ np.array([0, 0, 1.0])
            bow = R_W_S.matrix()[:, 0]
            left = np.array([-bow[1], bow[0], 0.0]) / np.hypot(bow[0], bow[1])  # horizontal, towards the turn
            f = R_W_S.matrix().T @ (G * u_noisy + truth_v * yaw_rate * left)
            key = gtsam.symbol("r", j)
            graph.add(tilt_factor(gtsam.noiseModel.Isotropic.Sigma(2, sigma), key, f, np.zeros((3, 3)), 0.0, w_S,
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


def test_hull_acceleration_is_the_simulated_hull_s_on_a_rolling_turning_voyage():
    """The known hull acceleration from the log's speed and the gyro's body rate (``hull_acceleration_W``) equals
    the simulator's, which differentiates the heading's Euler angles in closed form (an independent path), on a
    voyage that turns while rolling and pitching; its Jacobian on the attitude matches central differences."""
    from selfcal.sim.ship import ShipScenario
    motion = ShipScenario(kind="turning", duration_s=300.0, seed=3).motion
    t = np.linspace(5.0, 295.0, 60)
    R_W_S = motion.R_W_S(t)
    w_S, _ = motion.body_rates(t)
    v, v_dot = motion.speed(t)
    truth = motion.acceleration_W(t)
    a_W = np.array([ship.hull_acceleration_W(R_W_S[i], v_dot[i], v[i] * w_S[i])[0] for i in range(len(t))])
    np.testing.assert_allclose(a_W[:, :2], truth[:, :2], atol=1e-12)
    assert np.all(a_W[:, 2] == 0.0)
    # the level-ship form this replaced is off by the rolling: a check that the voyage tests something
    level = np.einsum("nij,nj->ni", R_W_S, ship.known_acceleration_S(v, v_dot, w_S[:, 2]))
    assert np.max(np.abs(level[:, :2] - truth[:, :2])) > 1e-3
    rng = np.random.default_rng(5)
    for i in rng.choice(len(t), 5, replace=False):
        _, H = ship.hull_acceleration_W(R_W_S[i], v_dot[i], v[i] * w_S[i])
        numeric = np.column_stack([
            (ship.hull_acceleration_W(R_W_S[i] @ gtsam.Rot3.Expmap(h * e).matrix(), v_dot[i], v[i] * w_S[i])[0]
             - ship.hull_acceleration_W(R_W_S[i] @ gtsam.Rot3.Expmap(-h * e).matrix(), v_dot[i], v[i] * w_S[i])[0])
            / (2 * h) for e in np.eye(3) for h in [1e-6]])
        np.testing.assert_allclose(H, numeric, atol=1e-7)


def test_euler_angles_and_their_jacobian():
    """``euler_zyx`` inverts ``Rz(yaw) Ry(pitch) Rx(roll)`` and its Jacobian on a right perturbation matches central
    differences at random attitudes."""
    rng = np.random.default_rng(8)
    for _ in range(5):
        roll, pitch, yaw = rng.uniform(-1.2, 1.2, 3)
        R_W_S = gtsam.Rot3.Ypr(yaw, pitch, roll).matrix()
        angles, J = ship.euler_zyx(R_W_S)
        np.testing.assert_allclose(angles, [roll, pitch, yaw], atol=1e-12)
        h = 1e-6
        numeric = np.column_stack([(ship.euler_zyx(R_W_S @ gtsam.Rot3.Expmap(h * e).matrix())[0]
                                    - ship.euler_zyx(R_W_S @ gtsam.Rot3.Expmap(-h * e).matrix())[0]) / (2 * h)
                                   for e in np.eye(3)])
        np.testing.assert_allclose(J, numeric, atol=1e-7)


@pytest.mark.parametrize("along_track_ratio", [0.0, 2.0])
@pytest.mark.parametrize("seed", range(3))
def test_offsets_in_the_attitude_have_jacobians_and_vanish_on_exact_data(seed, along_track_ratio):
    """A generic term in the heading (the audit's ``AttitudeColumn``: the basis evaluated at the state's own
    heading), fitted and known: Jacobians at a random point (the basis' slope on the attitude included), and zero
    error where the force carries exactly that offset."""
    from selfcal.audit.ship import AttitudeColumn
    from selfcal.audit.terms import Coordinate, terms_for
    rng = np.random.default_rng(seed + 30)
    R_W_S, A, hull, r, k = random_case(rng)
    heading = Coordinate("heading", np.linspace(-3.0, 3.0, 50), "rad", "angle")
    term = next(t for t in terms_for([heading]) if t.form == "harmonic")
    columns = [AttitudeColumn(term, j, np.array([ship.euler_zyx(R_W_S.matrix())[0][2]])) for j in range(2)]
    keys = [gtsam.symbol("u", j) for j in range(2)]
    coefficients = [rng.normal(0, 0.01, 2) for _ in range(2)]
    noise = gtsam.noiseModel.Isotropic.Sigma(2, 0.01)
    f = rng.normal(0, 0.5, 3) + np.array([0.0, 0.0, G])
    fitted = tilt_factor(noise, R, f, A, *hull, L, K, offset_channels=[(key, c[0]) for key, c in zip(keys, columns)],
                         known_offsets=[(rng.normal(0, 0.01, 2), columns[0][0])], along_track_ratio=along_track_ratio)
    assert_factor_jacobians(fitted, {R: R_W_S, L: r, K: k, keys[0]: coefficients[0], keys[1]: coefficients[1]},
                            atol=1e-5)
    # exact data: the force tilted by the offset the term states at this heading
    offset = sum(c * col[0](R_W_S.matrix())[0] for c, col in zip(coefficients, columns))
    a_W = ship.hull_acceleration_W(R_W_S.matrix(), *hull)[0]
    # the residual is the horizontal part of unit(R f_c - a_W): the corrected force tilted by the offset
    tilted = G * np.array([offset[0], offset[1], np.sqrt(1.0 - offset @ offset)])
    f_exact = R_W_S.matrix().T @ (tilted + (1 + k[0]) * a_W) + A @ r
    exact = tilt_factor(noise, R, f_exact, A, *hull, L, K, offset_channels=[(key, c[0]) for key, c in zip(keys, columns)],
                        along_track_ratio=along_track_ratio)
    values = gtsam.Values()
    for key, value in ((L, r), (K, k), (keys[0], coefficients[0]), (keys[1], coefficients[1])):
        values.insert(key, value)
    values.insert(R, R_W_S)
    np.testing.assert_allclose(exact.unwhitenedError(values), 0.0, atol=1e-12)


def test_a_smoothed_regressor_takes_the_attenuation_out_of_the_speed_log_scale():
    """Errors in the variables.  A level hull at 10 m/s turning at 0.05 sin(2 pi t / 60 s) rad/s, keyframes 1 s
    apart, its speed log exact (k = 0); the known hull acceleration ``v w`` carries the gyro's white noise (here
    0.2 m/s^2 per keyframe, exaggerated so 400 voyages resolve the bias).  That noise is in the residual (removed
    with the acceleration) and, unsmoothed, in the scale's regressor too: the fitted scale is pulled by
    ``-Var(n) / E[(v w)^2] = -0.04 / (0.125 + 0.04) = -0.24``.  The regressor averaged over the neighbouring
    keyframes (the keyframe's own left out; in the recordings its 0.2 s carry 3.5 % of the 20 s smoother's weight)
    shares no noise with the residual: the scale's mean over voyages is 0 within 3 standard errors and its scatter is
    the least-squares sigma ``sigma_n / sqrt(sum regressor^2)`` (400 voyages: the scatter's own error is 3.5 %, 15 %
    allowed).  At the true attitude the residual is linear in k: one Gauss-Newton step is the fit."""
    from scipy.ndimage import uniform_filter1d
    rng = np.random.default_rng(11)
    t = np.arange(300.0)
    v, sigma_n, window = 10.0, 0.2, 11
    psi_dot = 0.05 * np.sin(2 * np.pi * t / 60.0)
    rotations = [gtsam.Rot3.Yaw(p).matrix() for p in np.cumsum(psi_dot)]
    vw_true = v * np.column_stack([0 * t, 0 * t, psi_dot])
    f = [R_W_S.T @ (np.array([0.0, 0.0, G]) + ship.hull_acceleration_W(R_W_S, 0.0, vw)[0])
         for R_W_S, vw in zip(rotations, vw_true)]
    fits, sigmas = {"raw": [], "smoothed": []}, []
    for _ in range(400):
        vw = vw_true + np.column_stack([0 * t, 0 * t, rng.normal(0, sigma_n, len(t))])
        smoothed = (uniform_filter1d(vw, window, axis=0, mode="nearest") * window - vw) / (window - 1)  # own left out
        for name, regressor in (("raw", None), ("smoothed", smoothed)):
            num = den = 0.0
            for j, R_W_S in enumerate(rotations):
                scale_regressor = None if regressor is None else (0.0, regressor[j])
                e, _, _, H_k = ship.level_residual(R_W_S, f[j], np.zeros((3, 3)), np.zeros(3), 0.0, vw[j], 0.0,
                                                   scale_regressor)
                num, den = num + H_k[:, 0] @ e, den + H_k[:, 0] @ H_k[:, 0]
            fits[name].append(-num / den)
        sigmas.append(sigma_n / np.sqrt(np.sum(smoothed[:, 2] ** 2)))
    raw, smooth = np.array(fits["raw"]), np.array(fits["smoothed"])
    assert raw.mean() < -0.15, raw.mean()  # the attenuation (predicted -0.24)
    assert abs(smooth.mean()) < 3 * smooth.std() / np.sqrt(len(smooth)), (smooth.mean(), smooth.std())
    assert smooth.std() == pytest.approx(np.median(sigmas), rel=0.15), (smooth.std(), np.median(sigmas))
