"""Exports for Kalibr and OpenVINS, and the one camera key convention: every file is read back with a YAML
parser and checked against the estimate; conventions are checked by correcting raw samples both ways.

The intrinsics tests correct random raw samples with our equations (``f_S = M_a (a_raw - b_a)``,
``w_S = M_g (w_raw - b_g - A f_S)``) and with Kalibr's / OpenVINS's equations written out here from their
sources (docs/exports.md), using the matrices read back from the files: both must give the same vectors, up to
the frame rotation the files declare (``T_i_b``).
"""
from pathlib import Path

import numpy as np
import pytest
import yaml

from selfcal.audit.noise import kalibr_noise
from selfcal.cli.main import main
from selfcal.core.inertial import ImuNoise
from selfcal.core.so3 import exp
from selfcal.io.camera import camera_keys, read_camera
from selfcal.io.exports import kalibr_intrinsics, lq
from selfcal.io.recording import RecordingError, read_recording
from selfcal.sim.imu import ImuPairScenario, ImuScenario, random_intrinsics
from selfcal.sim.trajectories import HandheldTrajectory, MultiPositionTrajectory

RATE_HZ = 100.0


def random_ours(rng):
    """Our intrinsics of a MEMS-like IMU: M_a upper triangular, M_g full, A the g-sensitivity."""
    M_a = np.triu(np.eye(3) + 0.02 * rng.standard_normal((3, 3)))
    M_g = (np.eye(3) + 0.02 * rng.standard_normal((3, 3))) @ exp(0.01 * rng.standard_normal(3))
    return M_a, M_g, 1e-3 * rng.standard_normal((3, 3))


def correct_ours(a_raw, w_raw, b_a, b_g, M_a, M_g, A):
    f = M_a @ (a_raw - b_a)
    return f, M_g @ (w_raw - b_g - A @ f)


def correct_kalibr(a_raw, w_raw, b_a, b_g, M_acc, M_gyr, A, C_gyro_i):
    """Invert Kalibr's scale-misalignment model (IccSensors.py: a = M C_i_b a_b + b;
    w = M C_gyro_b w_b + A C_gyro_b a_b + b), in its IMU frame i."""
    f_i = np.linalg.solve(M_acc, a_raw - b_a)
    return f_i, C_gyro_i.T @ np.linalg.solve(M_gyr, w_raw - b_g - A @ C_gyro_i @ f_i)


def correct_openvins(a_m, w_m, b_a, b_g, imu):
    """OpenVINS Propagator.cpp: a = R_ACCtoIMU Da (a_m - b_a); w = R_GYROtoIMU Dw (w_m - b_g - Tg a), with the
    loader's Dw = inv(Tw), Da = inv(Ta), R_XtoIMU = R_IMUtoX^T and the kalibr model's lower triangles kept."""
    m = {k: np.array(imu[k], dtype=float) for k in ("Tw", "Ta", "Tg", "R_IMUtoGYRO", "R_IMUtoACC")}
    Dw, Da = np.tril(np.linalg.inv(m["Tw"])), np.tril(np.linalg.inv(m["Ta"]))
    a = m["R_IMUtoACC"].T @ Da @ (a_m - b_a)
    return a, m["R_IMUtoGYRO"].T @ Dw @ (w_m - b_g - m["Tg"] @ a)


def load_openvins(path):
    text = Path(path).read_text()
    assert text.startswith("%YAML:1.0\n")  # OpenCV FileStorage wants it; PyYAML does not know it
    return yaml.safe_load(text.split("\n", 1)[1])


# --- the conversions, numerically ----------------------------------------------------------------------------------

def test_lq_gives_lower_triangular_and_a_rotation():
    rng = np.random.default_rng(0)
    for _ in range(20):
        M = np.eye(3) + 0.05 * rng.standard_normal((3, 3))
        L, Q = lq(M)
        np.testing.assert_allclose(L @ Q, M, atol=1e-14)
        assert np.all(np.triu(L, 1) == 0) and np.all(np.diag(L) > 0)
        np.testing.assert_allclose(Q @ Q.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(Q) == pytest.approx(1.0)


@pytest.mark.parametrize("seed", range(5))
def test_kalibr_matrices_correct_raw_samples_as_ours_do(seed):
    rng = np.random.default_rng(seed)
    M_a, M_g, A = random_ours(rng)
    b_a, b_g = 0.05 * rng.standard_normal(3), 0.01 * rng.standard_normal(3)
    k = kalibr_intrinsics(M_a, M_g, A)
    assert np.all(np.triu(k.M_acc, 1) == 0) and np.all(np.triu(k.M_gyr, 1) == 0)  # Kalibr's estimated pattern
    for _ in range(10):
        a_raw, w_raw = 9.8 * rng.standard_normal(3), rng.standard_normal(3)
        f_S, w_S = correct_ours(a_raw, w_raw, b_a, b_g, M_a, M_g, A)
        f_i, w_i = correct_kalibr(a_raw, w_raw, b_a, b_g, k.M_acc, k.M_gyr, k.A, k.C_gyro_i)
        np.testing.assert_allclose(f_i, k.C_i_S @ f_S, rtol=0, atol=1e-12)
        np.testing.assert_allclose(w_i, k.C_i_S @ w_S, rtol=0, atol=1e-12)


# --- calibrate imu: the three files --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def imu_exports(tmp_path_factory):
    """One multi-position recording with intrinsics, g-sensitivity and noise; calibrated once, all exports."""
    tmp = tmp_path_factory.mktemp("imu")
    accel, gyro = random_intrinsics(3, g_sensitivity=2e-3)
    trajectory = MultiPositionTrajectory(n_poses=14, static_s=3.0, move_s=2.0, initial_static_s=20.0, seed=3)
    rec = ImuScenario(trajectory, accel=accel, gyro=gyro, rate_hz=RATE_HZ).write(tmp / "rec", seed=1)
    out = tmp / "out"
    code = main(["calibrate", "imu", str(rec), "--out", str(out / "cal.yaml"), "--kalibr", str(out / "imu.yaml"),
                 "--kalibr-chain", str(out / "chain.yaml"), "--openvins", str(out / "ov.yaml")])
    assert code in (0, None)
    cal = yaml.safe_load((out / "cal.yaml").read_text())["imu0"]
    return rec, out, cal


def test_kalibr_imu_yaml_has_kalibrs_keys_and_the_measured_white_noise(imu_exports, capsys):
    _, out, _ = imu_exports
    d = yaml.safe_load((out / "imu.yaml").read_text())
    assert set(d) == {"rostopic", "update_rate", "accelerometer_noise_density", "accelerometer_random_walk",
                      "gyroscope_noise_density", "gyroscope_random_walk"}
    assert d["rostopic"] == "/imu0" and d["update_rate"] == RATE_HZ
    # densities: the largest of three axes, each estimated from ~19 s at 100 Hz: the N line rests on taus up to
    # ~1 s, so each axis is known to a few percent (1 / sqrt(2 edf) at tau = 1 s with edf ~ 20: 16 %, pooled
    # over the short taus ~3 %); 10 % is over 3 sigma and still far from any other noise level
    truth = ImuNoise()
    assert d["accelerometer_noise_density"] == pytest.approx(truth.accelerometer_noise_density, rel=0.1)
    assert d["gyroscope_noise_density"] == pytest.approx(truth.gyroscope_noise_density, rel=0.1)
    # 19 s show no random walk: the sensor.yaml values are kept, and the comments say so
    assert d["accelerometer_random_walk"] == truth.accelerometer_random_walk
    assert d["gyroscope_random_walk"] == truth.gyroscope_random_walk
    assert (out / "imu.yaml").read_text().count("NOT MEASURED") == 2


def test_kalibr_chain_reads_back_and_corrects_as_our_result(imu_exports):
    _, out, cal = imu_exports
    imu = yaml.safe_load((out / "chain.yaml").read_text())["imu0"]
    assert imu["model"] == "scale-misalignment" and imu["time_offset"] == 0.0
    M_acc, M_gyr = np.array(imu["accelerometers"]["M"]), np.array(imu["gyroscopes"]["M"])
    A, C_gyro_i = (np.array(imu["gyroscopes"][k]) for k in ("A", "C_gyro_i"))
    T_i_b = np.array(imu["T_i_b"])
    assert M_acc.shape == M_gyr.shape == A.shape == C_gyro_i.shape == (3, 3) and T_i_b.shape == (4, 4)
    np.testing.assert_array_equal(T_i_b[:3, 3], 0.0)
    C_i_S = T_i_b[:3, :3]
    np.testing.assert_allclose(C_i_S @ C_i_S.T, np.eye(3), atol=1e-12)
    ours = [np.array(cal[s][k]) for s, k in (("accelerometers", "bias"), ("gyroscopes", "bias"),
                                             ("accelerometers", "M"), ("gyroscopes", "M"), ("gyroscopes", "A"))]
    rng = np.random.default_rng(7)
    for _ in range(10):
        a_raw, w_raw = 9.8 * rng.standard_normal(3), rng.standard_normal(3)
        f_S, w_S = correct_ours(a_raw, w_raw, *ours)
        f_i, w_i = correct_kalibr(a_raw, w_raw, ours[0], ours[1], M_acc, M_gyr, A, C_gyro_i)
        # the YAML holds float64 reprs: exact to round-off
        np.testing.assert_allclose(f_i, C_i_S @ f_S, rtol=0, atol=1e-12)
        np.testing.assert_allclose(w_i, C_i_S @ w_S, rtol=0, atol=1e-12)
    noise = yaml.safe_load((out / "imu.yaml").read_text())
    assert all(imu[k] == pytest.approx(v) for k, v in noise.items() if k.endswith(("density", "walk")))


def test_openvins_file_reads_back_and_corrects_as_our_result(imu_exports):
    _, out, cal = imu_exports
    imu = load_openvins(out / "ov.yaml")["imu0"]
    assert imu["model"] == "kalibr"
    for key in ("Tw", "Ta", "Tg", "R_IMUtoGYRO", "R_IMUtoACC"):
        assert np.array(imu[key]).shape == (3, 3), key
    # the kalibr model keeps only the lower triangles of Dw, Da: nothing may be lost there
    for key in ("Tw", "Ta"):
        D = np.linalg.inv(np.array(imu[key]))
        np.testing.assert_allclose(np.triu(D, 1), 0.0, atol=1e-15)
    np.testing.assert_array_equal(imu["R_IMUtoACC"], np.eye(3))
    C_i_S = np.array(imu["T_i_b"])[:3, :3]
    b_a, b_g = np.array(cal["accelerometers"]["bias"]), np.array(cal["gyroscopes"]["bias"])
    M_a, M_g, A = (np.array(cal[s][k]) for s, k in (("accelerometers", "M"), ("gyroscopes", "M"), ("gyroscopes", "A")))
    rng = np.random.default_rng(8)
    for _ in range(10):
        a_m, w_m = 9.8 * rng.standard_normal(3), rng.standard_normal(3)
        f_S, w_S = correct_ours(a_m, w_m, b_a, b_g, M_a, M_g, A)
        f_I, w_I = correct_openvins(a_m, w_m, b_a, b_g, imu)
        np.testing.assert_allclose(f_I, C_i_S @ f_S, rtol=0, atol=1e-12)
        np.testing.assert_allclose(w_I, C_i_S @ w_S, rtol=0, atol=1e-12)
    for key in ("accelerometer_noise_density", "gyroscope_noise_density", "accelerometer_random_walk",
                "gyroscope_random_walk"):
        assert imu[key] > 0, key  # OpenVINS requires all four


def test_exports_need_one_imu(capsys, tmp_path):
    sc = ImuPairScenario.random(HandheldTrajectory(15.0, seed=1), seed=1, intrinsics=False)
    rec = sc.write(tmp_path / "rec")
    code = main(["calibrate", "imu", str(rec), "--kalibr", str(tmp_path / "imu.yaml")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and "--imu" in err[0]
    assert not (tmp_path / "imu.yaml").exists()


# --- the noise figures -----------------------------------------------------------------------------------------------

def white_plus_walk(rng, n, density, walk, rate_hz=RATE_HZ):
    return (rng.standard_normal((n, 3)) * density * np.sqrt(rate_hz)
            + np.cumsum(rng.standard_normal((n, 3)) * walk / np.sqrt(rate_hz), axis=0))


def test_random_walk_measured_on_a_long_rest_within_three_sigma():
    # 20 min at 100 Hz; K chosen so that the +1/2 line crosses the white line at tau = sqrt(3) N / K ~ 1.7 s,
    # far inside the curve (taus to 150 s): every axis must show it
    N, K = 1e-3, 1e-3
    n = kalibr_noise(white_plus_walk(np.random.default_rng(3), 120_000, N, K), RATE_HZ, "gyro")
    assert n.random_walk_seen and np.all(np.isfinite(n.random_walk))
    assert np.all(np.abs(n.white_density - N) < 3 * n.white_density_std)
    assert np.all(np.abs(n.random_walk - K) < 3 * n.random_walk_std)


def test_random_walk_bound_holds_the_truth_and_shrinks_with_the_rest():
    # white noise plus a random walk too small to see in 40 s: the bound must lie above the true K, and it
    # follows the longest tau, sigma(tau_max) sqrt(3 / tau_max) = N sqrt(3) / tau_max for white noise
    N, K = 1e-3, 1e-5
    rng = np.random.default_rng(4)
    short = kalibr_noise(white_plus_walk(rng, 4_000, N, K), RATE_HZ, "accel")
    longer = kalibr_noise(white_plus_walk(rng, 16_000, N, K), RATE_HZ, "accel")
    for n in (short, longer):
        assert not n.random_walk_seen
        assert np.all(n.random_walk_bound > K)
        assert np.all(n.random_walk_bound >= 0.5 * N * np.sqrt(3) / n.tau_max_s)
    assert np.max(longer.random_walk_bound) < np.min(short.random_walk_bound)


# --- calibrate imu-pair ----------------------------------------------------------------------------------------------

def test_pair_result_T_and_kalibr_chain(tmp_path):
    sc = ImuPairScenario.random(HandheldTrajectory(30.0, seed=4), seed=4, intrinsics=False)
    rec = sc.write(tmp_path / "rec", seed=2)
    assert main(["calibrate", "imu-pair", str(rec), "--out", str(tmp_path / "pair.yaml"),
                 "--kalibr", str(tmp_path / "chain.yaml")]) in (0, None)
    pair = yaml.safe_load((tmp_path / "pair.yaml").read_text())
    T = np.array(pair["T_imu0_imu1"])
    R, r = np.array(pair["rotation_imu0_imu1"]), np.array(pair["lever_arm_m"])
    np.testing.assert_array_equal(T[:3, :3], R)
    np.testing.assert_array_equal(T[:3, 3], r)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    # p_imu0 = T p_imu1: imu1's origin is at the lever arm, imu1's axes are the columns of R; against the truth
    truth = sc.truth()["pair"]
    np.testing.assert_allclose(T[:3, 3], truth["lever_arm_m"], atol=5 * max(pair["lever_arm_sigma_m"]))
    chain = yaml.safe_load((tmp_path / "chain.yaml").read_text())
    assert set(chain) == {"imu0", "imu1"}
    np.testing.assert_array_equal(chain["imu0"]["T_i_b"], np.eye(4))
    assert chain["imu0"]["time_offset"] == 0.0
    imu1 = chain["imu1"]
    T_i_b = np.array(imu1["T_i_b"])
    # Kalibr (IccImu.updateImuConfig): rotation C_i_b maps imu0 (body) vectors into imu1, translation r_b is
    # imu1's position in the body frame, as the accelerometer error term uses it
    np.testing.assert_allclose(T_i_b[:3, :3], R.T, atol=1e-15)
    np.testing.assert_array_equal(T_i_b[:3, 3], r)
    # Kalibr's time offset: imu1 stamp + time_offset = reference time; ours t_imu0 = t_imu1 + dt: the same number
    assert imu1["time_offset"] == pair["time_offset_s"]
    assert imu1["time_offset"] == pytest.approx(truth["time_offset_s"], abs=5 * pair["time_offset_sigma_s"])
    assert imu1["model"] == "calibrated" and imu1["rostopic"] == "/imu1"


# --- camera keys -------------------------------------------------------------------------------------------------------

def test_camera_keys_round_trip_and_old_keys_still_read():
    K = np.array([[1200.0, 0, 320.5], [0, 1190.0, 240.25], [0, 0, 1]])
    four = np.array([-0.12, 0.05, 1e-4, -2e-4, 0.0])
    d = yaml.safe_load(yaml.safe_dump(camera_keys(K, four, (640, 480))))
    assert d == {"camera_model": "pinhole", "intrinsics": [1200.0, 1190.0, 320.5, 240.25],
                 "distortion_model": "radial-tangential", "distortion_coefficients": four[:4].tolist(),
                 "resolution": [640, 480]}
    cam = read_camera(d)
    np.testing.assert_array_equal(cam.K, K)
    np.testing.assert_array_equal(cam.dist, four)
    assert cam.resolution == (640, 480)
    five = four + [0, 0, 0, 0, 0.01]  # k3 kept as the fifth coefficient (OpenCV's order)
    assert camera_keys(K, five)["distortion_coefficients"] == five.tolist()
    np.testing.assert_array_equal(read_camera(camera_keys(K, five)).dist, five)
    old_tracker = read_camera({"camera_matrix": K.tolist(), "dist_coeffs": five.tolist()})
    old_scan = read_camera({"K": K.tolist(), "dist": four.tolist(), "width_px": 2048})
    np.testing.assert_array_equal(old_tracker.dist, five)
    np.testing.assert_array_equal(old_scan.K, K)
    assert old_scan.resolution == (2048, 1)
    with pytest.raises(RecordingError, match="distortion_model"):
        read_camera({**d, "distortion_model": "equidistant"})
    with pytest.raises(RecordingError, match="intrinsics"):
        read_camera({"intrinsics": [1, 2, 3]})


def test_tracker_and_scan_recordings_write_the_shared_keys(tmp_path):
    from selfcal.pipelines.tracker import noise_from_meta
    from selfcal.sim.scan import default_stereo, LineCamera
    from selfcal.sim.tracker import TrackerScenario
    sc = TrackerScenario(duration_s=2.0, seed=0)
    cam0 = sc.measurements(seed=None).sensors["cam0"].meta
    assert {"camera_model", "intrinsics", "distortion_model", "distortion_coefficients", "resolution"} <= set(cam0)
    assert "camera_matrix" not in cam0 and "dist_coeffs" not in cam0
    n = noise_from_meta({"cam0": cam0})
    np.testing.assert_array_equal(n.camera_matrix, sc.camera_matrix)
    np.testing.assert_array_equal(n.dist_coeffs, sc.dist_coeffs)
    left, _ = default_stereo()
    d = left.to_dict()
    assert "K" not in d and d["resolution"] == [2048, 1]
    back = LineCamera.from_dict(yaml.safe_load(yaml.safe_dump(d)))
    np.testing.assert_array_equal(back.K, left.K)
    np.testing.assert_array_equal(back.dist, left.dist)
    assert back.width_px == left.width_px


def test_no_declared_random_walk_writes_the_bound_and_says_so(imu_exports):
    from selfcal.pipelines.imu import kalibr_noise_values
    rec, out, _ = imu_exports
    data = read_recording(rec).imu("imu0")
    data.meta = {k: v for k, v in data.meta.items() if not k.endswith("random_walk")}
    values, note = kalibr_noise_values(data)
    assert "too short" in note and "\n" not in note
    text = (out / "imu.yaml").read_text()
    for key, unit in (("accelerometer_random_walk", "m s^-3 / sqrt(Hz)"), ("gyroscope_random_walk", "rad s^-2 / sqrt(Hz)")):
        assert "upper bound" in values[key].comment
        # the bound is above the true random walk (ImuNoise defaults) and not absurdly so: a +1/2 line through
        # the curve's last octave (~1.2 s) of white noise, N sqrt(3) / tau_max, times the one-sigma margin
        true_walk = getattr(ImuNoise(), key)
        assert values[key].value > true_walk
        density = values[key.replace("random_walk", "noise_density")].value
        assert values[key].value < 3 * density * np.sqrt(3.0) / 1.0
        assert f"{key}: " in text and unit in text
    for unit in ("m s^-2 / sqrt(Hz)", "rad s^-1 / sqrt(Hz)"):
        assert unit in text


def test_short_gauss_markov_is_no_random_walk_on_real_xsens_data():
    # the Xsens MTi's internal filter correlates its accelerometer noise over ~10 ms: the audit accepts a
    # Gauss-Markov term there, whose short-tau equivalent sigma sqrt(2 / T) (~0.06 m s^-3 / sqrt(Hz)) is no
    # random walk of the bias; Kalibr's key must not get it
    from selfcal.audit.noise import noise_audit
    from selfcal.core.static_intervals import detect_static_intervals
    data = read_recording(Path(__file__).resolve().parents[1] / "data" / "xsens_mti_multiposition").imu("imu0")
    start, end = max(detect_static_intervals(data.t_s, data.accel_m_s2), key=lambda run: run[1] - run[0])
    rest = data.accel_m_s2[start:end]
    finals = [a.final for a in noise_audit(rest, data.rate_hz, "accel").axes]
    short = [f for f in finals if f.model == "gauss_markov" and f.params["tau_s"] < 1.0]
    assert short, [f.model for f in finals]  # the case this test is about is present
    n = kalibr_noise(rest, data.rate_hz, "accel")
    assert not n.random_walk_seen
