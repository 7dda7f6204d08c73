"""Tracker audit (selfcal.audit.tracker): its calibrated factors, and hidden effects it must name.

Hidden-effect tests: a short calibration run (20 s, tilt steered by 1-2 deg over 20-40 s, vibration bursts) is
simulated with ONE effect the audit is not told about; the audit must accept that effect first, accept nothing
else, and report its size within 3 of its own sigmas (per component).  The null run must give no finding.
"""
import json

import gtsam
import numpy as np
import pytest
from scipy import stats

from selfcal.core import inertial, so3
from selfcal.audit.engine import run_audit
from selfcal.cli.main import main
from selfcal.audit.tracker import TrackerAudit
from selfcal.factors import tracker as ft
from selfcal.models import tracker as mt
from selfcal.pipelines.tracker import estimator_for_audit
from selfcal.sim.tracker import TrackerScenario
from factor_checks import assert_factor_jacobians

X, V, B = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B
L, O, D, S, A = (gtsam.symbol(c, 0) for c in "LODSA")


def random_pose(rng):
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.05, 3)), np.array([30.0, 0.0, 0.0]) + rng.normal(0, 0.5, 3))


@pytest.mark.parametrize("seed", range(3))
def test_calibrated_factor_jacobians(seed):
    rng = np.random.default_rng(seed)
    unit = gtsam.noiseModel.Unit.Create
    z, v = rng.normal(0, 0.01, (4, 3)) + [30.0, 0.0, 0.0], rng.normal(0, 0.05, (4, 3))
    f = ft.calibrated_prism_factor(unit(12), X(0), z, [0.12, -0.05, 0.25], v, L, O, start_velocity_key=V(1),
                                   lead_s=rng.uniform(0, 0.2, 4), v_start=rng.normal(0, 0.05, 3))
    assert_factor_jacobians(f, {X(0): random_pose(rng), L: rng.normal(0, 0.02, 3), O: rng.normal(0, 0.02, 1),
                                V(1): rng.normal(0, 0.05, 3)})
    # the offset's regressor interpolated between two velocity variables, one of them also the start velocity
    f = ft.calibrated_prism_factor(unit(12), X(0), z, [0.12, -0.05, 0.25], rng.normal(0, 0.003, 3), L, O,
                                   start_velocity_key=V(1), lead_s=rng.uniform(0, 0.2, 4),
                                   v_start=rng.normal(0, 0.05, 3), velocity_keys=(V(1), V(2)),
                                   velocity_fraction=rng.uniform(0, 1, 4))
    assert_factor_jacobians(f, {X(0): random_pose(rng), L: rng.normal(0, 0.02, 3), O: rng.normal(0, 0.02, 1),
                                V(1): rng.normal(0, 0.1, 3), V(2): rng.normal(0, 0.1, 3)})
    f = ft.calibrated_prism_velocity_factor(unit(3), X(0), V(0), rng.normal(0, 0.01, 3), rng.normal(0, 0.3, 3),
                                            [0.12, -0.05, 0.25], rng.normal(0, 0.2, 3), O)
    assert_factor_jacobians(f, {X(0): random_pose(rng), V(0): rng.normal(0, 0.01, 3), O: rng.normal(0, 0.02, 1)})
    f = ft.calibrated_prism_velocity_factor(unit(3), X(0), V(0), rng.normal(0, 0.01, 3), rng.normal(0, 0.3, 3),
                                            [0.12, -0.05, 0.25], np.zeros(3), O, previous_velocity_key=V(1),
                                            fraction=rng.uniform(0, 1), span_s=0.2, lever_key=L)
    assert_factor_jacobians(f, {X(0): random_pose(rng), V(0): rng.normal(0, 0.1, 3), O: rng.normal(0, 0.02, 1),
                                V(1): rng.normal(0, 0.1, 3), L: rng.normal(0, 0.02, 3)})
    f = ft.calibrated_inclinometer_factor(unit(2), X(0), rng.normal(0, 0.03, 2), rng.normal(0, 0.003, 2),
                                          {"bias": D, "scale": S, "accel_sensitivity": A}, {})
    assert_factor_jacobians(f, {X(0): random_pose(rng), D: rng.normal(0, 1e-3, 2), S: rng.normal(0, 0.02, 1),
                                A: rng.normal(0, 0.3, 1)}, atol=1e-5)
    # the disturbance predicted from the accelerometer at the pose's attitude and the IMU bias variable
    f_B = 9.81 * np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.3, 3)
    vibration = ft.AccelerometerTilt(f_B, np.eye(3) - 0.02 * so3.hat(rng.normal(0, 0.1, 3)), 0.7, B(0))
    f = ft.calibrated_inclinometer_factor(unit(2), X(0), rng.normal(0, 0.03, 2), rng.normal(0, 0.003, 2),
                                          {"bias": D, "scale": S, "accel_sensitivity": A}, {}, vibration=vibration)
    assert_factor_jacobians(f, {X(0): random_pose(rng), B(0): gtsam.imuBias.ConstantBias(rng.normal(0, 0.05, 3),
                                                                                         rng.normal(0, 1e-3, 3)),
                                D: rng.normal(0, 1e-3, 2), S: rng.normal(0, 0.02, 1), A: rng.normal(0, 0.3, 1)},
                            atol=1e-5)


def test_calibrated_factors_vanish_on_exact_data():
    """The models are the simulator's: at the true pose and the true effects the errors are zero."""
    sc = TrackerScenario(duration_s=5.0, seed=2, incl_bias_rad=(3e-4, -2e-4), incl_scale=0.01,
                         incl_accel_sensitivity=0.2, burst_rate_per_min=60.0)
    rec = sc.measurements(None)
    inc = rec.sensors["incl0"]
    t = (inc.t_ns - sc.t0_ns) * 1e-9
    R, p, *_ = sc.kinematics(t)
    rate, n_avg = sc.rates["imu0"], int(round(sc.incl_average_s * sc.rates["imu0"]))
    errors = []
    for i in range(len(t)):
        # the disturbance a perfect specific-force inclinometer reads: exact specific force, same averaging
        _, f = sc._imu_exact(t[i] - np.arange(1, n_avg + 1)[::-1] / rate)
        d = np.array(inertial.tilt_from_specific_force(f.mean(axis=0))) - mt.tilt_of_rotation(R[i])
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose3(gtsam.Rot3(R[i]), p[i]))
        fac = ft.calibrated_inclinometer_factor(gtsam.noiseModel.Unit.Create(2), X(0),
                                                [inc.values["roll"][i], inc.values["pitch"][i]], d, {},
                                                {"bias": sc.incl_bias_rad, "scale": sc.incl_scale,
                                                 "accel_sensitivity": sc.incl_accel_sensitivity})
        errors.append(fac.unwhitenedError(values))
        # the same disturbance predicted from the accelerometer (weight 1: a noise-free one) read with a bias
        # the IMU bias variable holds
        accel_bias = np.array([0.03, -0.02, 0.05])
        values.insert(B(0), gtsam.imuBias.ConstantBias(accel_bias, np.zeros(3)))
        fac = ft.calibrated_inclinometer_factor(
            gtsam.noiseModel.Unit.Create(2), X(0), [inc.values["roll"][i], inc.values["pitch"][i]], np.zeros(2), {},
            {"bias": sc.incl_bias_rad, "scale": sc.incl_scale, "accel_sensitivity": sc.incl_accel_sensitivity},
            vibration=ft.AccelerometerTilt(f.mean(axis=0) + accel_bias, np.eye(3), 1.0, B(0)))
        errors.append(fac.unwhitenedError(values))
    np.testing.assert_allclose(errors, 0.0, atol=1e-12)
    sc = TrackerScenario(duration_s=2.0, seed=2, tracker_clock_offset_s=0.02, steer_position_m=(0.05, 0.1),
                         steer_position_period_s=(4.0, 8.0))
    tr = sc.measurements(None).sensors["tracker0"]
    t = (tr.t_ns - sc.t0_ns) * 1e-9
    R, p, v, a, w, _ = sc.kinematics(t)
    z = np.column_stack([tr.values[c] for c in "xyz"])
    for i in range(0, len(t), 7):
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose3(gtsam.Rot3(R[i]), p[i]))
        fac = ft.calibrated_prism_factor(gtsam.noiseModel.Unit.Create(3), X(0), z[i], sc.r_P_B,
                                         mt.prism_velocity_W(R[i], v[i], w[i], sc.r_P_B), offset_fixed=0.02)
        # first order in dt: the neglected 0.5 a dt^2 (a < 0.3 m/s^2) is below 1e-4 m
        np.testing.assert_allclose(fac.unwhitenedError(values), 0.0, atol=1e-4)
        values.insert(V(0), v[i])
        zv = np.array([tr.values[c][i] for c in ("vx", "vy", "vz")])
        fac = ft.calibrated_prism_velocity_factor(gtsam.noiseModel.Unit.Create(3), X(0), V(0), zv, w[i], sc.r_P_B,
                                                  a[i], offset_fixed=0.02)
        # neglected: 0.5 jerk dt^2 and the rotation rate's change over dt times the lever arm (< 1e-4 m/s)
        np.testing.assert_allclose(fac.unwhitenedError(values), 0.0, atol=1e-4)
        # sensor.yaml's lever arm off by metres, the error known: the prism's rotation velocity is the true one
        # (ignored, w x dr would leave up to 6e-4 m/s here: the steering turns at ~2e-4 rad/s)
        dr = np.array([2.0, -1.0, 3.0])
        fac = ft.calibrated_prism_velocity_factor(gtsam.noiseModel.Unit.Create(3), X(0), V(0), zv, w[i],
                                                  np.asarray(sc.r_P_B) - dr, a[i], offset_fixed=0.02, lever_fixed=dr)
        np.testing.assert_allclose(fac.unwhitenedError(values), 0.0, atol=1e-4)


def test_interpolated_offset_regressors_vanish_on_exact_data():
    """The audit's clock-offset model with the state velocity interpolated between two keyframes (the tracker
    block and the bridge form of the velocity factor): zero error at the truth, up to the neglected terms."""
    dt, span = 0.02, 0.2
    sc = TrackerScenario(duration_s=2.0, seed=2, tracker_clock_offset_s=dt, steer_position_m=(0.05, 0.1),
                         steer_position_period_s=(4.0, 8.0), burst_rate_per_min=0.0)
    tr = sc.measurements(None).sensors["tracker0"]
    t = (tr.t_ns - sc.t0_ns) * 1e-9
    t0, t1 = 0.505, 0.505 + span  # keyframes on IMU stamps, between tracker stamps
    sel = (t >= t0) & (t < t1)
    ti, z = t[sel], np.column_stack([tr.values[c] for c in "xyz"])[sel]
    v_raw = np.column_stack([tr.values[c] for c in ("vx", "vy", "vz")])[sel]
    (_, R1), (_, p1), (v0, v1), _, (_, w1), _ = sc.kinematics(np.array([t0, t1]))
    Ri, pi, vi, _, wi, _ = sc.kinematics(ti)
    prism = lambda R, p: p + R @ sc.r_P_B  # noqa: E731
    moved = z + prism(R1, p1) - np.array([prism(R, q) for R, q in zip(Ri, pi)])  # the IMU's move, exact
    lead, f = t1 - ti, (ti - t0) / span
    values = gtsam.Values()
    values.insert(X(1), gtsam.Pose3(gtsam.Rot3(R1), p1))
    values.insert(V(0), v0)
    values.insert(V(1), v1)
    fac = ft.calibrated_prism_factor(gtsam.noiseModel.Unit.Create(z.size), X(1), moved, sc.r_P_B,
                                     np.tile(R1 @ mt.cross(w1, sc.r_P_B), (len(ti), 1)), offset_fixed=dt,
                                     start_velocity_key=V(0), lead_s=lead, v_start=v0, velocity_keys=(V(0), V(1)),
                                     velocity_fraction=f)
    # neglected: 0.5 a dt^2 (a < 0.25 m/s^2: 5e-5 m), dt times the interpolation's miss of the velocity's curvature
    # (jerk < 0.4 m/s^3: 0.4 span^2 / 8 = 2e-3 m/s, 4e-5 m) and of the lever arm's rotation velocity (< 1e-5 m)
    np.testing.assert_allclose(fac.unwhitenedError(values), 0.0, atol=1e-4)
    # velocity: the samples' mean minus the IMU's bridge (its velocity change less the linear share), exact here
    f_mean = float(f.mean())
    z_bridge = v_raw.mean(axis=0) - vi.mean(axis=0) + (1 - f_mean) * v0 + f_mean * v1
    fac = ft.calibrated_prism_velocity_factor(gtsam.noiseModel.Unit.Create(3), X(1), V(1), z_bridge, wi.mean(axis=0),
                                              sc.r_P_B, np.zeros(3), offset_fixed=dt, previous_velocity_key=V(0),
                                              fraction=f_mean, span_s=span)
    # neglected: 0.5 jerk dt^2 (8e-5 m/s), dt jerk times the samples' mean time off the interval's middle (0.01 s:
    # 8e-5 m/s) and the lever arm's rotation velocity's change over dt (< 1e-5 m/s)
    np.testing.assert_allclose(fac.unwhitenedError(values), 0.0, atol=2e-4)


def test_monte_carlo_scatter_of_offset_with_interpolated_velocity_matches_reported_sigma():
    """Clock offset and lever-arm correction when the offset's regressor is the velocity variables interpolated
    (tracker blocks moved with a start velocity, bridge-form velocity factors, velocities estimated with them):
    scatter over 100 runs against the marginal sigmas (99.8 % chi-square bounds), and no bias."""
    rng = np.random.default_rng(11)
    runs, sigma_p, sigma_v, n, m, span = 100, 5e-4, 2e-3 / np.sqrt(5), 20, 5, 0.2
    r0, dr, dt = np.array([0.12, -0.05, 0.25]), np.array([0.01, -0.02, 0.005]), 0.03
    poses = [gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.2, 3)), rng.normal([30.0, 0, 0], 0.5)) for _ in range(n)]
    v_prev, v_k = rng.normal(0, 0.1, (n, 3)), rng.normal(0, 0.1, (n, 3))
    v_start = v_prev + rng.normal(0, 0.01, (n, 3))  # the filtered velocity the samples were moved with
    w = rng.normal(0, 0.05, (n, 3))
    f = (np.arange(m) + 0.5) / m
    lead = (1 - f) * span
    err, sig = [], []
    for _ in range(runs):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for j, pose in enumerate(poses):
            R, p = pose.rotation().matrix(), pose.translation()
            kp, kk = V(2 * j), V(2 * j + 1)
            v_rot = R @ mt.cross(w[j], r0)
            v_i = np.outer(1 - f, v_prev[j]) + np.outer(f, v_k[j]) + v_rot
            z = p + R @ (r0 + dr) - dt * v_i - np.outer(lead, v_prev[j] - v_start[j]) + rng.normal(0, sigma_p, (m, 3))
            f_mean = f.mean()
            zv = (mt.prism_velocity_W(R, (1 - f_mean) * v_prev[j] + f_mean * v_k[j], w[j], r0 + dr)
                  - dt * (v_k[j] - v_prev[j]) / span + rng.normal(0, sigma_v, 3))
            graph.add(gtsam.PriorFactorPose3(X(j), pose, gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)))
            for key, truth in ((kp, v_prev[j]), (kk, v_k[j])):  # weak priors: the data decide the velocities
                graph.add(gtsam.PriorFactorVector(key, truth + rng.normal(0, 0.05, 3),
                                                  gtsam.noiseModel.Isotropic.Sigma(3, 0.05)))
                values.insert(key, truth + rng.normal(0, 0.01, 3))
            graph.add(ft.calibrated_prism_factor(gtsam.noiseModel.Isotropic.Sigma(3 * m, sigma_p), X(j), z, r0,
                                                 np.tile(v_rot, (m, 1)), L, O, start_velocity_key=kp, lead_s=lead,
                                                 v_start=v_start[j], velocity_keys=(kp, kk), velocity_fraction=f))
            graph.add(ft.calibrated_prism_velocity_factor(gtsam.noiseModel.Isotropic.Sigma(3, sigma_v), X(j), kk, zv,
                                                          w[j], r0 + dr, np.zeros(3), O, previous_velocity_key=kp,
                                                          fraction=f_mean, span_s=span))
            values.insert(X(j), pose)
        values.insert(L, np.zeros(3))
        values.insert(O, np.zeros(1))
        _solve_and_record(graph, values, L, O, dr, dt, err, sig)
    _assert_scatter_matches_sigma(np.array(err), np.array(sig))


@pytest.mark.parametrize("from_accelerometer", [False, True])
def test_monte_carlo_scatter_of_inclinometer_effects_matches_reported_sigma(from_accelerometer):
    """Bias, scale and sensitivity estimated from noisy readings at 30 known attitudes: scatter over 120 runs
    against GTSAM's marginal sigmas (variance ratio within its 99.8 % chi-square bounds, mean within 4 standard
    errors).  The disturbance known, or predicted from the accelerometer at the IMU bias variable (Wiener weights
    0.3-0.95; the accelerometer bias estimated too, its prior 0.02 m/s^2 drawn around the truth per run)."""
    rng = np.random.default_rng(9 if from_accelerometer else 5)
    runs, sigma, sigma_b, g = 120, 8.7e-5, 0.02, 9.81
    truth = {"bias": np.array([2e-4, -1e-4]), "scale": 0.01, "accel_sensitivity": 0.2,
             "accel_bias": np.array([0.03, -0.02, 0.04])}
    poses = [gtsam.Rot3.Ypr(*rng.uniform(-0.05, 0.05, 3)) for _ in range(30)]
    dist, weight = rng.normal(0, 2e-3, (30, 2)), rng.uniform(0.3, 0.95, 30)
    known, vibrations, exact = [], [], []
    for R, d, w in zip(poses, dist, weight):
        roll, pitch = mt.tilt_of_rotation(R.matrix()) + d / w  # the accelerometer's tilt: d = w (tilt_f - tilt_R)
        f_B = g * np.array([-np.sin(pitch), np.sin(roll) * np.cos(pitch), np.cos(roll) * np.cos(pitch)])
        known.append(np.zeros(2) if from_accelerometer else d)
        vibrations.append(ft.AccelerometerTilt(f_B + truth["accel_bias"], np.eye(3), w, B(0))
                          if from_accelerometer else None)
        exact.append(mt.inclinometer_reading(R.matrix(), d, truth["bias"], truth["scale"], truth["accel_sensitivity"]))
    err, sig = [], []
    for _ in range(runs):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for j, (R, d, vibration, z) in enumerate(zip(poses, known, vibrations, exact)):
            graph.add(gtsam.PriorFactorPose3(X(j), gtsam.Pose3(R, np.zeros(3)),
                                             gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)))
            graph.add(ft.calibrated_inclinometer_factor(gtsam.noiseModel.Isotropic.Sigma(2, sigma), X(j),
                                                        z + rng.normal(0, sigma, 2), d,
                                                        {"bias": D, "scale": S, "accel_sensitivity": A}, {},
                                                        vibration=vibration))
            values.insert(X(j), gtsam.Pose3(R, np.zeros(3)))
        for key, dim in ((D, 2), (S, 1), (A, 1)):
            values.insert(key, np.zeros(dim))
        if from_accelerometer:
            prior = gtsam.imuBias.ConstantBias(truth["accel_bias"] + rng.normal(0, sigma_b, 3), np.zeros(3))
            graph.add(gtsam.PriorFactorConstantBias(B(0), prior, gtsam.noiseModel.Diagonal.Sigmas(
                np.array([sigma_b] * 3 + [1e-6] * 3))))
            values.insert(B(0), prior)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        marg = gtsam.Marginals(graph, result)
        e = [result.atVector(D) - truth["bias"], result.atVector(S) - truth["scale"],
             result.atVector(A) - truth["accel_sensitivity"]]
        s = [np.diag(marg.marginalCovariance(k)) for k in (D, S, A)]
        if from_accelerometer:
            e.append(result.atConstantBias(B(0)).accelerometer() - truth["accel_bias"])
            s.append(np.diag(marg.marginalCovariance(B(0)))[:3])
        err.append(np.concatenate(e))
        sig.append(np.sqrt(np.concatenate(s)))
    _assert_scatter_matches_sigma(np.array(err), np.array(sig))


def test_monte_carlo_scatter_of_prism_lever_arm_and_clock_offset_matches_reported_sigma():
    """Lever-arm correction and clock offset from tracker position blocks and velocities at 20 known poses
    (rotated +-0.2 rad, moving): scatter over 100 runs against the marginal sigmas (99.8 % chi-square bounds)."""
    rng = np.random.default_rng(8)
    runs, sigma_p, sigma_v, n = 100, 5e-4, 2e-3, 20
    r0, dr, dt = np.array([0.12, -0.05, 0.25]), np.array([0.01, -0.02, 0.005]), 0.02
    poses = [gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.2, 3)), rng.normal([30.0, 0, 0], 0.5)) for _ in range(n)]
    vel, acc, w = rng.normal(0, 0.1, (n, 5, 3)), rng.normal(0, 0.3, (n, 3)), rng.normal(0, 0.05, (n, 3))
    err, sig = [], []
    for _ in range(runs):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for j, pose in enumerate(poses):
            R, p = pose.rotation().matrix(), pose.translation()
            z = p + R @ (r0 + dr) - dt * vel[j] + rng.normal(0, sigma_p, (5, 3))
            zv = mt.prism_velocity_W(R, vel[j, -1], w[j], r0 + dr) - dt * acc[j] + rng.normal(0, sigma_v, 3)
            graph.add(gtsam.PriorFactorPose3(X(j), pose, gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)))
            graph.add(gtsam.PriorFactorVector(V(j), vel[j, -1], gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
            graph.add(ft.calibrated_prism_factor(gtsam.noiseModel.Isotropic.Sigma(15, sigma_p), X(j), z, r0, vel[j],
                                                 L, O))
            graph.add(ft.calibrated_prism_velocity_factor(gtsam.noiseModel.Isotropic.Sigma(3, sigma_v), X(j), V(j),
                                                          zv, w[j], r0 + dr, acc[j], O))
            values.insert(X(j), pose)
            values.insert(V(j), vel[j, -1])
        values.insert(L, np.zeros(3))
        values.insert(O, np.zeros(1))
        _solve_and_record(graph, values, L, O, dr, dt, err, sig)
    _assert_scatter_matches_sigma(np.array(err), np.array(sig))


def _audit(scenario_seed=3, noise_seed=None, **effects):
    nominal_offset = effects.pop("nominal_lever_error_m", None)
    sc = TrackerScenario(duration_s=20.0, seed=scenario_seed, burst_rate_per_min=6.0, steer_angle_deg=(1.0, 2.0),
                         steer_period_s=(20.0, 40.0), **effects)
    rec = sc.measurements(seed=scenario_seed + 1 if noise_seed is None else noise_seed)
    if nominal_offset is not None:  # sensor.yaml states a lever arm that is wrong by nominal_offset
        rec.sensors["tracker0"].meta["lever_arm_prism_m"] = (sc.r_P_B + nominal_offset).tolist()
    return sc, run_audit(TrackerAudit(estimator_for_audit(rec)))


def _assert_found(result, effect, key, truth):
    assert [f["effect"] for f in result.findings] == [effect], [(f["effect"], f["estimate"]) for f in result.findings]
    est, std = (np.atleast_1d(result.findings[0][k][key]) for k in ("estimate", "std"))
    assert np.all(np.abs(est - np.asarray(truth)) <= 3 * std), (est, std, truth)


def test_audit_finds_nothing_on_data_without_effects():
    _, result = _audit()
    assert result.findings == [], [(f["effect"], f["estimate"]) for f in result.findings]


@pytest.mark.slow
def test_audit_false_findings_over_noise_and_scenario_seeds():
    """Null runs (no effect): 20 noise seeds of the calibration scenario and 10 other scenarios (motion, bursts).
    The engine allows a false finding with probability 1e-3 per run (family-wise per step): P(>= 2 of 30) < 5e-4.
    (Before the inclinometer's averaging lag was modelled, incl_bias had p < 0.02 on 12 of 14 such runs.)"""
    runs = [(3, seed) for seed in range(100, 120)] + [(scenario, 4) for scenario in range(4, 14)]
    found = []
    for scenario, seed in runs:
        sc = TrackerScenario(duration_s=20.0, seed=scenario, burst_rate_per_min=6.0, steer_angle_deg=(1.0, 2.0),
                             steer_period_s=(20.0, 40.0))
        result = run_audit(TrackerAudit(estimator_for_audit(sc.measurements(seed=seed))))
        found += [(scenario, seed, f["effect"]) for f in result.findings]
    assert len(found) <= 1, found


@pytest.mark.parametrize("effect, kwargs, key, truth", [
    ("incl_bias", {"incl_bias_rad": (5e-4, -5e-4)}, "bias", [5e-4, -5e-4]),
    ("incl_accel_sensitivity", {"incl_accel_sensitivity": 0.3}, "sensitivity", 0.3),
])
def test_audit_names_a_hidden_inclinometer_effect(effect, kwargs, key, truth):
    _, result = _audit(**kwargs)
    _assert_found(result, effect, key, truth)


def test_audit_names_a_large_inclinometer_bias_not_a_lever_arm():
    """A constant (1.1, 4.2) mrad inclinometer offset tilts the attitude, which a 13 cm lever-arm error also
    mimics in the tracker and camera residuals; both score tests underflow to p = 0 and the catalog's order tries
    the lever arm first.  On this seed the bias then failed the held-out check next to it (3435 -> 3444) while the
    held-out comparison counted the tracker, inclinometer and camera residuals only: the held-out states had
    moved the misfit into the IMU factors.  With the whole held-out graph compared, the bias is named alone."""
    _, result = _audit(scenario_seed=4, incl_bias_rad=(1.1e-3, 4.2e-3))
    _assert_found(result, "incl_bias", "bias", [1.1e-3, 4.2e-3])


@pytest.mark.parametrize("scenario_seed", [3010, 3016, 3000])
def test_a_named_inclinometer_bias_leaves_no_stale_term_behind(scenario_seed):
    """The same (1.1, 4.2) mrad offset (~100 sigma) on the catalog benchmark's runs; the offset pulls the base
    fit's states.  (1) The inclinometer's vibration disturbance ``w a`` was computed once against the base fit's
    attitude and accelerometer bias; with the offset named it was stale, and a term in vibration was named beside
    it (3010: a product, 3016: poly1, p ~ 5e-9).  It is now predicted from the factor's own attitude and IMU bias
    variables.  (2) The library's drivers were the base fit's: its speed, which had followed the tilted gravity,
    left a distance term in speed beside the offset (3000: p = 3e-9).  They are now taken from the fit with the
    catalog effects named.  The offset is named alone."""
    _, result = _audit(scenario_seed=scenario_seed, noise_seed=1000 + scenario_seed, incl_bias_rad=(1.1e-3, 4.2e-3))
    _assert_found(result, "incl_bias", "bias", [1.1e-3, 4.2e-3])


def test_cli_audit_names_a_hidden_inclinometer_scale(tmp_path):
    """``selfcal audit REC --system tracker``: the JSON contract, and the scale error found and measured."""
    sc = TrackerScenario(duration_s=20.0, seed=3, burst_rate_per_min=6.0, steer_angle_deg=(1.0, 2.0),
                         steer_period_s=(20.0, 40.0), incl_scale=0.02)
    rec = sc.write(tmp_path / "rec", seed=4)
    out = tmp_path / "audit.json"
    assert main(["audit", str(rec), "--system", "tracker", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["system"] == "tracker" and report["base_model"] == "smoother"
    assert [f["effect"] for f in report["findings"]] == ["incl_scale"]
    f = report["findings"][0]
    assert abs(f["estimate"]["scale"] - 0.02) <= 3 * f["std"]["scale"]
    assert f["gain"]["heldout_rms_after"] < f["gain"]["heldout_rms_before"]
    assert set(report["residual_rms"]) == {"tracker0/position", "incl0/tilt", "cam0/bearing"}
    assert main(["audit", str(rec), "--system", "tracker", "--base", "nonsense"]) == 1


@pytest.mark.parametrize("scenario_seed, noise_seed", [(3, None), (3000, 4000)])
def test_audit_names_a_wrong_prism_lever_arm_or_says_it_cannot_tell_it_from_an_inclinometer_bias(scenario_seed,
                                                                                                 noise_seed):
    """sensor.yaml's lever arm is 3 cm too high.  The camera's beam elevation against the inclinometer's pitch shows
    the height, but seen from ~30 m a 3 cm height tilts the beam as a 1 mrad inclinometer pitch bias does: on
    noise-free data of the second scenario the two fits differ by 1.3 in chi-square.  The audit must either name the
    lever arm, sized within 3 sigma, or name the bias *and* say it cannot be told from the lever arm
    (``ambiguous_with``), never the bias alone.  The bias was named alone on most seeds while the audit kept the
    online pass's first-pose prior (1 cm, built with sensor.yaml's lever arm: the true lever arm paid 9.7 in it) and
    while the prism velocity factors ignored the lever-arm correction (``R (w x dr)``)."""
    sc, result = _audit(scenario_seed, noise_seed, nominal_lever_error_m=np.array([0.0, 0.0, 0.03]))
    named = [f["effect"] for f in result.findings]
    if named == ["incl_bias"]:
        rivals = [r["effect"] for r in result.findings[0].get("ambiguous_with", [])]
        assert "lever_arm_prism" in rivals, result.findings[0]
    else:
        _assert_found(result, "lever_arm_prism", "r_m", sc.r_P_B)


@pytest.mark.parametrize("offset_s", [0.03, 0.01])
def test_audit_names_a_tracker_clock_offset(offset_s):
    """The tracker stamps 30 ms (10 ms) late while the target is steered up and down (5-10 cm, 4-8 s periods):
    the audit names the offset alone and sizes it within 3 of its sigmas (~2 ms here)."""
    _, result = _audit(tracker_clock_offset_s=offset_s, steer_position_m=(0.05, 0.1),
                       steer_position_period_s=(4.0, 8.0), steer_position_axes=(0.0, 0.0, 1.0))
    _assert_found(result, "tracker_time_offset", "dt_s", offset_s)
    gain = result.findings[0]["gain"]
    assert gain["heldout_rms_after"] <= gain["heldout_rms_before"]


def _solve_and_record(graph, values, L, O, dr, dt, err, sig):
    """Solve one Monte Carlo run; append the (lever arm, offset) error and the marginal sigmas."""
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    marg = gtsam.Marginals(graph, result)
    err.append(np.concatenate([result.atVector(L) - dr, result.atVector(O) - dt]))
    sig.append(np.sqrt(np.concatenate([np.diag(marg.marginalCovariance(k)) for k in (L, O)])))


def _assert_scatter_matches_sigma(err, sig):
    """Scatter / reported variance inside the chi-square(runs - 1) 99.8 % band per component, and unbiased
    (mean error within 4 standard errors)."""
    runs = len(err)
    ratio = np.var(err, axis=0, ddof=1) / np.mean(np.square(sig), axis=0)
    lo, hi = stats.chi2.ppf(0.001, runs - 1) / (runs - 1), stats.chi2.ppf(0.999, runs - 1) / (runs - 1)
    assert np.all((ratio > lo) & (ratio < hi)), ratio
    assert np.all(np.abs(np.mean(err, axis=0)) < 4 * np.mean(sig, axis=0) / np.sqrt(runs))


def test_audit_names_a_clock_offset_whose_target_is_not_better_held_out():
    """benchmarks/audit_catalog_recall.py's tracker case, seed 3014: a 24 ms offset, the target steered 2-5 cm at
    4-8 s periods.  The score test gives F = 42 and the whole held-out graph falls 3839 -> 3811, but the tracker's own
    held-out residual rose by 1.3 (whitened; a third of its paired sampling sigma, 4.1): the state velocities bend
    to take part of the offset in either model.  'Its target not worse at all' refused the offset here; a target
    worse by more than one sampling sigma is refused now.  Sized within 3 of its sigmas (~4.7 ms here)."""
    sc = TrackerScenario(duration_s=20.0, seed=3014, burst_rate_per_min=6.0, steer_angle_deg=(1.0, 2.0),
                         steer_period_s=(20.0, 40.0), tracker_clock_offset_s=0.024, steer_position_m=(0.02, 0.05),
                         steer_position_period_s=(4.0, 8.0), steer_position_axes=(0.0, 0.0, 1.0))
    result = run_audit(TrackerAudit(estimator_for_audit(sc.measurements(seed=4014))))
    _assert_found(result, "tracker_time_offset", "dt_s", 0.024)
