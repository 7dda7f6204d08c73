"""Monte Carlo studies: is the estimator as good as the Cramér–Rao bound says, and are its sigmas honest?

One scenario (fixed truth), many noise realisations (seeded).  For each run the graph estimate, its reported
covariance and the error against the truth; the bound is the graph's marginal covariance linearised at the
truth with the true noise sigmas.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from selfcal.baselines import imu_pair as patent
from selfcal.graphs import imu_pair as gp
from selfcal.core import so3
from selfcal.sim.imu import ImuNoise, ImuPairScenario
from selfcal.sim.trajectories import MultiPositionTrajectory


@dataclass
class RotationStudy:
    """Per-run rotation errors (rad, right-perturbation tangent) of the graph and of the patent baseline."""

    errors_graph: np.ndarray  # (n, 3)
    nees: np.ndarray  # (n,) e^T P^-1 e with the graph's own reported P
    bound_cov: np.ndarray  # (3, 3) Cramér–Rao bound at the truth
    errors_patent: np.ndarray  # (n, 3)
    seconds_graph: float
    seconds_patent: float
    notes: dict = field(default_factory=dict)

    @property
    def rms_graph_rad(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.errors_graph**2, axis=1))))

    @property
    def rms_patent_rad(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.errors_patent**2, axis=1))))

    @property
    def rms_bound_rad(self) -> float:
        return float(np.sqrt(np.trace(self.bound_cov)))

    def summary(self) -> dict:
        n = len(self.nees)
        return {"runs": n,
                "rms_rotation_error_graph_deg": np.degrees(self.rms_graph_rad),
                "rms_rotation_bound_deg": np.degrees(self.rms_bound_rad),
                "efficiency_ratio": self.rms_graph_rad / self.rms_bound_rad,
                "mean_nees": float(np.mean(self.nees)), "nees_expected": 3.0,
                "rms_rotation_error_patent_deg": np.degrees(self.rms_patent_rad),
                "accuracy_ratio_patent_over_graph": self.rms_patent_rad / self.rms_graph_rad,
                "seconds_per_run_graph": self.seconds_graph / n,
                "seconds_per_run_patent": self.seconds_patent / n,
                "time_ratio_graph_over_patent": self.seconds_graph / self.seconds_patent}


def pair_scenario(seed: int = 7, n_poses: int = 8, rate_hz: float = 100.0) -> ImuPairScenario:
    """Two IMUs on a multi-position trajectory: white noise only (no bias walk), ideal intrinsics, so the
    pair model (R, dt, lever arm, relative offsets) is the whole truth and the bound applies exactly."""
    noise = ImuNoise(accelerometer_random_walk=0.0, gyroscope_random_walk=0.0)
    trajectory = MultiPositionTrajectory(n_poses=n_poses, static_s=3.0, move_s=2.0, seed=seed)
    return ImuPairScenario.random(trajectory, seed=seed, intrinsics=False, noise0=noise, noise1=noise,
                                  rate_hz=rate_hz)


def _truth_values(scenario: ImuPairScenario, model: gp.PairModel):
    pair = scenario.truth()["pair"]
    return gp.pair_values(pair["rotation_imu0_imu1"], model, pair["time_offset_s"], pair["lever_arm_m"])


def _with_true_sigmas(problem, scenario: ImuPairScenario):
    """The exact-data problem with the sigmas the simulated noise really has (for the bound)."""
    s_a0, s_g0 = _white(scenario.noise0, scenario.rate_hz)
    s_a1, s_g1 = _white(scenario.noise1, scenario.rate1_hz or scenario.rate_hz)
    for pair in problem.static:
        pair.sigma = np.full(3, np.sqrt(s_a0**2 / pair.n_samples0 + s_a1**2 / pair.n_samples1))
    if problem.dynamic is not None:
        problem.dynamic.gyro_sigma = float(np.hypot(s_g0, s_g1))
        problem.dynamic.accel_sigma = float(np.hypot(s_a0, s_a1))
    return problem


def _problem(recording, lowpass_hz):
    return gp.problem_from_imus(recording.imu("imu0"), recording.imu("imu1"), lowpass_hz)


def _white(noise: ImuNoise, rate_hz: float) -> tuple[float, float]:
    """Per-sample white-noise sigmas (accelerometer, gyro)."""
    return noise.accelerometer_noise_density * np.sqrt(rate_hz), noise.gyroscope_noise_density * np.sqrt(rate_hz)


def imu_pair_rotation_study(n_runs: int, scenario: ImuPairScenario | None = None, first_seed: int = 1000,
                            model: gp.PairModel = gp.PairModel(), lowpass_hz: float | None = 5.0) -> RotationStudy:
    """Graph estimate vs bound vs patent baseline over ``n_runs`` noise realisations of one scenario.

    The estimator runs as the pipeline does (zero-phase low-pass, reweighting, Huber); the bound uses every
    raw sample with its true white-noise sigma, so filtering that lost information would show as a ratio > 1.
    """
    scenario = scenario or pair_scenario()
    R_true = np.asarray(scenario.truth()["pair"]["rotation_imu0_imu1"])
    bound_problem = _with_true_sigmas(_problem(scenario.exact_measurements(), None), scenario)
    bound = gp.rotation_covariance_at(bound_problem.static, bound_problem.dynamic, model,
                                      _truth_values(scenario, model))
    errors, nees, errors_patent = [], [], []
    t_graph = t_patent = 0.0
    for run in range(n_runs):
        problem = _problem(scenario.perturbed_measurements(first_seed + run), lowpass_hz)
        start = time.perf_counter()
        est = gp.solve_pair(problem.static, problem.dynamic, model, initial_dt_s=problem.initial_dt_s)
        t_graph += time.perf_counter() - start
        e = so3.log(R_true.T @ est.R_imu0_imu1)
        errors.append(e)
        nees.append(float(e @ np.linalg.solve(est.rotation_cov_rad2, e)))
        start = time.perf_counter()
        baseline = patent.rotation_3d(np.array([p.accel0 for p in problem.static]),
                                      np.array([p.accel1 for p in problem.static]))
        t_patent += time.perf_counter() - start
        errors_patent.append(so3.log(R_true.T @ baseline.R_imu0_imu1))
    return RotationStudy(np.array(errors), np.array(nees), bound, np.array(errors_patent), t_graph, t_patent)
