"""Patent seed 003 baseline: accelerometer-tilt PID loop removes gyro drift; heave, surge and turns as claimed."""
import math
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from selfcal.baselines import ship as p
from selfcal.core.inertial import tilt_from_specific_force

G = p.G_M_S2
FS_HZ = 50.0
CUTOFF_HZ = 0.05
WC = 2.0 * math.pi * CUTOFF_HZ
BIAS_RAD_S = math.radians(10.0) / 3600.0  # 10 deg/h


def specific_force(roll, pitch, yaw=0.0, accel_world=(0.0, 0.0, 0.0)):
    """f = R^T (a + g z) with R = Rz(yaw) Ry(pitch) Rx(roll), built by scipy."""
    R = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    return R.T @ (np.asarray(accel_world) + [0.0, 0.0, G])


def times(duration_s):
    return np.arange(int(duration_s * FS_HZ)) / FS_HZ


def test_tilt_formula_matches_rotation_matrices():
    rng = np.random.default_rng(3)
    angles = rng.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi], size=(200, 3))  # roll, pitch, yaw
    f = np.array([specific_force(r, pt, y) for r, pt, y in angles]) * rng.uniform(0.2, 3.0, size=(200, 1))
    roll, pitch = tilt_from_specific_force(f)
    np.testing.assert_allclose(roll, angles[:, 0], atol=1e-12)
    np.testing.assert_allclose(pitch, angles[:, 1], atol=1e-12)


def test_euler_rates_match_finite_difference_of_rotation():
    """Body rate omega: R(t + h) = R(t) Exp(omega h); the Euler rates must reproduce it."""
    rng = np.random.default_rng(4)
    h = 1e-6
    for _ in range(20):
        roll, pitch, yaw = rng.uniform([-3, -1.4, -3], [3, 1.4, 3])
        omega = rng.normal(size=3)
        R1 = Rotation.from_euler("ZYX", [yaw, pitch, roll]) * Rotation.from_rotvec(omega * h)
        R0 = Rotation.from_euler("ZYX", [yaw, pitch, roll]) * Rotation.from_rotvec(-omega * h)
        d = (R1.as_euler("ZYX") - R0.as_euler("ZYX")) / (2 * h)  # yaw, pitch, roll rates
        np.testing.assert_allclose(p.euler_rates_zyx(roll, pitch, omega), d[::-1], rtol=1e-6, atol=1e-6)


def test_static_tilt_with_gyro_bias_converges_while_raw_gyro_drifts():
    """Start at zero attitude, truth roll 5 deg, pitch -3 deg, gyro bias 10 deg/h on x and y.

    Default PI: double pole at -wc, so the start error (5 deg) decays as (1 + wc t) exp(-wc t); 2 % after
    18.6 s, 1e-6 of it (9e-8 rad) after 53 s (`settling_time_s`).  What remains is the PI's ramp-following error b / ki = b / wc
    (0.0088 deg); tolerance 1.5 b / wc."""
    t = times(600.0)
    roll0, pitch0 = math.radians(5.0), math.radians(-3.0)
    f = np.tile(specific_force(roll0, pitch0, 0.7), (t.size, 1))
    gyro = np.tile([BIAS_RAD_S, BIAS_RAD_S, 0.0], (t.size, 1))
    res = p.PatentDriftFilter(CUTOFF_HZ, align_to_first_tilt=False).run(t, gyro, f)
    assert p.settling_time_s(CUTOFF_HZ, 1e-6) < 60.0
    late = t >= 60.0
    tol = 1.5 * BIAS_RAD_S / WC
    assert np.max(np.abs(res.roll[late] - roll0)) < tol
    assert np.max(np.abs(res.pitch[late] - pitch0)) < tol
    # steady state: the correction ramps at minus the bias's Euler roll rate (it cancels the drift)
    slope = np.polyfit(t[late], res.correction[late, 0], 1)[0]
    roll_drift_rad_s = p.euler_rates_zyx(roll0, pitch0, (BIAS_RAD_S, BIAS_RAD_S, 0.0))[0]
    assert slope == pytest.approx(-roll_drift_rad_s, rel=1e-4)
    raw = p.integrate_euler_angles(t, gyro, (roll0, pitch0, 0.0))
    assert abs(raw[-1, 0] - roll0) > 100 * tol  # the uncompensated gyro drifts ~1.7 deg in 600 s
    assert np.all(res.correction[:, 2] == 0.0)


def test_second_order_filter_also_converges():
    t = times(300.0)
    roll0 = math.radians(4.0)
    f = np.tile(specific_force(roll0, 0.0), (t.size, 1))
    gyro = np.tile([BIAS_RAD_S, -BIAS_RAD_S, 0.0], (t.size, 1))
    res = p.PatentDriftFilter(CUTOFF_HZ, filter_order=2, align_to_first_tilt=False).run(t, gyro, f)
    late = t >= 150.0
    assert np.max(np.abs(res.roll[late] - roll0)) < 2.0 * BIAS_RAD_S / WC
    assert np.max(np.abs(res.pitch[late])) < 2.0 * BIAS_RAD_S / WC


def test_heave_leaves_tilt_and_filter_unchanged():
    """Heave 2 m/s^2 at a 12 s period: only |f| changes, so the tilt and the compensated angles stay exact."""
    t = times(200.0)
    roll0, pitch0 = math.radians(2.0), math.radians(1.0)
    scale = 1.0 + (2.0 / G) * np.sin(2 * np.pi * t / 12.0)
    f = specific_force(roll0, pitch0)[None, :] * scale[:, None]
    roll, pitch = tilt_from_specific_force(f)
    np.testing.assert_allclose(roll, roll0, atol=1e-13)
    np.testing.assert_allclose(pitch, pitch0, atol=1e-13)
    res = p.PatentDriftFilter(CUTOFF_HZ).run(t, np.zeros((t.size, 3)), f)
    np.testing.assert_allclose(res.roll, roll0, atol=1e-12)
    np.testing.assert_allclose(res.pitch, pitch0, atol=1e-12)


def test_surge_acceleration_biases_pitch_unless_removed():
    """Level vessel accelerating at 0.5 m/s^2: without removal pitch -> -atan(a / g), with removal -> 0."""
    t = times(200.0)
    a = 0.5
    f = np.tile([a, 0.0, G], (t.size, 1))
    speed = 2.0 + a * t
    gyro = np.zeros((t.size, 3))
    late = t >= 100.0
    off = p.PatentDriftFilter(CUTOFF_HZ, remove_known_acceleration=False).run(t, gyro, f, speed)
    np.testing.assert_allclose(off.pitch[late], -math.atan(a / G), atol=1e-6)
    on = p.PatentDriftFilter(CUTOFF_HZ).run(t, gyro, f, speed)
    assert np.max(np.abs(on.pitch[late])) < 1e-9
    assert np.max(np.abs(on.tilt_pitch[t >= 1.0])) < 1e-12  # the 1 s causal difference is exact on a ramp


def test_steady_turn_centrifugal_biases_roll_unless_removed():
    """Flat left turn, v = 10 m/s, yaw rate 3 deg/s: f_y = v r; roll is biased towards atan(v r / g) unless removed.

    Without removal the bias is not exactly atan(v r / g): the wrongly rolled attitude projects the true yaw
    rate r into pitch rate (-r sin roll), the PI follows that ramp with a lag (ramp / ki), and the pitch error
    feeds back into roll (tan(pitch) r cos roll).  So: roll within 5 % of atan(v r / g), pitch visibly off too."""
    t = times(200.0)
    v, r = 10.0, math.radians(3.0)
    f = np.tile([0.0, v * r, G], (t.size, 1))
    gyro = np.tile([0.0, 0.0, r], (t.size, 1))
    speed = np.full(t.size, v)
    late = t >= 100.0
    off = p.PatentDriftFilter(CUTOFF_HZ, remove_known_acceleration=False).run(t, gyro, f, speed)
    np.testing.assert_allclose(off.roll[late], math.atan(v * r / G), rtol=0.05)
    assert np.min(np.abs(off.pitch[late])) > math.radians(0.1)
    on = p.PatentDriftFilter(CUTOFF_HZ).run(t, gyro, f, speed)
    assert np.max(np.abs(on.roll[late])) < 1e-9
    np.testing.assert_allclose(on.yaw[-1], r * t[-1], rtol=1e-9)  # yaw: integrated, uncompensated


def test_cutoff_between_rule_and_error():
    fc = p.cutoff_between(heave_period_s=60.0, roll_period_s=8.0)
    assert 1.0 / 60.0 < fc < 1.0 / 8.0
    assert fc == pytest.approx(math.sqrt((1 / 60.0) * (1 / 8.0)))
    with pytest.raises(ValueError, match="not longer"):
        p.cutoff_between(heave_period_s=8.0, roll_period_s=8.0)
    with pytest.raises(ValueError, match="not longer"):
        p.cutoff_between(heave_period_s=5.0, roll_period_s=10.0)
    with pytest.raises(ValueError):
        p.cutoff_between(0.0, 10.0)


def test_bad_inputs_raise():
    t = times(10.0)
    z = np.zeros((t.size, 3))
    with pytest.raises(ValueError, match="uniformly"):
        p.PatentDriftFilter(CUTOFF_HZ).run(t ** 1.1, z, z + [0, 0, G])
    with pytest.raises(ValueError, match="cutoff"):
        p.PatentDriftFilter(30.0).run(t, z, z + [0, 0, G])
    with pytest.raises(ValueError, match="filter_order"):
        p.PatentDriftFilter(CUTOFF_HZ, filter_order=3).run(t, z, z + [0, 0, G])


def test_one_hour_at_50_hz_runs_in_seconds():
    t = times(3600.0)
    rng = np.random.default_rng(0)
    gyro = rng.normal(0.0, 1e-3, size=(t.size, 3)) + BIAS_RAD_S
    f = np.tile([0.0, 0.0, G], (t.size, 1)) + rng.normal(0.0, 0.02, size=(t.size, 3))
    start = time.process_time()  # CPU time: the machine is shared (other tests, other jobs)
    res = p.PatentDriftFilter(CUTOFF_HZ).run(t, gyro, f, np.full(t.size, 5.0))
    elapsed = time.process_time() - start
    assert res.roll.shape == (180_000,)
    assert elapsed < 5.0
    assert np.max(np.abs(res.roll[t > 60])) < math.radians(0.1)


def test_rolling_heaving_vessel_with_bias_tracks_true_roll():
    """Roll 5 deg at an 8 s period (above the 0.05 Hz cutoff), heave 1.5 m/s^2 at 60 s, pitch trim 1 deg, gyro
    bias 10 deg/h: after settling, the compensated roll follows the oscillating truth.  Tolerance: the ramp lag
    b / wc plus 1e-4 rad for trapezoidal integration and the one-sample compensation delay."""
    t = times(600.0)
    w_roll = 2 * np.pi / 8.0
    roll = math.radians(5.0) * np.sin(w_roll * t)
    roll_dot = math.radians(5.0) * w_roll * np.cos(w_roll * t)
    pitch0 = math.radians(1.0)
    heave = 1.5 * np.sin(2 * np.pi * t / 60.0)
    R = Rotation.from_euler("ZYX", np.column_stack([np.zeros_like(t), np.full_like(t, pitch0), roll]))
    f = R.inv().apply(np.column_stack([np.zeros_like(t), np.zeros_like(t), G + heave]))  # f = R^T (a + g z)
    gyro = np.column_stack([roll_dot, np.zeros_like(t), np.zeros_like(t)]) + BIAS_RAD_S  # pitch const: p = roll'
    res = p.PatentDriftFilter(p.cutoff_between(60.0, 8.0)).run(t, gyro, f)
    late = t >= 120.0
    wc = 2 * np.pi * p.cutoff_between(60.0, 8.0)
    tol = 1.5 * BIAS_RAD_S / wc + 1e-4
    assert np.max(np.abs(res.roll[late] - roll[late])) < tol
    assert np.max(np.abs(res.pitch[late] - pitch0)) < tol
    raw = p.integrate_euler_angles(t, gyro, (0.0, pitch0, 0.0))
    assert np.max(np.abs(raw[late, 0] - roll[late])) > 10 * tol


def test_vessel_cutoff_uses_fastest_heave_and_slowest_roll_or_falls_an_octave_below():
    # swell slower than the roll: claim 1's geometric mean of the fastest heave (40 s) and slowest roll (12 s)
    assert p.vessel_cutoff_hz([60.0, 40.0], [8.0, 12.0]) == pytest.approx(1.0 / np.sqrt(40.0 * 12.0))
    # swell (6 s) faster than the slowest roll (20 s): no cutoff between, an octave below 1/20 Hz
    assert p.vessel_cutoff_hz([6.0, 10.0], [5.0, 20.0]) == pytest.approx(0.025)
