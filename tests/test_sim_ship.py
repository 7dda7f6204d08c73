"""Ship voyage simulator (selfcal.sim.ship): kinematics, lever arm, heave vs tilt, sensors, speed."""
import time

import numpy as np
import pytest
import yaml

from selfcal.core import so3
from selfcal.sim.ship import DEG_H, ShipScenario


def _short(kind="turning", **kwargs):
    return ShipScenario(kind, duration_s=kwargs.pop("duration_s", 600.0), **kwargs)


def test_seeded_reproducibility():
    a, b = _short(seed=3).perturbed_measurements(7), _short(seed=3).perturbed_measurements(7)
    for name in ("imu0", "speed0", "gps0"):
        assert np.array_equal(a.sensors[name].t_ns, b.sensors[name].t_ns)
        for col, v in a.sensors[name].values.items():
            assert np.array_equal(v, b.sensors[name].values[col])
    c = _short(seed=3).perturbed_measurements(8)
    assert not np.array_equal(a.sensors["imu0"].values["w_RS_S_x"], c.sensors["imu0"].values["w_RS_S_x"])
    d = _short(seed=4)
    assert not np.allclose(d.gyro_bias0_rad_s, _short(seed=3).gyro_bias0_rad_s)
    t = np.linspace(0, 600, 50)
    assert np.array_equal(_short(seed=3).truth_gyro_bias(t), _short(seed=3).truth_gyro_bias(t))


@pytest.mark.parametrize("kind", ["calm", "heave", "turning"])
def test_body_rates_integrate_to_attitude(kind):
    sc = _short(kind, seed=1)
    t0 = 95.0 if kind != "turning" else sc.motion.turn_list[0]["start_s"] + 2.0  # inside a turn's ramp
    span, dt = 10.0, 1e-3
    t_mid = t0 + dt * (np.arange(int(span / dt)) + 0.5)  # midpoint rule: global error <= span dt^2 C
    w, w_dot = sc.motion.body_rates(t_mid)
    R0, R1 = sc.motion.R_W_S(np.array([t0, t0 + span]))
    err = np.linalg.norm(so3.log(so3.integrate_rates(w, np.full(len(w), dt)).T @ (R0.T @ R1)))
    # midpoint product of Exp's: local error ~ dt^3 (|w_ddot| / 24 + |w x w_dot| / 12); bound with margin 10
    w_ddot = np.gradient(w_dot, dt, axis=0)
    bound = 10 * span * dt**2 * (np.max(np.linalg.norm(w_ddot, axis=1)) / 24
                                 + np.max(np.linalg.norm(np.cross(w, w_dot), axis=1)) / 12) + 1e-12
    assert err < max(bound, 1e-10), (err, bound)
    # exact w_dot vs central difference (h = 1e-4: truncation h^2 |w'''| / 6 ~ 1e-10, rounding 1e-16 / h)
    h = 1e-4
    w_p, _ = sc.motion.body_rates(t_mid[::1000] + h)
    w_m, _ = sc.motion.body_rates(t_mid[::1000] - h)
    assert np.allclose((w_p - w_m) / (2 * h), w_dot[::1000], atol=1e-9)


def test_specific_force_magnitude_within_acceleration_bounds():
    # at the centre (no lever arm): | |f| - g | <= |a_W| <= heave bound + |v_dot| + |v yaw_dot| (triangle ineq.)
    sc = ShipScenario("calm", duration_s=600.0, seed=2, lever_arm_m=(0, 0, 0))
    t_ns, t = sc.imu_stamps()
    _, f = sc.true_imu(t)
    v, v_dot = sc.motion.speed(t)
    yaw_dot = sc.motion.euler(t)[2][1]
    bound = sc.motion.heave.second_derivative_bound() + np.max(np.abs(v_dot)) + np.max(np.abs(v * yaw_dot))
    dev = np.abs(np.linalg.norm(f, axis=1) - sc.gravity_m_s2)
    assert np.max(dev) <= bound + 1e-12
    assert np.max(dev) > 0.2 * bound  # the heave is really there
    # rest-like instants (heave acceleration crossing zero): |f| = g to within the horizontal accelerations
    z_ddot = sc.motion.heave.evaluate(t)[2]
    still = np.abs(z_ddot) < 1e-3
    assert still.sum() > 10
    assert np.max(dev[still]) <= 1e-3 + np.max(np.abs(v * yaw_dot)) + 1e-12


def test_heave_changes_magnitude_not_direction_when_level():
    sc = ShipScenario("heave", duration_s=300.0, seed=5, lever_arm_m=(0, 0, 0), roll_scale=0, pitch_scale=0,
                      yaw_wave_scale=0)
    _, t = sc.imu_stamps()
    _, f = sc.true_imu(t)
    tilt = np.arctan2(np.linalg.norm(f[:, :2], axis=1), f[:, 2])
    assert np.max(np.abs(tilt)) < 1e-15
    z_ddot = sc.motion.heave.evaluate(t)[2]
    assert np.allclose(np.linalg.norm(f, axis=1), sc.gravity_m_s2 + z_ddot, atol=1e-12)
    assert np.ptp(np.linalg.norm(f, axis=1)) > 0.1  # metres of long swell: ~0.1-0.5 m/s^2 of heave


def test_lever_arm_term():
    r = np.array([2.0, 0.5, 5.0])
    with_arm = ShipScenario("turning", duration_s=600.0, seed=1, lever_arm_m=r).exact_measurements().imu("imu0")
    at_centre = ShipScenario("turning", duration_s=600.0, seed=1, lever_arm_m=(0, 0, 0)).exact_measurements()
    at_centre = at_centre.imu("imu0")
    w, w_dot = ShipScenario("turning", duration_s=600.0, seed=1).motion.body_rates(with_arm.t_s)
    expected = np.cross(w_dot, r) + np.cross(w, np.cross(w, r))
    assert np.allclose(with_arm.accel_m_s2 - at_centre.accel_m_s2, expected, atol=1e-12)
    assert np.max(np.linalg.norm(expected, axis=1)) > 0.01  # the lever arm matters
    assert np.array_equal(with_arm.gyro_rad_s, at_centre.gyro_rad_s)


def test_recording_layout_and_sensors():
    sc = ShipScenario("turning", duration_s=600.0, seed=1, speed_log_scale=1.02, current_m_s=(0.3, -0.2))
    rec = sc.exact_measurements()
    assert sorted(rec.sensors) == ["gps0", "imu0", "speed0"]
    imu0 = rec.imu("imu0")
    assert len(imu0.t_ns) == 600 * 50 + 1 and imu0.t_ns.dtype == np.int64 and imu0.t_ns[0] == sc.t0_ns
    assert imu0.meta["rate_hz"] == 50.0 and "lever_arm_m" not in imu0.meta
    for key in ("accelerometer_noise_density", "gyroscope_noise_density", "accelerometer_random_walk",
                "gyroscope_random_walk", "gravity_m_s2"):
        assert key in imu0.meta
    # gyro = true rate + drifting bias
    w, _ = sc.motion.body_rates(imu0.t_s)
    assert np.allclose(imu0.gyro_rad_s - w, sc.truth_gyro_bias(imu0.t_s), atol=1e-15)
    assert np.isclose(np.linalg.norm(sc.truth_gyro_bias(0.0)), 10 * DEG_H)
    speed, gps = rec.sensors["speed0"], rec.sensors["gps0"]
    assert speed.units == {"speed_log": "m s^-1"} and gps.units == {"speed": "m s^-1"}
    assert len(speed.t_ns) == 601 and len(gps.t_ns) == 601 and speed.t_ns.dtype == np.int64
    t_log = (speed.t_ns - sc.t0_ns) * 1e-9
    v, _ = sc.motion.speed(t_log)
    assert np.allclose(speed.values["speed_log"], 1.02 * v)
    assert np.all((v >= 5.0 - 1e-9) & (v <= 15.0 + 1e-9))
    assert np.max(np.abs(gps.values["speed"] - v)) <= np.hypot(0.3, 0.2) + 1e-9  # current separates them
    noisy = sc.perturbed_measurements(0)
    res = noisy.sensors["speed0"].values["speed_log"] - speed.values["speed_log"]
    # sigma 0.05 m/s; the sample std of 601 draws has relative sigma 1/sqrt(2 * 600): allow 6 of those
    assert abs(np.std(res) / 0.05 - 1.0) < 6.0 / np.sqrt(1200)
    yaml.safe_dump(sc.truth())  # plain, serialisable


def test_turning_has_turns_and_surges():
    sc = ShipScenario("turning", duration_s=3600.0, seed=0)
    t = np.arange(0, 3600.0, 0.5)
    yaw_rate = np.degrees(sc.motion.euler(t)[2][1])
    v, v_dot = sc.motion.speed(t)
    assert 1.0 <= np.max(np.abs(yaw_rate)) <= 4.5
    assert np.min(v_dot) < -0.1 and np.max(v_dot) > 0.05
    assert np.min(v) >= 5.0 - 1e-9 and np.max(v) <= 15.0 + 1e-9


def test_heave_kind_is_long_swell():
    sc = ShipScenario("heave", duration_s=60.0, seed=0)
    assert np.all((sc.motion.heave.period_s >= 25.0) & (sc.motion.heave.period_s <= 60.0))
    assert np.min(sc.motion.heave.period_s) > np.max(np.r_[sc.motion.roll.period_s, sc.motion.pitch.period_s])
    assert np.all(np.abs(sc.motion.heave.amplitude) >= 1.0)
    for s in (sc.motion.roll, sc.motion.pitch):
        assert np.all((s.period_s >= 5.0) & (s.period_s <= 20.0))


def test_position_derivative_is_velocity():
    sc = ShipScenario("turning", duration_s=600.0, seed=1, current_m_s=(0.3, -0.2))
    t = np.linspace(50.0, 550.0, 7)
    h = 0.01
    p = sc.motion.position_W(np.r_[t - h, t + h])
    v = (p[len(t):] - p[:len(t)]) / (2 * h)
    sample = sc.motion.evaluate(t)
    # central difference: truncation h^2 |jerk| / 6 ~ 1e-5 m/s (heave jerk A w^3 < 1 m/s^3); the Hermite
    # interpolation of the 0.05 s position grid adds less than that
    assert np.allclose(v, sample.v_W, atol=1e-4)
    assert np.allclose(np.linalg.norm(sample.v_W[:, :2], axis=1), sc.motion.speed_over_ground(t))


def test_write_and_read_back(tmp_path):
    from selfcal.io.recording import read_recording, read_truth

    sc = ShipScenario("calm", duration_s=20.0, seed=0)
    sc.write(tmp_path / "rec", seed=3)
    rec = read_recording(tmp_path / "rec")
    assert sorted(rec.sensors) == ["gps0", "imu0", "speed0"]
    assert np.array_equal(rec.imu("imu0").accel_m_s2, sc.perturbed_measurements(3).imu("imu0").accel_m_s2)
    assert read_truth(tmp_path / "rec")["sensors"]["imu0"]["lever_arm_m"] == [2.0, 0.5, 5.0]


def test_one_hour_50hz_is_fast(tmp_path):
    start = time.process_time()  # CPU time: the machine is shared (other tests, other jobs)
    rec = ShipScenario("turning", duration_s=3600.0, rate_hz=50.0, seed=0).perturbed_measurements(1)
    elapsed = time.process_time() - start
    assert len(rec.imu("imu0").t_ns) == 180001
    assert elapsed < 20.0, elapsed
