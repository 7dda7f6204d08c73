"""Tracker factors (selfcal.factors.tracker): Jacobians, zero error on exact simulated data, Monte Carlo vs sigma."""
import gtsam
import numpy as np
import pytest
from scipy import stats

from selfcal.factors import tracker as ft
from selfcal.models import tracker as mt
from selfcal.sim.tracker import TrackerScenario
from factor_checks import assert_factor_jacobians

X, V = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V
R_B_C = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def random_pose(rng):
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.3, 3)), rng.uniform(10, 40, 3) * np.array([1, 0.1, 0.1]))


@pytest.mark.parametrize("seed", range(5))
def test_prism_velocity_jacobians(seed):
    rng = np.random.default_rng(seed)
    f = ft.prism_velocity_factor(gtsam.noiseModel.Isotropic.Sigma(3, 2e-3), X(0), V(0), rng.normal(0, 0.01, 3),
                                 rng.normal(0, 0.5, 3), rng.normal(0, 0.3, 3))
    assert_factor_jacobians(f, {X(0): random_pose(rng), V(0): rng.normal(0, 0.01, 3)})


@pytest.mark.parametrize("seed", range(5))
def test_beam_bearing_jacobians(seed):
    rng = np.random.default_rng(seed)
    b = np.array([0.05, -0.03, 1.0]) + rng.normal(0, 0.05, 3)
    f = ft.beam_bearing_factor(gtsam.noiseModel.Isotropic.Sigma(2, 1.7e-4), X(0), b / np.linalg.norm(b),
                               rng.normal(0, 0.2, 3), R_B_C, rng.normal(0, 1.0, 3))
    pose = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.05, 3)), np.array([30.0, 0.0, 0.0]) + rng.normal(0, 1, 3))
    assert_factor_jacobians(f, {X(0): pose}, atol=1e-5)


@pytest.fixture(scope="module")
def exact():
    sc = TrackerScenario(duration_s=25.0, seed=4, burst_rate_per_min=30.0)
    return sc, sc.measurements(None)


def test_zero_error_on_exact_data(exact):
    """Every measurement factor (GTSAM's and ours) vanishes at the true pose: conventions agree with the sim."""
    sc, rec = exact
    tr, inc, cam = (rec.sensors[s] for s in ("tracker0", "incl0", "cam0"))
    unit = gtsam.noiseModel.Unit.Create
    for i in range(0, len(tr.t_ns), 37):
        t = (tr.t_ns[i] - sc.t0_ns) * 1e-9
        R, p, v, _, w, _ = (a[0] for a in sc.kinematics([t]))
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose3(gtsam.Rot3(R), p))
        values.insert(V(0), v)
        z = np.array([tr.values[c][i] for c in ("x", "y", "z")])
        zv = np.array([tr.values[c][i] for c in ("vx", "vy", "vz")])
        np.testing.assert_allclose(ft.prism_position_factor(unit(3), X(0), z, sc.r_P_B).unwhitenedError(values), 0,
                                   atol=1e-12)
        np.testing.assert_allclose(ft.prism_velocity_factor(unit(3), X(0), V(0), zv, w, sc.r_P_B)
                                   .unwhitenedError(values), 0, atol=1e-12)
    bearings = mt.bearing_from_pixel(np.column_stack([cam.values["u"], cam.values["v"]]), sc.camera_matrix,
                                     sc.dist_coeffs)
    for i in range(0, len(cam.t_ns), 7):
        t = (cam.t_ns[i] - sc.t0_ns) * 1e-9
        R, p = (a[0] for a in sc.truth_pose([t]))
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose3(gtsam.Rot3(R), p))
        f = ft.beam_bearing_factor(unit(2), X(0), bearings[i], sc.r_C_B, sc.R_B_C)
        np.testing.assert_allclose(f.unwhitenedError(values), 0, atol=1e-9)  # undistortPoints converges to 1e-12
    # the inclinometer: the direction of the specific force, so any acceleration tilts it
    t = (inc.t_ns - sc.t0_ns) * 1e-9
    R, p = sc.truth_pose(t)
    quiet = np.array([not any(b.start_s <= ti <= b.start_s + b.duration_s for b in sc.bursts) for ti in t])
    assert quiet.any() and (~quiet).any()
    err = []
    for i in range(len(t)):
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose3(gtsam.Rot3(R[i]), p[i]))
        up = mt.up_direction_B(inc.values["roll"][i], inc.values["pitch"][i])
        err.append(np.linalg.norm(ft.inclinometer_factor(unit(2), X(0), up).unwhitenedError(values)))
    err = np.array(err)
    # when quiet, only the slow steering tilts the reading: its acceleration (|a_horizontal| / g) and its rotation
    # during the averaging window (each IMU interval is referred to its start: delay = window / 2 + dt / 2)
    _, _, _, a_W, w_B, _ = sc.kinematics(t)
    bound = (np.linalg.norm(a_W[:, :2], axis=1) / sc.gravity_m_s2
             + np.linalg.norm(w_B, axis=1) * (sc.incl_average_s + 1.0 / sc.rates["imu0"]) / 2)
    assert np.all(err[quiet] <= 1.01 * bound[quiet] + 1e-9)
    assert err[~quiet].max() > 1e-5  # vibration tilts the specific force: the reason for gating


def _mc_variance_bounds(runs):
    """Two-sided 99.8 % bounds on sample variance / true variance for ``runs`` Gaussian draws."""
    return stats.chi2.ppf(0.001, runs - 1) / (runs - 1), stats.chi2.ppf(0.999, runs - 1) / (runs - 1)


def test_monte_carlo_scatter_matches_reported_sigma():
    """Velocity (from the custom velocity factor) and azimuth (from the custom bearing factor) estimated from
    noisy measurements: their scatter over 300 runs agrees with the marginal sigma GTSAM reports (chi-square
    bounds on the variance ratio at 99.8 %)."""
    rng = np.random.default_rng(11)
    runs, n_meas = 300, 5
    sigma_v, sigma_b = 2e-3, 1.7e-4
    R_true = gtsam.Rot3.Ypr(0.02, -0.01, 0.015)
    pose_true = gtsam.Pose3(R_true, np.array([30.0, 0.2, -0.1]))
    v_true = np.array([1e-3, 0.0, 0.0])
    r_P, r_C, w = np.array([0.12, -0.05, 0.25]), np.array([0.1, 0.03, 0.2]), np.array([0.01, -0.02, 0.005])
    v_pred = mt.prism_velocity_W(R_true.matrix(), v_true, w, r_P)
    d_C = mt.beam_direction_C(R_true.matrix(), pose_true.translation(), r_C, R_B_C)
    b_true = d_C / np.linalg.norm(d_C)
    err_v, err_yaw, sig_v, sig_yaw = [], [], [], []
    for _ in range(runs):
        graph = gtsam.NonlinearFactorGraph()
        # roll, pitch and position known tightly (as the inclinometer and tracker give them); yaw free
        graph.add(gtsam.PriorFactorPose3(X(0), pose_true, gtsam.noiseModel.Diagonal.Sigmas(
            np.array([1e-7, 1e-7, 1.0, 1e-7, 1e-7, 1e-7]))))
        for _ in range(n_meas):
            graph.add(ft.prism_velocity_factor(gtsam.noiseModel.Isotropic.Sigma(3, sigma_v), X(0), V(0),
                                               v_pred + rng.normal(0, sigma_v, 3), w, r_P))
            b = b_true + gtsam.Unit3(b_true).basis() @ rng.normal(0, sigma_b, 2)
            graph.add(ft.beam_bearing_factor(gtsam.noiseModel.Isotropic.Sigma(2, sigma_b), X(0), b / np.linalg.norm(b),
                                             r_C, R_B_C))
        values = gtsam.Values()
        values.insert(X(0), pose_true.retract(np.r_[0, 0, 0.01, 0, 0, 0]))
        values.insert(V(0), np.zeros(3))
        result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        marg = gtsam.Marginals(graph, result)
        err_v.append(result.atVector(V(0)) - v_true)
        err_yaw.append(pose_true.localCoordinates(result.atPose3(X(0)))[2])
        sig_v.append(np.sqrt(np.diag(marg.marginalCovariance(V(0)))))
        sig_yaw.append(np.sqrt(marg.marginalCovariance(X(0))[2, 2]))
    lo, hi = _mc_variance_bounds(runs)
    ratio_v = np.var(np.array(err_v), axis=0, ddof=1) / np.mean(sig_v, axis=0) ** 2
    ratio_yaw = np.var(err_yaw, ddof=1) / np.mean(sig_yaw) ** 2
    assert np.all((ratio_v > lo) & (ratio_v < hi)), ratio_v
    assert lo < ratio_yaw < hi, ratio_yaw


F = gtsam.symbol_shorthand.F


@pytest.mark.parametrize("seed", range(5))
def test_drifting_inclinometer_jacobians(seed):
    rng = np.random.default_rng(seed)
    up = mt.up_direction_B(*rng.normal(0, 0.05, 2))
    f = ft.drifting_inclinometer_factor(gtsam.noiseModel.Isotropic.Sigma(2, 8.7e-5), X(0), F(0), up,
                                        rng.uniform(-5.0, 40.0))
    drift = np.r_[rng.normal(0, 0.01, 2), rng.normal(0, 2e-4, 2)]
    assert_factor_jacobians(f, {X(0): random_pose(rng), F(0): drift})


def test_drifting_inclinometer_is_the_nominal_factor_without_drift_and_zero_on_an_exact_ramp():
    """Without drift the error and the pose Jacobian are GTSAM's AttitudeFactorPose3's.  On the simulator's noise-
    free readings with a bias ramp (added to the reading, as the simulator's faults are), the factor at the true
    drift gives the error the nominal factor gives on the same run without the ramp (the steering's own tilt of
    the reading): to 1e-12 rad for a roll ramp (a body-x rotation exactly); for a pitch ramp within the third-order
    term of the model's docstring, ``|b| (|sin r| |tilt| + 1 - cos r)`` (here ~1e-6 rad: 1 % of the noise)."""
    rng = np.random.default_rng(3)
    unit = gtsam.noiseModel.Unit.Create(2)
    for _ in range(5):
        up = mt.up_direction_B(*rng.normal(0, 0.05, 2))
        values = gtsam.Values()
        values.insert(X(0), random_pose(rng))
        values.insert(F(0), np.zeros(4))
        drifting = ft.drifting_inclinometer_factor(unit, X(0), F(0), up, 12.0)
        nominal = ft.inclinometer_factor(unit, X(0), up)
        np.testing.assert_allclose(drifting.unwhitenedError(values), nominal.unwhitenedError(values), atol=1e-15)
        A, _ = drifting.linearize(values).jacobian()
        A0, _ = nominal.linearize(values).jacobian()
        np.testing.assert_allclose(A[:, :6], A0, atol=1e-12)
    from selfcal.sim.tracker import Fault
    rate = np.radians(0.01)  # rad/s, the default schedule's ramp
    t_ref = 12.0  # the episode's reference time (an alarm some seconds into the ramp)
    clean_sc = TrackerScenario(duration_s=30.0, seed=4, burst_rate_per_min=0.0)
    clean = clean_sc.measurements(None).sensors["incl0"]
    for axis in (0, 1):
        sc = TrackerScenario(duration_s=30.0, seed=4, burst_rate_per_min=0.0,
                             faults=[Fault("incl0", "ramp", 5.0, 30.0, -rate, axis)])
        inc = sc.measurements(None).sensors["incl0"]
        t = (inc.t_ns - sc.t0_ns) * 1e-9
        R, p = sc.truth_pose(t)
        drift = np.zeros(4)
        drift[axis], drift[2 + axis] = -rate * (t_ref - 5.0), -rate
        diff, bound = [], []
        for i in np.flatnonzero((t >= 5.0) & (t < 30.0)):  # the ramp ends (is gone) at 30 s
            values = gtsam.Values()
            values.insert(X(0), gtsam.Pose3(gtsam.Rot3(R[i]), p[i]))
            values.insert(F(0), drift)
            up = mt.up_direction_B(inc.values["roll"][i], inc.values["pitch"][i])
            up_clean = mt.up_direction_B(clean.values["roll"][i], clean.values["pitch"][i])
            e = ft.drifting_inclinometer_factor(unit, X(0), F(0), up, t[i] - t_ref).unwhitenedError(values)
            diff.append(np.linalg.norm(e - ft.inclinometer_factor(unit, X(0), up_clean).unwhitenedError(values)))
            r, tilt = clean.values["roll"][i], np.hypot(clean.values["roll"][i], clean.values["pitch"][i])
            b = rate * (t[i] - 5.0)
            bound.append(b * (abs(np.sin(r)) * tilt + 1.0 - np.cos(r)) if axis else 0.0)
        assert len(diff) > 200
        assert np.all(np.array(diff) <= 1.01 * np.array(bound) + 1e-12), (axis, max(diff), max(bound))


def test_drifting_inclinometer_estimates_its_drift_at_the_cramer_rao_bound():
    """A known attitude, 10 Hz readings over a 30 s episode: the drift (offset and rate on both axes) estimated
    from noisy readings over 300 runs.  GTSAM's marginal covariance equals the Cramer-Rao bound of the linear
    model ``sigma^2 (H^T H)^-1`` (H: the mounting Jacobian and dt times it), and the estimates' scatter matches it
    (chi-square bounds on the variance ratio at 99.8 %, per component) with a mean inside 4 standard errors."""
    rng = np.random.default_rng(12)
    runs, sigma = 300, 8.7e-5
    R_true = gtsam.Rot3.Ypr(0.3, 0.01, -0.02)
    pose = gtsam.Pose3(R_true, np.zeros(3))
    drift_true = np.array([2e-3, -1e-3, 1.7e-4, -5e-5])
    dts = np.arange(-5.0, 25.0, 0.1)
    up_true = R_true.matrix()[2]
    basis = ft.UP_W.basis()
    H = []
    for dt in dts:
        m = drift_true[:2] + dt * drift_true[2:]
        _, J = mt.drifting_up_error(R_true.matrix(), so3_exp_minus(m) @ up_true, m, basis, with_jacobian=True)
        H.append(np.hstack([J["mount"], dt * J["mount"]]))
    H = np.vstack(H)
    crb = sigma**2 * np.linalg.inv(H.T @ H)
    estimates, marginals = [], []
    noise = gtsam.noiseModel.Isotropic.Sigma(2, sigma)
    for _ in range(runs):
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(X(0), pose, gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)))
        for dt in dts:
            m = drift_true[:2] + dt * drift_true[2:]
            # the reading: the true up direction offset by the mounting, then tilted by white noise
            up = so3_exp_minus(m) @ up_true
            up = up + gtsam.Unit3(up).basis() @ rng.normal(0, sigma, 2)
            graph.add(ft.drifting_inclinometer_factor(noise, X(0), F(0), up / np.linalg.norm(up), dt))
        values = gtsam.Values()
        values.insert(X(0), pose)
        values.insert(F(0), np.zeros(4))
        result = gtsam.GaussNewtonOptimizer(graph, values).optimize()
        estimates.append(result.atVector(F(0)))
        marginals.append(gtsam.Marginals(graph, result).marginalCovariance(F(0)))
    estimates = np.array(estimates)
    np.testing.assert_allclose(np.mean(marginals, axis=0), crb, rtol=1e-3, atol=1e-3 * np.sqrt(np.outer(
        np.diag(crb), np.diag(crb))).max())
    lo, hi = _mc_variance_bounds(runs)
    ratio = np.var(estimates, axis=0, ddof=1) / np.diag(crb)
    assert np.all((ratio > lo) & (ratio < hi)), ratio
    assert np.all(np.abs(estimates.mean(axis=0) - drift_true) < 4 * np.sqrt(np.diag(crb) / runs))


def so3_exp_minus(mount):
    """Exp(-m) of a mounting offset (m_x, m_y): turns a true up direction into the reading it gives."""
    from selfcal.models import so3
    return so3.exp(-np.array([mount[0], mount[1], 0.0]))
