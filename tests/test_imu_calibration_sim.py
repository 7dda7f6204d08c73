"""End to end on simulated recordings: the pipelines recover the truth, and their sigmas are honest.

Truth comes from ``selfcal.sim`` (kept apart from the measurements); every tolerance is derived from the
sampling (exact data) or from the estimator's own reported covariance (perturbed data), as stated at each check.
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from selfcal.core.solve import DegenerateDataError
from selfcal.core.inertial import STANDARD_GRAVITY_M_S2
from selfcal.models.imu import upper_triangular_entries
from selfcal.pipelines.imu import calibrate_imu
from selfcal.pipelines.imu_pair import calibrate_imu_pair
from selfcal.core.inertial import ImuNoise
from selfcal.sim.imu import ImuPairScenario, ImuScenario, random_intrinsics
from selfcal.sim.trajectories import HandheldTrajectory, MultiPositionTrajectory, Trajectory, TrajectorySample

RATE_HZ = 100.0
# White noise only: the intrinsics graph models constant biases and reports white-noise sigmas, so a bias random
# walk (not in the model) is left out where the sigmas themselves are under test.
WHITE = ImuNoise(accelerometer_random_walk=0.0, gyroscope_random_walk=0.0)


def multi_position(seed):
    return MultiPositionTrajectory(n_poses=12, static_s=3.0, move_s=2.0, initial_static_s=10.0, seed=seed)


def imu_scenario(seed, noise):
    accel, gyro = random_intrinsics(seed, g_sensitivity=1e-4)  # every block of the model present, A included
    return ImuScenario(multi_position(seed), accel, gyro, noise=noise, rate_hz=RATE_HZ)


def errors_by_block(estimate, scenario):
    """Estimate minus truth for every estimated block, in the parametrisation of the reported covariance."""
    e, a, g = estimate, scenario.accel, scenario.gyro
    return {"accel_M": upper_triangular_entries(e.accel.M) - upper_triangular_entries(a.M),
            "accel_bias": e.accel.bias - a.bias,
            "gyro_M": (e.gyro.M - g.M).ravel(), "gyro_bias": e.gyro.bias - g.bias, "gyro_A": (e.gyro.A - g.A).ravel()}


def zoh_discretisation_rad(trajectory, rate_hz):
    """Per move: angle between the true relative rotation of the two poses and the zero-order-hold product of the
    true body rates sampled at ``rate_hz`` (what the pipeline integrates), and the move angle.  Computed with
    scipy from the trajectory's closed form, independently of the library's integrator."""
    t_s = np.arange(0.0, trajectory.duration_s + 0.5 / rate_hz, 1.0 / rate_hz)
    w_S = trajectory.evaluate(t_s).w_S
    out = []
    for k, ((_, end), (start, _)) in enumerate(zip(trajectory.static_intervals_s[:-1],
                                                   trajectory.static_intervals_s[1:])):
        idx = np.flatnonzero((t_s >= end - 1.0 / rate_hz) & (t_s <= start))
        delta = Rotation.identity()
        for w in w_S[idx]:
            delta = delta * Rotation.from_rotvec(w / rate_hz)
        R_true = trajectory.pose_R_W_S[k].T @ trajectory.pose_R_W_S[k + 1]
        angle = np.linalg.norm(trajectory.move_rotvec[k])
        out.append((np.linalg.norm((Rotation.from_matrix(R_true).inv() * delta).as_rotvec()), angle))
    return np.array(out)


# --- (a) exact measurements -------------------------------------------------------------------------------------

def test_exact_measurements_recover_every_intrinsic():
    scenario = imu_scenario(seed=1, noise=ImuNoise.zero())
    estimate = calibrate_imu(scenario.exact_measurements(), "imu0").estimate
    err = errors_by_block(estimate, scenario)

    # The only model error in exact data is the moves' zero-order-hold integration (second order in 1/rate:
    # ~5e-6 rad per move at 100 Hz, computed here from the trajectory).  A gyro M error eps turns a move of angle
    # theta by ~eps theta, so least squares over the moves keeps |eps| at most about max(delta_k / theta_k);
    # 3x that allows for the conditioning of the 9 entries.
    disc = zoh_discretisation_rad(scenario.trajectory, RATE_HZ)
    assert disc[:, 0].max() < 1e-5  # the sampling premise of this tolerance
    gyro_M_tol = 3 * np.max(disc[:, 0] / disc[:, 1])
    assert np.abs(err["gyro_M"]).max() < gyro_M_tol, (np.abs(err["gyro_M"]).max(), gyro_M_tol)

    # The static equations hold exactly for exact data (M_a (a - b_a) = g u, w = b_g + A g u) and over-determine
    # their blocks (12 poses); the discretisation reaches them only through the up-directions, which the exact
    # static accelerometer means pin.  So they sit at the solver's convergence level: 1e-9 relative to g or 1.
    g = STANDARD_GRAVITY_M_S2
    assert np.abs(err["accel_M"]).max() < 1e-9
    assert np.abs(err["accel_bias"]).max() < 1e-9 * g
    assert np.abs(err["gyro_bias"]).max() < 1e-9  # rad/s
    assert np.abs(err["gyro_A"]).max() < 1e-9  # rad/s per m/s^2: A ~ 1e-4, so 1e-5 relative


# --- (b) perturbed measurements: honest sigmas --------------------------------------------------------------------

N_SEEDS = 20


def test_perturbed_normalised_errors_are_chi_square_consistent():
    nees, dims, z_all = {}, {}, []
    for seed in range(N_SEEDS):
        scenario = imu_scenario(seed, WHITE)
        estimate = calibrate_imu(scenario.perturbed_measurements(1000 + seed), "imu0").estimate
        for block, e in errors_by_block(estimate, scenario).items():
            P = estimate.covariance[block]
            nees.setdefault(block, []).append(float(e @ np.linalg.solve(P, e)))
            dims[block] = len(e)
            z_all.extend(e / np.sqrt(np.diag(P)))
    # Per block, e^T P^-1 e with the block's reported marginal covariance is chi2(dim) when the sigmas are right;
    # summed over independent seeds it is chi2(dim * N_SEEDS).  Two-sided 99.9 % interval per block (5 blocks:
    # <= 0.5 % chance of a false alarm): too-small sigmas fail above, too-large (useless) sigmas below.
    for block, values in nees.items():
        dof = dims[block] * N_SEEDS
        total = float(np.sum(values))
        assert chi2.ppf(0.0005, dof) < total < chi2.ppf(0.9995, dof), (block, total, dof, values)
    # Mean of the squared per-parameter normalised errors over all 30 parameters and all seeds: expectation 1.
    # Parameters of one run are correlated, so the sum is not chi2(30 N); each independent run still carries at
    # least one degree of freedom, so chi2(N) / N bounds the mean conservatively (99.9 %, two-sided).
    z_all = np.asarray(z_all)
    assert chi2.ppf(0.0005, N_SEEDS) / N_SEEDS < np.mean(z_all**2) < chi2.ppf(0.9995, N_SEEDS) / N_SEEDS, \
        np.mean(z_all**2)
    # and no single parameter beyond 5 sigma (p = 6e-7 each for Gaussian errors, 600 of them here)
    assert np.abs(z_all).max() < 5, np.abs(z_all).max()


# --- (b2) a gap in a move ------------------------------------------------------------------------------------------

def test_a_clock_jump_in_a_move_weakens_its_rotation_only_while_turning():
    """A 0.1 s stamp jump (10 periods: lost samples or a clock jump, nobody can tell) leaves the rotation over it
    unknown by |w| x 0.1 s.  Still (0.2 s before the first move's true start): harmless, not named.  Turning
    (mid-move 1, |w| ~ 1.2 rad/s): that move's 1-sigma becomes hypot(noise, |w| 0.1 s), named in a note the audit
    adapter carries too; every other move is untouched."""
    from dataclasses import replace
    from selfcal.audit.imu.intrinsics import ImuIntrinsicsAudit
    from selfcal.graphs.imu import problem_from_imu
    scenario = imu_scenario(seed=3, noise=WHITE)
    data = scenario.perturbed_measurements(7).imu("imu0")
    (_, move0_start_s), (_, move1_start_s), (move1_end_s, _) = scenario.trajectory.static_intervals_s[:3]
    still_s, jump_ns = move0_start_s - 0.2, 100_000_000
    turning_s = (move1_start_s + move1_end_s) / 2  # the trajectory's peak rate
    t_ns = data.t_ns.copy()
    for at_s in (still_s, turning_s):
        t_ns[data.t_s > at_s] += jump_ns
    clean, jumped = problem_from_imu(data, STANDARD_GRAVITY_M_S2), problem_from_imu(replace(data, t_ns=t_ns),
                                                                                     STANDARD_GRAVITY_M_S2)
    sigma_clean = np.array([m.angle_sigma_rad for m in clean.moves])
    sigma_jumped = np.array([m.angle_sigma_rad for m in jumped.moves])
    assert len(sigma_jumped) == len(sigma_clean) == len(scenario.trajectory.static_intervals_s) - 1
    np.testing.assert_allclose(sigma_jumped[2:], sigma_clean[2:], rtol=1e-12)  # the shifted stamps' round-off
    # still: the noise of the sample held 0.11 s instead of 0.01 s (sum dt^2 over ~250 samples: x1.22) and a rate
    # of noise only (mean of 10 samples); 2x bounds both, against x450 when turning
    assert sigma_jumped[0] < 2 * sigma_clean[0], (sigma_jumped[0], sigma_clean[0])
    # turning: |w| from the trajectory's truth; the raw rate differs from it by the gyro scale (random_intrinsics:
    # at most 3 %) and by the 10-sample mean's noise and curvature (well under 1 %)
    rate = float(np.linalg.norm(scenario.trajectory.evaluate(np.array([turning_s])).w_S))
    assert rate > 1.0  # the premise: turning
    expected = np.hypot(sigma_clean[1], rate * jump_ns * 1e-9)
    assert abs(sigma_jumped[1] / expected - 1) < 0.04, (sigma_jumped[1], expected)
    assert len(jumped.notes) == 1 and jumped.notes[0].startswith("imu0: move 1 ") and \
        "0.11 s gap while turning" in jumped.notes[0], jumped.notes
    assert not clean.notes
    assert ImuIntrinsicsAudit(replace(data, t_ns=t_ns), STANDARD_GRAVITY_M_S2).notes == jumped.notes


# --- (c) the pair pipeline on hand-held motion ----------------------------------------------------------------------

PAIR_SEEDS = range(5)


def pair_scenario(seed):
    # Ideal intrinsics: the pair model (rotation, clock offset, lever arm, relative offsets) is then the whole truth.
    # Default noise, bias random walk included: the relative offsets and the per-group reweighting absorb it.
    return ImuPairScenario.random(HandheldTrajectory(30.0, seed=seed), seed=seed, intrinsics=False,
                                  rate_hz=RATE_HZ)


def test_pair_pipeline_within_its_reported_sigmas():
    nees_all = []
    for seed in PAIR_SEEDS:
        scenario = pair_scenario(seed)
        est = calibrate_imu_pair(scenario.perturbed_measurements(500 + seed), "imu0", "imu1").estimate
        # rotation: NEES on the right tangent, e = Log(R_true^T R_est), against chi2(3) at 99.9 %
        e = Rotation.from_matrix(scenario.R_imu0_imu1.T @ est.R_imu0_imu1).as_rotvec()
        nees = float(e @ np.linalg.solve(est.rotation_cov_rad2, e))
        nees_all.append(nees)
        assert nees < chi2.ppf(0.999, 3), (seed, nees, e)
        # hand-held motion about all axes determines both: they must be estimated, and within 3 reported sigmas
        assert est.time_offset_s is not None and est.lever_arm_m is not None, est.notes
        assert abs(est.time_offset_s - scenario.dt_s) < 3 * est.time_offset_sigma_s, seed
        assert np.all(np.abs(est.lever_arm_m - scenario.r_m) < 3 * est.lever_arm_sigma_m), \
            (seed, est.lever_arm_m - scenario.r_m, est.lever_arm_sigma_m)
    # pooled over the independent seeds: sum of NEES ~ chi2(3 n), two-sided 99.9 %
    dof = 3 * len(PAIR_SEEDS)
    assert chi2.ppf(0.0005, dof) < sum(nees_all) < chi2.ppf(0.9995, dof), nees_all


# --- (d) degenerate motion ----------------------------------------------------------------------------------------

class OneAxisTrajectory(Trajectory):
    """Rotation about one fixed axis only, never at rest: ``R_W_S(t) = Exp(theta(t) a)``, theta a sum of sinusoids.

    The body rate ``theta_dot a`` keeps one direction in the body frame for the whole recording.
    """

    def __init__(self, axis, duration_s=30.0, amplitude_rad=1.0, freq_hz=(0.5, 0.8, 1.3)):
        self.axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
        self.duration_s = float(duration_s)
        self.static_intervals_s = []
        self.amplitude_rad, self.omega = amplitude_rad, 2 * np.pi * np.asarray(freq_hz)

    def evaluate(self, t_s):
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        arg = t[:, None] * self.omega
        k = self.amplitude_rad / len(self.omega)
        theta = k * np.sin(arg).sum(axis=1)
        theta_dot = k * (self.omega * np.cos(arg)).sum(axis=1)
        theta_ddot = -k * (self.omega**2 * np.sin(arg)).sum(axis=1)
        zero = np.zeros((len(t), 3))
        return TrajectorySample(t, Rotation.from_rotvec(theta[:, None] * self.axis).as_matrix(),
                                theta_dot[:, None] * self.axis, theta_ddot[:, None] * self.axis, zero, zero, zero)

    def to_dict(self):
        return {"kind": "one_axis", "axis": self.axis.tolist(), "duration_s": self.duration_s}


def one_axis_pair(axis):
    return ImuPairScenario.random(OneAxisTrajectory(axis), seed=3, intrinsics=False, rate_hz=RATE_HZ)


def test_rotation_about_the_vertical_only_is_refused():
    """Turning about the vertical with no static pose: gravity and the rate are both along the axis, so any extra
    turn of R (and of the lever arm) about it fits the data exactly; the pipeline promises an error saying
    what motion to add, never a rotation."""
    scenario = one_axis_pair([0.0, 0.0, 1.0])
    with pytest.raises(DegenerateDataError, match="two different axes"):
        calibrate_imu_pair(scenario.perturbed_measurements(1), "imu0", "imu1")


@pytest.mark.parametrize("lever_arm", [None, True])
def test_rotation_about_one_horizontal_axis_never_reports_the_axial_lever_arm(lever_arm):
    """Turning about one horizontal axis: gravity sweeps a plane, so the rotation may be determined, but the lever
    arm along the axis is not (w x r and w x (w x r) vanish for r along w).  The pipeline promises
    (calibrate_imu_pair): an error, or a lever arm left out with a note when not forced; forced (True), an error.
    Whatever it returns must be right: rotation within chi2(3) 99.9 %, time offset within 3 sigma."""
    scenario = one_axis_pair([1.0, 0.0, 0.0])
    rec = scenario.perturbed_measurements(1)
    try:
        cal = calibrate_imu_pair(rec, "imu0", "imu1", lever_arm=lever_arm)
    except DegenerateDataError as err:
        assert "axes" in str(err)  # says what motion to add
        return
    est = cal.estimate
    assert lever_arm is None, "a forced lever arm along the only rotation axis must be refused"
    assert est.lever_arm_m is None and any("lever arm" in note for note in est.notes), est.notes
    e = Rotation.from_matrix(scenario.R_imu0_imu1.T @ est.R_imu0_imu1).as_rotvec()
    assert float(e @ np.linalg.solve(est.rotation_cov_rad2, e)) < chi2.ppf(0.999, 3)
    if est.time_offset_s is not None:
        assert abs(est.time_offset_s - scenario.dt_s) < 3 * est.time_offset_sigma_s
