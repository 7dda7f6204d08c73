"""Simulated IMU scenarios: reproducible, physically consistent, truth kept apart from the measurements."""
import numpy as np
import pytest
import yaml

from selfcal.core import inertial
from selfcal.io.recording import read_recording, read_truth
from selfcal.models import imu
from selfcal.core import so3
from selfcal.sim.imu import AuxChannel, ImuPairScenario, ImuScenario, TemperatureProfile, random_intrinsics
from selfcal.core.inertial import ImuNoise
from selfcal.sim.trajectories import E_Z, HandheldTrajectory, MultiPositionTrajectory

G = 9.80665


def multi_position(seed=1, **kw):
    kw = {"n_poses": 12, "static_s": 2.0, "move_s": 2.0, "initial_static_s": 4.0, **kw}
    return MultiPositionTrajectory(seed=seed, **kw)


def handheld(duration_s, seed):
    return HandheldTrajectory(duration_s, seed=seed, static_start_s=2.0, static_end_s=2.0)


def full_scenario(seed=1, **kw):
    """Every single-IMU effect present: biases, scales, misalignments, g-sensitivity, temperature, a channel."""
    accel, gyro = random_intrinsics(seed, g_sensitivity=1e-4, accel_temperature_slope=1e-3,
                                    gyro_temperature_slope=1e-4)
    voltage = AuxChannel(lambda t: 5.0 + 0.05 * np.sin(0.3 * t), "V", accel_slope=[0.02, 0.0, -0.01],
                         gyro_slope=[0.0, 1e-3, 0.0], reference=5.0)
    return ImuScenario(multi_position(seed), accel, gyro, temperature=TemperatureProfile(20.0, 35.0, 30.0),
                       channels={"supply_voltage": voltage}, **kw)


def assert_same(rec_a, rec_b):
    assert rec_a.sensors.keys() == rec_b.sensors.keys()
    for name in rec_a.sensors:
        a, b = rec_a.sensors[name], rec_b.sensors[name]
        assert np.array_equal(a.t_ns, b.t_ns) and a.values.keys() == b.values.keys() and a.meta == b.meta
        for col in a.values:
            assert np.array_equal(a.values[col], b.values[col]), (name, col)


def in_static(t_s, intervals):
    return np.any([(t_s >= s) & (t_s <= e) for s, e in intervals], axis=0)


# --- reproducibility -------------------------------------------------------------------------------------------

def test_same_seed_same_recording_other_seed_differs():
    assert_same(full_scenario(3).exact_measurements(), full_scenario(3).exact_measurements())
    assert_same(full_scenario(3).perturbed_measurements(7), full_scenario(3).perturbed_measurements(7))
    a = full_scenario(3).perturbed_measurements(7).imu("imu0")
    b = full_scenario(3).perturbed_measurements(8).imu("imu0")
    assert np.all(a.accel_m_s2 != b.accel_m_s2) and np.all(a.gyro_rad_s != b.gyro_rad_s)
    assert not np.allclose(multi_position(1).pose_R_W_S, multi_position(2).pose_R_W_S)
    assert not np.allclose(handheld(10.0, seed=1).evaluate(5.0).w_S,
                           handheld(10.0, seed=2).evaluate(5.0).w_S)
    pair = ImuPairScenario.random(handheld(10.0, seed=1), seed=5)
    assert_same(pair.perturbed_measurements(1), ImuPairScenario.random(handheld(10.0, seed=1),
                                                                       seed=5).perturbed_measurements(1))


# --- the trajectories ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("trajectory", [multi_position(4), handheld(20.0, seed=4)], ids=["multi", "hand"])
def test_trajectory_derivatives_agree_with_central_differences(trajectory):
    """w from R, w_dot from w, v from p, a from v: central differences with h = 1e-5 s (error O(h^2) ~ 1e-9)."""
    t = np.linspace(-1.0, trajectory.duration_s + 1.0, 4001)
    h = 1e-5
    now, before, after = trajectory.evaluate(t), trajectory.evaluate(t - h), trajectory.evaluate(t + h)
    w_numerical = so3.log(np.einsum("nji,njk->nik", before.R_W_S, after.R_W_S)) / (2 * h)
    np.testing.assert_allclose(now.w_S, w_numerical, atol=1e-8)
    np.testing.assert_allclose(now.w_dot_S, (after.w_S - before.w_S) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(now.v_W, (after.p_W - before.p_W) / (2 * h), atol=1e-8)
    np.testing.assert_allclose(now.a_W, (after.v_W - before.v_W) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(now.R_W_S @ np.transpose(now.R_W_S, (0, 2, 1)),
                               np.broadcast_to(np.eye(3), now.R_W_S.shape), atol=1e-13)
    rest = in_static(t, trajectory.static_intervals_s)
    assert rest.sum() > 100
    for x in (now.w_S, now.w_dot_S, now.v_W, now.a_W):
        assert np.all(x[rest] == 0.0)


def test_multi_position_geometry():
    for seed in range(5):
        tr = multi_position(seed, n_poses=15)
        assert np.max(np.degrees(np.linalg.norm(tr.move_rotvec, axis=1))) <= 120.0
        np.testing.assert_allclose(tr.up_S[0], E_Z, atol=1e-15)  # starts level
        np.testing.assert_allclose(np.einsum("nji,j->ni", tr.pose_R_W_S, E_Z), tr.up_S, atol=1e-12)
        # gravity directions well spread: for points evenly on the sphere the scatter matrix is (n/3) I
        assert np.min(np.linalg.eigvalsh(tr.up_S.T @ tr.up_S)) > 0.8 * tr.n_poses / 3
        lengths = np.diff(tr.static_intervals_s, axis=1).ravel()
        np.testing.assert_allclose(lengths, [4.0] + [2.0] * 14)
        np.testing.assert_allclose(tr.evaluate([s for s, _ in tr.static_intervals_s]).R_W_S, tr.pose_R_W_S,
                                   atol=1e-15)


def test_handheld_excitation():
    tr = HandheldTrajectory(60.0, seed=3)
    s = tr.evaluate(np.arange(11.0, 57.0, 0.005))
    rate_rms = np.sqrt(np.mean(s.w_S**2, axis=0))
    accel_rms = np.sqrt(np.mean(s.a_W**2, axis=0))
    assert np.all((rate_rms > 0.5) & (rate_rms < 3.0)), rate_rms
    assert np.all((accel_rms > 1.0) & (accel_rms < 5.0)), accel_rms
    assert tr.static_intervals_s == [(0.0, 10.0), (58.0, 60.0)]


def test_body_rate_integrates_to_the_pose_change():
    """Zero-order-hold integration of w over each move reproduces R_k^T R_{k+1}.

    With the wobble the rotation axis turns during a move and the ZOH product has the second-order coning
    error: measured 4.7e-6 rad (max over 11 moves) at 100 Hz, 4.7e-8 rad at 1 kHz, 4.7e-10 rad at 10 kHz.
    Without it every move turns about one fixed axis, the steps commute and only the rectangle rule's error
    on a septic profile remains, O(h^4): 1.8e-9 rad at 100 Hz, 1.8e-13 rad at 1 kHz.
    """
    def worst_error(trajectory, rate_hz):
        errors = []
        for k in range(trajectory.n_poses - 1):
            start, end = trajectory.static_intervals_s[k][1], trajectory.static_intervals_s[k + 1][0]
            n = int(round((end - start) * rate_hz))
            w = trajectory.evaluate(start + np.arange(n) / rate_hz).w_S
            delta_R = so3.integrate_rates(w, np.full(n, 1.0 / rate_hz))
            true = trajectory.pose_R_W_S[k].T @ trajectory.pose_R_W_S[k + 1]
            errors.append(np.linalg.norm(so3.log(true.T @ delta_R)))
        return max(errors)

    wobbling = multi_position(1)
    e100, e1k = worst_error(wobbling, 100.0), worst_error(wobbling, 1000.0)
    assert 1e-6 < e100 < 1e-5
    assert 80 < e100 / e1k < 120  # second order: 10x the rate, 100x smaller
    straight = multi_position(1, wobble_rad=0.0)
    e100, e1k = worst_error(straight, 100.0), worst_error(straight, 1000.0)
    assert e100 < 1e-8 and e1k < 1e-11  # fourth order (h^4 would give 1e4x; rounding takes over near 1e-13)


# --- single IMU --------------------------------------------------------------------------------------------------

def test_exact_static_measurements_read_gravity_and_bias():
    scenario = full_scenario(2)
    data = scenario.exact_measurements().imu("imu0")
    temperature = data.channels["temperature"]
    t_s = data.t_s
    c = data.channels["supply_voltage"] - 5.0
    a_raw = data.accel_m_s2 - np.outer(c, [0.02, 0.0, -0.01])  # remove the hidden channel effect
    w_raw = data.gyro_rad_s - np.outer(c, [0.0, 1e-3, 0.0])
    f = scenario.accel.specific_force(a_raw, temperature)
    rest = in_static(t_s, scenario.trajectory.static_intervals_s)
    assert rest.sum() > 0.5 * len(t_s)
    np.testing.assert_allclose(np.linalg.norm(f[rest], axis=1), G, rtol=0, atol=1e-9)
    up = np.einsum("nji,j->ni", scenario.trajectory.evaluate(t_s[rest]).R_W_S, E_Z)
    np.testing.assert_allclose(f[rest], G * up, atol=1e-9)
    expected_gyro = scenario.gyro.bias_at(temperature[rest]) + f[rest] @ scenario.gyro.A.T
    np.testing.assert_allclose(w_raw[rest], expected_gyro, atol=1e-12)
    np.testing.assert_allclose(scenario.gyro.rate(w_raw, f, temperature)[rest], 0.0, atol=1e-12)
    np.testing.assert_allclose(temperature, TemperatureProfile(20.0, 35.0, 30.0)(t_s))
    assert data.channel_units == {"temperature": "degC", "supply_voltage": "V"}


def test_exact_measurements_invert_to_the_true_motion():
    scenario = full_scenario(5)
    data = scenario.exact_measurements().imu("imu0")
    truth = scenario.trajectory.evaluate(data.t_s)
    c = data.channels["supply_voltage"] - 5.0
    f = scenario.accel.specific_force(data.accel_m_s2 - np.outer(c, [0.02, 0.0, -0.01]), data.channels["temperature"])
    w = scenario.gyro.rate(data.gyro_rad_s - np.outer(c, [0.0, 1e-3, 0.0]), f, data.channels["temperature"])
    np.testing.assert_allclose(f, truth.specific_force_S(G), atol=1e-9)
    np.testing.assert_allclose(w, truth.w_S, atol=1e-12)


def test_noise_has_the_stated_sigma():
    """Perturbed - exact = white noise + bias walk, each with the stated discrete sigma.

    Bound: the sample std s of n Gaussian samples has relative sd 1/sqrt(2(n-1)) (chi-square, large n); we
    allow 5 of those per axis (n = 40001: 2.5 %), and 5 sigma/sqrt(n) on the mean.
    """
    noise = ImuNoise(accelerometer_noise_density=3e-3, gyroscope_noise_density=2e-4,
                     accelerometer_random_walk=1e-3, gyroscope_random_walk=5e-5)
    rate = 400.0
    scenario = ImuScenario(handheld(100.0, seed=1), noise=noise, rate_hz=rate)
    exact = scenario.exact_measurements().imu("imu0")
    perturbed = scenario.perturbed_measurements(11).imu("imu0")
    parts = scenario.noise_realisation(11)["imu0"]
    np.testing.assert_allclose(perturbed.accel_m_s2 - exact.accel_m_s2, parts["accel_white"] + parts["accel_walk"],
                               atol=1e-12)
    np.testing.assert_allclose(perturbed.gyro_rad_s - exact.gyro_rad_s, parts["gyro_white"] + parts["gyro_walk"],
                               atol=1e-12)
    n = len(exact.t_ns)
    assert n == 40001
    tolerance = 5.0 / np.sqrt(2 * (n - 1))
    checks = {"accel_white": parts["accel_white"], "gyro_white": parts["gyro_white"],
              "accel_walk": np.diff(parts["accel_walk"], axis=0), "gyro_walk": np.diff(parts["gyro_walk"], axis=0)}
    sigmas = {"accel_white": noise.accelerometer_noise_density * np.sqrt(rate),
              "gyro_white": noise.gyroscope_noise_density * np.sqrt(rate),
              "accel_walk": noise.accelerometer_random_walk / np.sqrt(rate),
              "gyro_walk": noise.gyroscope_random_walk / np.sqrt(rate)}
    for key, x in checks.items():
        np.testing.assert_allclose(x.std(axis=0, ddof=1) / sigmas[key], 1.0, atol=tolerance, err_msg=key)
        assert np.all(np.abs(x.mean(axis=0)) < 5 * sigmas[key] / np.sqrt(len(x))), key
    assert np.all(parts["accel_walk"][0] == 0) and np.all(parts["gyro_walk"][0] == 0)
    zero = ImuScenario(handheld(10.0, seed=1), noise=ImuNoise.zero())
    assert_same(zero.exact_measurements(), zero.perturbed_measurements(3))


def test_noise_from_sensor_yaml():
    noise = ImuNoise(1e-3, 2e-4, 3e-5, 4e-6)
    assert ImuNoise.from_sensor_yaml({**noise.to_dict(), "rate_hz": 200.0}) == noise
    assert ImuNoise.from_sensor_yaml({"gyroscope_noise_density": 1.0}).accelerometer_noise_density == \
        ImuNoise().accelerometer_noise_density
    meta = ImuScenario(multi_position(), noise=noise, rate_hz=250.0).exact_measurements().imu("imu0").meta
    assert meta == {"sensor_type": "imu", "rate_hz": 250.0, "gravity_m_s2": G, **noise.to_dict()}


def test_random_intrinsics_are_realistic():
    accel, gyro = random_intrinsics(9)
    scale_a, angles_a = imu.scale_and_misalignment(accel.M)
    assert np.all((np.abs(scale_a) >= 0.005 - 1e-12) & (np.abs(scale_a) <= 0.02 + 1e-12))
    assert np.all((np.abs(angles_a) >= 0.5e-3 - 1e-12) & (np.abs(angles_a) <= 1.5e-3 + 1e-12))
    assert np.all(np.tril(accel.M, -1) == 0)
    assert np.all((np.abs(accel.bias) >= 0.025) & (np.abs(accel.bias) <= 0.075))
    assert np.all((np.abs(gyro.bias) >= 0.005) & (np.abs(gyro.bias) <= 0.015))
    assert np.all(gyro.A == 0) and np.all(np.abs(gyro.M[np.tril_indices(3, -1)]) > 0)


# --- two IMUs ------------------------------------------------------------------------------------------------

def calibrated(scenario, data, which):
    accel, gyro = getattr(scenario, "accel" + which), getattr(scenario, "gyro" + which)
    f = accel.specific_force(data.accel_m_s2)
    return gyro.rate(data.gyro_rad_s, f), f


@pytest.mark.parametrize("trajectory", [multi_position(6, n_poses=6), handheld(20.0, seed=6)],
                         ids=["multi", "hand"])
def test_pair_imu1_equals_imu0_after_rotation_and_lever_arm(trajectory):
    """dt = 3 samples: imu1's sample j was taken at imu0's sample j + 3; its calibrated output, rotated into imu0
    and with the lever-arm terms removed, equals imu0's."""
    rate, lag = 200.0, 3
    scenario = ImuPairScenario.random(trajectory, seed=2, lever_arm_m=0.2, dt_s=lag / rate, rate_hz=rate)
    rec = scenario.exact_measurements()
    d0, d1 = rec.imu("imu0"), rec.imu("imu1")
    np.testing.assert_array_equal(d0.t_ns, d1.t_ns)  # same stamps on two clocks
    w0, f0 = calibrated(scenario, d0, "0")
    w1, f1 = calibrated(scenario, d1, "1")
    R, r = scenario.R_imu0_imu1, scenario.r_m
    w0, f0, w1, f1 = w0[lag:], f0[lag:], w1[:-lag], f1[:-lag]
    w_dot = trajectory.evaluate(d0.t_s[lag:]).w_dot_S
    np.testing.assert_allclose(w1 @ R.T, w0, atol=1e-12)
    lever = np.cross(w_dot, r) + np.cross(w0, np.cross(w0, r))
    assert np.max(np.abs(lever)) > 0.1  # the lever arm matters here
    np.testing.assert_allclose(f1 @ R.T - lever, f0, atol=1e-9)


def test_pair_clock_offset_and_rates_follow_the_convention():
    """Non-integer offset, imu1 at another rate: imu1's sample stamped t1 shows the motion at imu0 time t1 + dt."""
    trajectory = handheld(10.0, seed=8)
    scenario = ImuPairScenario.random(trajectory, seed=3, dt_s=0.0123, rate_hz=200.0, rate1_hz=150.0,
                                      noise1=ImuNoise.zero())
    d1 = scenario.exact_measurements().imu("imu1")
    assert d1.meta["rate_hz"] == 150.0 and len(d1.t_ns) == 1501
    w1, f1 = calibrated(scenario, d1, "1")
    t_true = (d1.t_ns - scenario.t0_ns) * 1e-9 + 0.0123
    s = trajectory.evaluate(t_true)
    f_expected = inertial.specific_force_at_lever_arm(s.specific_force_S(G), s.w_S, s.w_dot_S, scenario.r_m)
    np.testing.assert_allclose(w1, s.w_S @ scenario.R_imu0_imu1, atol=1e-12)
    np.testing.assert_allclose(f1, f_expected @ scenario.R_imu0_imu1, atol=1e-9)
    truth = scenario.truth()
    assert truth["pair"]["time_offset_s"] == 0.0123
    start0, _ = truth["static_intervals_s"][1]
    start1 = truth["sensors"]["imu1"]["static_intervals_ns"][1][0]
    assert start1 == scenario.t0_ns + round((start0 - 0.0123) * 1e9)


# --- truth ---------------------------------------------------------------------------------------------------

def test_truth_is_yaml_and_kept_out_of_the_measurements(tmp_path):
    pair = ImuPairScenario.random(multi_position(3, n_poses=4), seed=1, temperature=TemperatureProfile(),
                                  channels1={"supply_voltage": (5.0, "V")})
    for scenario in (full_scenario(1), pair):
        truth = scenario.truth()
        assert yaml.safe_load(yaml.safe_dump(truth)) == truth
        rec = scenario.perturbed_measurements(0)
        assert set(rec.sensors) == set(truth["sensors"])
        for name, sensor in rec.sensors.items():
            expected = {"w_RS_S_x", "w_RS_S_y", "w_RS_S_z", "a_RS_S_x", "a_RS_S_y", "a_RS_S_z", "temperature"}
            assert set(sensor.values) - expected <= {"supply_voltage"}
            assert set(sensor.meta) == {"sensor_type", "rate_hz", "gravity_m_s2", *ImuNoise.KEYS}
    truth = pair.truth()
    np.testing.assert_allclose(truth["pair"]["rotation_imu0_imu1"], pair.R_imu0_imu1)
    np.testing.assert_allclose(truth["sensors"]["imu1"]["accelerometers"]["M"], pair.accel1.M)
    assert truth["pair"]["effects"] == ["time_offset", "lever_arm"]
    assert "bias_temperature" not in truth["sensors"]["imu0"]["effects"]  # no temperature slopes drawn
    assert "channel:supply_voltage" in full_scenario(1).truth()["sensors"]["imu0"]["effects"]
    path = pair.write(tmp_path / "rec", seed=4)
    back = read_recording(path)
    assert set(back.sensors) == {"imu0", "imu1"}
    assert_same(back, pair.perturbed_measurements(4))
    written = read_truth(path)
    assert written.pop("measurements") == {"perturbed_seed": 4}
    assert written == truth
