"""Tracker simulator (selfcal.sim.tracker) and models (selfcal.models.tracker): physics checks on exact data."""
import gtsam
import numpy as np
import pytest
from scipy import stats

from selfcal.core import inertial
from selfcal.core.stats import wishart_lambda_max_quantile, wishart_lambda_min_quantile
from selfcal.io.recording import read_recording
from selfcal.models import tracker as mt
from selfcal.sim.tracker import Fault, TrackerScenario


@pytest.fixture(scope="module")
def scenario():
    return TrackerScenario(duration_s=30.0, seed=3, burst_rate_per_min=6.0)


def test_exact_imu_preintegrates_to_the_truth(scenario):
    """IMU samples made for zero-order-hold integration: 10 s of preintegration lands on the true state."""
    sc = scenario
    rec = sc.measurements(None)
    imu = rec.imu("imu0")
    t = (imu.t_ns - sc.t0_ns) * 1e-9
    bg, ba = sc.truth_bias(t)
    R, p, v, *_ = sc.kinematics(t)
    params = gtsam.PreintegrationParams.MakeSharedU(sc.gravity_m_s2)
    params.setAccelerometerCovariance(np.eye(3))
    params.setGyroscopeCovariance(np.eye(3))
    params.setIntegrationCovariance(np.eye(3))
    pim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias())
    n = 2000
    for k in range(n):
        pim.integrateMeasurement(imu.accel_m_s2[k] - ba[k], imu.gyro_rad_s[k] - bg[k], 0.005)
    pred = pim.predict(gtsam.NavState(gtsam.Rot3(R[0]), p[0], v[0]), gtsam.imuBias.ConstantBias())
    np.testing.assert_allclose(gtsam.Rot3(R[n]).localCoordinates(pred.attitude()), 0, atol=1e-9)
    np.testing.assert_allclose(pred.velocity(), v[n], atol=1e-8)  # float64 rounding over 2000 steps
    # trapezoid position: O(dt^3 jerk) per step, vibration jerk <= (2 pi 25 Hz) 0.3 m/s^2 ~ 50 m/s^3
    np.testing.assert_allclose(pred.position(), p[n], atol=2000 * 50 * 0.005**3 / 12)


def test_measurement_models_roundtrip(scenario):
    sc = scenario
    rng = np.random.default_rng(0)
    roll, pitch = rng.uniform(-0.3, 0.3, 50), rng.uniform(-0.3, 0.3, 50)
    r2, p2 = inertial.tilt_from_specific_force(9.81 * mt.up_direction_B(roll, pitch))
    np.testing.assert_allclose(np.c_[r2, p2], np.c_[roll, pitch], atol=1e-12)
    r3, p3 = mt.tilt_from_axis_angles(*mt.axis_angles_from_tilt(roll, pitch))
    np.testing.assert_allclose(np.c_[r3, p3], np.c_[roll, pitch], atol=1e-12)
    d = np.c_[rng.normal(0, 0.1, (50, 2)), np.ones(50)]
    uv = mt.pixel_from_direction_C(d, sc.camera_matrix, sc.dist_coeffs)
    b = mt.bearing_from_pixel(uv, sc.camera_matrix, sc.dist_coeffs)
    np.testing.assert_allclose(b, d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-9)


def test_double_vector_attitude_recovers_truth(scenario):
    sc = scenario
    rec = sc.measurements(None)
    inc, cam = rec.sensors["incl0"], rec.sensors["cam0"]
    t = (inc.t_ns - sc.t0_ns) * 1e-9
    R, p = sc.truth_pose(t)
    b = mt.bearing_from_pixel(np.c_[cam.values["u"], cam.values["v"]], sc.camera_matrix, sc.dist_coeffs)
    quiet = [i for i, ti in enumerate(t) if not any(x.start_s <= ti <= x.start_s + x.duration_s for x in sc.bursts)]
    for i in quiet[::25]:
        p_cam = p[i] + R[i] @ sc.r_C_B
        R_est = mt.attitude_from_tilt_and_beam(inc.values["roll"][i], inc.values["pitch"][i], sc.R_B_C @ b[i],
                                               -p_cam / np.linalg.norm(p_cam))
        # the inclinometer's 20 ms average lags the steering by ~1e-6 rad
        assert np.linalg.norm(gtsam.Rot3(R[i]).localCoordinates(gtsam.Rot3(R_est))) < 1e-5


def test_noise_levels_and_faults_in_the_recording():
    sc = TrackerScenario(duration_s=60.0, seed=5, burst_rate_per_min=0.0, faults=[
        Fault("incl0", "spike", 10.0, 10.05, 0.02, 0), Fault("tracker0", "dropout", 20.0, 23.0),
        Fault("tracker0", "jump", 30.0, 30.1, 0.01, 0, (0.0, 0.0, 1.0)), Fault("incl0", "stuck", 40.0, 45.0)])
    exact, noisy = sc.measurements(None), sc.measurements(seed=1)
    tr_e, tr_n = exact.sensors["tracker0"], noisy.sensors["tracker0"]
    t = (tr_e.t_ns - sc.t0_ns) * 1e-9
    assert not np.any((t >= 20.0) & (t < 23.0))  # beam break: no tracker sample
    assert len(tr_e.t_ns) == 60 * 50 + 1 - 150
    clean = (t < 30.0) | (t >= 30.1)
    dx = tr_n.values["x"][clean] - tr_e.values["x"][clean]
    n = dx.size  # sample variance within 99.9 % chi-square bounds of the stated sigma
    ratio = np.var(dx, ddof=1) / sc.tracker_sigma_m**2
    assert stats.chi2.ppf(0.0005, n - 1) / (n - 1) < ratio < stats.chi2.ppf(0.9995, n - 1) / (n - 1)
    jump = (t >= 30.0) & (t < 30.1)
    assert jump.sum() == 5
    z = tr_e.values["z"]
    np.testing.assert_allclose(z[jump] - np.interp(t[jump], t[~jump], z[~jump]), 0.01, atol=1e-5)
    inc = exact.sensors["incl0"]
    ti = (inc.t_ns - sc.t0_ns) * 1e-9
    spike = np.argmin(np.abs(ti - 10.0))
    assert abs(inc.values["roll"][spike] - 0.5 * (inc.values["roll"][spike - 1] + inc.values["roll"][spike + 1])
               - 0.02) < 1e-5
    stuck = (ti >= 40.0) & (ti < 45.0)
    assert np.ptp(inc.values["roll"][stuck]) == 0.0 and np.ptp(inc.values["pitch"][stuck]) == 0.0


def test_stream_equals_recording_and_is_seeded(tmp_path):
    sc = TrackerScenario(duration_s=70.0, seed=2)  # two 60 s chunks
    rec = sc.measurements(seed=4)
    events = list(sc.stream(seed=4))
    imu = [e for e in events if e[0] == "imu0"]
    assert [e[1] for e in imu] == rec.sensors["imu0"].t_ns.tolist()
    np.testing.assert_array_equal([e[2]["a_RS_S_z"] for e in imu], rec.sensors["imu0"].values["a_RS_S_z"])
    cams = [e for e in events if e[0] == "cam0"]
    np.testing.assert_array_equal([e[2]["u"] for e in cams], rec.sensors["cam0"].values["u"])
    assert all(a[1] <= b[1] for a, b in zip(events, events[1:]))  # timestamp order
    path = sc.write(tmp_path / "rec", seed=4)
    back = read_recording(path)
    np.testing.assert_array_equal(back.sensors["incl0"].values["roll"], rec.sensors["incl0"].values["roll"])
    assert (path / "truth" / "truth.yaml").is_file() and (path / "truth" / "poses.tum").is_file()
    again = TrackerScenario(duration_s=70.0, seed=2).measurements(seed=4)
    np.testing.assert_array_equal(again.sensors["tracker0"].values["x"], rec.sensors["tracker0"].values["x"])


def test_wishart_quantiles_against_exact_and_brute_force():
    """m = 1 is chi2(n): the Monte Carlo quantile must match scipy's; m = 2 closed form against brute-force
    eigenvalues of Gaussian matrices (exceedance fraction within 4 binomial sigmas)."""
    n, alpha = 30, 1e-3
    q1 = wishart_lambda_max_quantile(1, n, alpha, draws=2_000_000)
    # the quantile's relative Monte Carlo error: sqrt(alpha (1 - alpha) / N) / (f(q) q) ~ 0.5 %
    assert abs(q1 / stats.chi2.ppf(1 - alpha, n) - 1) < 0.02
    rng = np.random.default_rng(3)
    N, a = 200_000, 0.01
    Y = rng.standard_normal((N, n, 2))
    eig = np.linalg.eigvalsh(np.einsum("kni,knj->kij", Y, Y))
    for lam, q, tail in ((eig[:, -1], wishart_lambda_max_quantile(2, n, a), lambda x, q: x > q),
                         (eig[:, 0], wishart_lambda_min_quantile(2, n, a), lambda x, q: x < q)):
        frac = np.mean(tail(lam, q))
        assert abs(frac - a) < 4 * np.sqrt(a * (1 - a) / N), frac
