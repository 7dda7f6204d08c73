"""Use cases of two rigidly mounted IMUs: ``selfcal calibrate imu-pair`` (recording in, result object out) and
the Monte Carlo study of the rotation estimate.

Monte Carlo: is the estimator as good as the Cramér–Rao bound says, and are its sigmas honest?  One scenario
(fixed truth), many noise realisations (seeded).  For each run the graph estimate, its reported covariance and
the error against the truth; the bound is the graph's marginal covariance linearised at the truth with the
true noise sigmas.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from selfcal.baselines import imu_pair as patent
from selfcal.graphs import imu_pair as gp
from selfcal.core import so3
from selfcal.core.inertial import ImuNoise
from selfcal.sim.imu import ImuPairScenario
from selfcal.sim.trajectories import MultiPositionTrajectory
from selfcal.core.solve import DegenerateDataError
from selfcal.io.exports import homogeneous
from selfcal.io.recording import Recording, read_recording
from selfcal.pipelines.imu import _imu_names, nested_list
from selfcal.pipelines.fleet import flat_columns, register_study, register_task, sensor_option


# --- calibration ---------------------------------------------------------------------------------------------

@dataclass
class PairCalibration:
    imu0: str
    imu1: str
    estimate: gp.PairEstimate
    n_static: int
    n_dynamic: int

    def to_dict(self) -> dict:
        e = self.estimate
        out = {
            "imu0": self.imu0, "imu1": self.imu1,
            "rotation_imu0_imu1": nested_list(e.R_imu0_imu1),
            "rotation_sigma_rad": nested_list(np.sqrt(np.diag(e.rotation_cov_rad2))),
            "rotation_convention": "v_imu0 = R v_imu1; sigma on the right-perturbation tangent (imu1 axes)",
            "time_offset_s": e.time_offset_s, "time_offset_sigma_s": e.time_offset_sigma_s,
            "time_offset_convention": "t_imu0 = t_imu1 + dt",
            "lever_arm_m": nested_list(e.lever_arm_m) if e.lever_arm_m is not None else None,
            "lever_arm_sigma_m": nested_list(e.lever_arm_sigma_m) if e.lever_arm_sigma_m is not None else None,
            "T_imu0_imu1": homogeneous(e.R_imu0_imu1, np.zeros(3) if e.lever_arm_m is None else e.lever_arm_m),
            "T_imu0_imu1_convention": "p_imu0 = T p_imu1 (4x4 homogeneous): rotation_imu0_imu1, and imu1's position "
                                      "in the imu0 frame (lever_arm_m; zero when not estimated)",
            "relative_gain_imu1": {
                name: {"G": nested_list(G), "S_sigma": nested_list(sigma),
                       "meaning": "v_imu0 = R G v_imu1, G = I + S symmetric: imu1's scale and non-orthogonality"}
                for name, (G, sigma) in e.gains.items()},
            "residual_rms": e.residual_rms,
            "static_poses": self.n_static, "dynamic_samples": self.n_dynamic,
            "notes": e.notes,
        }
        return out

    def summary(self) -> str:
        e = self.estimate
        angle = np.degrees(np.linalg.norm(so3.log(e.R_imu0_imu1)))
        sigma = np.degrees(np.sqrt(np.max(np.linalg.eigvalsh(e.rotation_cov_rad2))))
        lines = [f"{self.imu0} <- {self.imu1}: rotation {angle:.3f} deg (1-sigma {sigma:.3g} deg) from "
                 f"{self.n_static} static poses and {self.n_dynamic} moving samples"]
        if e.time_offset_s is not None:
            lines.append(f"  time offset {e.time_offset_s * 1e3:.3f} ms (1-sigma {e.time_offset_sigma_s * 1e3:.3g} ms)")
        if e.lever_arm_m is not None:
            lines.append(f"  lever arm {np.round(e.lever_arm_m, 4)} m (1-sigma {np.round(e.lever_arm_sigma_m, 4)} m)")
        lines += [f"  note: {n}" for n in e.notes]
        return "\n".join(lines)


@dataclass(frozen=True)
class Optional_:
    """A pair quantity estimated only where the data determine it: its 1-sigma must stay below ``limit``."""

    label: str
    sigma: object  # PairEstimate -> float
    limit: float
    hint: str


# A lever arm known only to a centimetre, a clock offset only to a millisecond or a relative gain only to 0.2 %
# is not worth reporting as calibrated: at hand-held rates each changes the prediction by less than MEMS noise.
OPTIONAL = {
    "time_offset": Optional_("time offset", lambda e: e.time_offset_sigma_s, 1e-3,
                             "needs rotation whose rate changes quickly (shake or twist the rig)"),
    "lever_arm": Optional_("lever arm", lambda e: float(np.max(e.lever_arm_sigma_m)), 0.01,
                           "needs rotation rate and angular acceleration about several axes"),
    "accel_gain": Optional_("accelerometer relative gain", lambda e: float(np.max(e.gains["accel"][1])), 2e-3,
                            "needs static poses or motion with gravity along all three axes"),
    "gyro_gain": Optional_("gyro relative gain", lambda e: float(np.max(e.gains["gyro"][1])), 2e-3,
                           "needs rotation about all three axes"),
}


MIN_SAMPLES, MIN_DURATION_S = 50, 1.0  # the shortest static pose the pair graph uses; filters need 4 x order


def calibrate_imu_pair(recording: Recording, imu0: str, imu1: str, lever_arm: bool | None = None,
                       time_offset: bool | None = None, lowpass_hz: float | None = 5.0,
                       gains: bool | None = False) -> PairCalibration:
    """Rotation imu0 <- imu1 from the static poses (if any) and the moving parts of the recording.

    ``lever_arm`` / ``time_offset`` / ``gains``: True forces, False skips, None estimates where the data
    determine them (1-sigma below the limits in ``OPTIONAL``), and says so in the notes otherwise.
    ``gains`` (off by default) adds imu1's scale and non-orthogonality relative to imu0, for raw outputs that
    were not calibrated first: R is then the rotation part of the map between them (polar decomposition).
    """
    data0, data1 = recording.imu(imu0), recording.imu(imu1)
    for data in (data0, data1):
        if data.t_s.size < MIN_SAMPLES or data.t_s[-1] < MIN_DURATION_S:
            raise DegenerateDataError(f"{data.name}: {data.t_s.size} samples over {data.t_s[-1]:.3g} s: a pair "
                                      f"calibration needs at least {MIN_DURATION_S:g} s ({MIN_SAMPLES} samples) of "
                                      "static poses or motion")
    problem = gp.problem_from_imus(data0, data1, lowpass_hz)
    static, dynamic, dt0 = problem.static, problem.dynamic, problem.initial_dt_s
    if not static and dynamic is None:
        raise DegenerateDataError(f"{imu0}/{imu1}: no static poses and no motion found in the recording")
    requested = {"time_offset": time_offset, "lever_arm": lever_arm, "accel_gain": gains, "gyro_gain": gains}
    possible = {"time_offset": dynamic is not None, "lever_arm": dynamic is not None,
                "accel_gain": dynamic is not None or len(static) >= 6, "gyro_gain": dynamic is not None}
    model = gp.PairModel(**{name: possible[name] and requested[name] is not False for name in OPTIONAL})
    estimate = gp.solve_pair(static, dynamic, model, initial_dt_s=dt0)
    weak = {name: getattr(model, name) and spec.sigma(estimate) > spec.limit for name, spec in OPTIONAL.items()}
    for name, spec in OPTIONAL.items():
        if weak[name] and requested[name]:
            raise DegenerateDataError(f"{imu0}/{imu1}: {spec.label} not determined by this recording: {spec.hint}")
    if any(weak.values()):
        model = gp.PairModel(**{name: getattr(model, name) and not weak[name] for name in OPTIONAL})
        estimate = gp.solve_pair(static, dynamic, model, initial_dt_s=dt0)
        estimate.notes += [f"{spec.label} not estimated: the data do not determine it ({spec.hint})"
                           for name, spec in OPTIONAL.items() if weak[name]]
    return PairCalibration(imu0, imu1, estimate, len(static), 0 if dynamic is None else len(dynamic.t0_s))


# --- Monte Carlo study of the rotation ----------------------------------------------------------------------

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


def audit_system(recording: Recording, base: str, sensors: list[str] | None = None):
    """The audit's view of two IMUs (``sensors``, default the recording's first two) against the rotation."""
    from selfcal.audit.imu_pair import ImuPairAudit
    imu0, imu1 = _imu_names(recording, sensors, 2)
    return ImuPairAudit(recording.imu(imu0), recording.imu(imu1))


# --- fleet and Monte Carlo on dask ------------------------------------------------------------------------------

def calibrate_imu_pair_task(recording_path, options: dict) -> dict:
    """Rotation (time offset, lever arm) between two IMUs (``selfcal calibrate imu-pair``), flattened.

    Options as the command: ``imu0``, ``imu1`` (default the first two), ``lever_arm``, ``time_offset``,
    ``gains`` (true / false / unset = where the data determine it), ``lowpass_hz`` (default 5, 0: none).
    """
    rec = read_recording(recording_path)
    imu0, imu1 = sensor_option(rec, options, "imu0", 0), sensor_option(rec, options, "imu1", 1)
    lowpass = options.get("lowpass_hz", 5.0)
    cal = calibrate_imu_pair(rec, imu0, imu1, lever_arm=options.get("lever_arm"),
                             time_offset=options.get("time_offset"), lowpass_hz=float(lowpass) or None,
                             gains=options.get("gains", False))
    d = cal.to_dict()
    # conventions are no columns; T_imu0_imu1 repeats the rotation and lever arm columns
    for key in ("rotation_convention", "time_offset_convention", "T_imu0_imu1", "T_imu0_imu1_convention"):
        d.pop(key)
    for gain in d["relative_gain_imu1"].values():
        gain.pop("meaning")
    rotation_vector = so3.log(np.asarray(cal.estimate.R_imu0_imu1))
    return {"rotation_angle_deg": float(np.degrees(np.linalg.norm(rotation_vector))),
            **flat_columns({"rotation_vector_rad": rotation_vector}), **flat_columns(d)}


def _rotation_study_block(n_runs: int, first_seed: int, **params) -> RotationStudy:
    return imu_pair_rotation_study(n_runs, first_seed=first_seed, **params)


def _combine_rotation_studies(blocks: list[RotationStudy]) -> RotationStudy:
    return RotationStudy(errors_graph=np.concatenate([b.errors_graph for b in blocks]),
                         nees=np.concatenate([b.nees for b in blocks]), bound_cov=blocks[0].bound_cov,
                         errors_patent=np.concatenate([b.errors_patent for b in blocks]),
                         seconds_graph=sum(b.seconds_graph for b in blocks),
                         seconds_patent=sum(b.seconds_patent for b in blocks))


register_task("calibrate-imu-pair", calibrate_imu_pair_task,
              ("imu0", "imu1", "lever_arm", "time_offset", "gains", "lowpass_hz"),
              "rotation (time offset, lever arm) between two IMUs")
register_study("imu-pair-rotation", _rotation_study_block, _combine_rotation_studies)
