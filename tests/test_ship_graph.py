"""Ship attitude graph (AHRSFactor + tilt factors + bias random walk): roll, pitch and the horizontal gyro biases
from a rolling, pitching hull with a drifting gyro; batch and iSAM2 agree."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from selfcal.graphs.ship import ShipInputs, ShipSmoother

RATE_HZ, DURATION_S, G = 50.0, 300.0, 9.80665


@pytest.fixture(scope="module")
def voyage():
    rng = np.random.default_rng(0)
    t = np.arange(0, DURATION_S, 1 / RATE_HZ)
    roll = np.radians(5) * np.sin(2 * np.pi * t / 8)
    pitch = np.radians(3) * np.sin(2 * np.pi * t / 12 + 1)
    roll_rate = np.radians(5) * 2 * np.pi / 8 * np.cos(2 * np.pi * t / 8)
    pitch_rate = np.radians(3) * 2 * np.pi / 12 * np.cos(2 * np.pi * t / 12 + 1)
    # ZYX body rates with constant yaw: w = (roll_dot, cos(roll) pitch_dot, -sin(roll) pitch_dot)
    w = np.stack([roll_rate, np.cos(roll) * pitch_rate, -np.sin(roll) * pitch_rate], axis=1)
    R = Rotation.from_euler("ZYX", np.stack([np.zeros_like(t), pitch, roll], axis=1)).as_matrix()
    f = np.einsum("nji,j->ni", R, np.array([0.0, 0.0, G]))
    bias = np.radians(30.0 / 3600) * np.array([1.0, -1.0, 0.5])  # 30 deg/h: three times the 10 deg/h
    gyro = w + bias + 1e-4 * np.sqrt(RATE_HZ) * rng.normal(size=w.shape)
    accel = f + 0.02 * rng.normal(size=f.shape)
    return ShipInputs(t, gyro, accel, None), roll, pitch, bias


def test_batch_recovers_roll_pitch_and_horizontal_bias(voyage):
    inputs, roll, pitch, bias = voyage
    est = ShipSmoother(inputs).batch()
    idx = np.searchsorted(inputs.t_s, est.t_s)
    # the tilt factors alone (0.02 m/s^2 noise over 10 samples, 0.002 rad floor) give ~0.12 deg per keyframe; the gyro links 1500
    # keyframes, so the smoothed error is far below: 0.1 deg is a loose, physics-sized bound
    assert np.degrees(np.sqrt(np.mean((est.roll - roll[idx]) ** 2))) < 0.1
    assert np.degrees(np.sqrt(np.mean((est.pitch - pitch[idx]) ** 2))) < 0.1
    # x and y biases show in the tilt (z, the heading axis, only weakly): the last segment's bias within 3 sigma
    # of its marginal.  The random walk the graph allows (1e-5 rad/s^2/sqrt(Hz), 1.7e-4 rad/s over the run) and
    # the one-sided information at the end make that sigma ~25 % of the 30 deg/h bias
    sigma = _last_bias_sigma(inputs)
    assert np.all(sigma[:2] < 0.5 * abs(bias[:2]))  # the tilt does determine it
    assert np.all(np.abs(est.gyro_bias[-1, :2] - bias[:2]) < 3.0 * sigma[:2])


def _last_bias_sigma(inputs):
    """Marginal sigma (rad/s) of the last bias segment in the batch graph the smoother solves."""
    import gtsam
    from selfcal.graphs.ship import ShipGraph, ShipGraphOptions, keyframes_from_inputs
    from selfcal.core.solve import marginal_covariances, optimize
    options = ShipGraphOptions()
    frames = keyframes_from_inputs(inputs, options)
    builder = ShipGraph(options, inputs.gravity_m_s2, inputs.gyro_noise_density, inputs.gyro_random_walk)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for frame in frames:
        g, v = builder.add(frame, values if builder.k >= 0 else None, propagate=False)
        graph.push_back(g)
        values.insert(v)
    key = builder.bias_key(frames[-1].t_s)
    return np.sqrt(np.diag(marginal_covariances(graph, optimize(graph, values), [key], "bias")[key]))


def test_online_isam2_tracks_like_the_batch(voyage):
    inputs, roll, pitch, _ = voyage
    short = ShipInputs(inputs.t_s[:3000], inputs.gyro_rad_s[:3000], inputs.accel_m_s2[:3000], None)
    online = ShipSmoother(short).online()
    idx = np.searchsorted(short.t_s, online.t_s)
    # filtered (not smoothed) estimates: allow twice the batch bound, after a 10 s start-up
    late = online.t_s > 10
    assert np.degrees(np.sqrt(np.mean((online.roll[late] - roll[idx][late]) ** 2))) < 0.2
    assert np.degrees(np.sqrt(np.mean((online.pitch[late] - pitch[idx][late]) ** 2))) < 0.2


@pytest.fixture(scope="module")
def turning_without_speed_source():
    """A simulated turning voyage (turns of 2.7-3.3 deg/s at 11-13 m/s: a centrifugal tilt of about 4 deg) whose
    speed log is not used: batch and online estimates, and the patent's filter without its known accelerations."""
    from selfcal.baselines.ship import PatentDriftFilter, vessel_cutoff_hz
    from selfcal.graphs.ship import ShipGraphOptions
    from selfcal.pipelines.ship import ship_inputs
    from selfcal.sim.ship import ShipScenario
    scenario = ShipScenario(kind="turning", duration_s=600.0, seed=3)
    inputs = ship_inputs(scenario.perturbed_measurements(103))
    smoother = ShipSmoother(inputs, ShipGraphOptions(remove_known_acceleration=False))
    motion = scenario.motion
    cutoff = vessel_cutoff_hz(motion.heave.period_s, np.concatenate([motion.roll.period_s, motion.pitch.period_s]))
    patent = PatentDriftFilter(cutoff, remove_known_acceleration=False).run(
        inputs.t_s, inputs.gyro_rad_s, inputs.accel_m_s2, inputs.speed_m_s)
    return scenario, inputs, {"batch": smoother.batch(), "online": smoother.online()}, patent


@pytest.mark.parametrize("method", ["batch", "online"])
def test_turns_reveal_the_unknown_speed(turning_without_speed_source, method):
    """Without a speed source the centrifugal ``v x yaw rate`` is modelled with the speed as an unknown: over the
    turns (|yaw rate| > 1 deg/s) the speed comes out within 5 % RMS of the truth (the accuracy the model grants a
    speed log, ``known_acceleration_relative_sigma``), and roll and pitch beat the patent's filter, which has no
    way to tell the turn's centrifugal force from gravity."""
    scenario, inputs, estimates, patent = turning_without_speed_source
    est = estimates[method]
    true_speed, _ = scenario.motion.speed(est.t_s)
    _, _, (_, yaw_rate, _) = scenario.motion.euler(est.t_s)
    turning = np.abs(yaw_rate) > np.radians(1.0)
    assert turning.sum() > 500
    relative = np.sqrt(np.mean((est.speed_m_s[turning] - true_speed[turning]) ** 2)) / np.mean(true_speed[turning])
    assert relative < 0.05, relative

    def rms(t, roll, pitch):
        true_roll, true_pitch, _ = scenario.truth_attitude(t)
        return np.sqrt(np.mean((roll - true_roll) ** 2)), np.sqrt(np.mean((pitch - true_pitch) ** 2))

    graph_roll, graph_pitch = rms(est.t_s, est.roll, est.pitch)
    patent_roll, patent_pitch = rms(inputs.t_s, patent.roll, patent.pitch)
    assert graph_roll < patent_roll and graph_pitch < patent_pitch, (graph_roll, patent_roll, graph_pitch, patent_pitch)
