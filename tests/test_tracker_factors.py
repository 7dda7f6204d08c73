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
