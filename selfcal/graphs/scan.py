"""The mobile scan as a factor graph (patent 001): per-clock poses, sphere centres and the INS error terms.

Variables: ``X(m)`` (Pose3) for every clock m of set B; ``O(j)`` (vector 3) for every sphere; ``D(0)`` the 15
error terms in units of their prior sigma; optional extensions (the audit's catalog): ``A(0)`` accelerometer
scale, ``G(0)`` gyro scale (3 each, in units of ``EXTENSION_SCALE``), ``T(0)`` camera-to-INS clock offset (s),
``E(0)`` extrinsic rotation error (rad), ``R(0)`` sphere radius error (m).

Factors: :func:`selfcal.factors.scan.sphere_surface_factor` for every (clock, sphere) of set B,
:func:`selfcal.factors.scan.inertial_tie_factor` for every clock of set B, and GTSAM's ``PriorFactorVector``
on the error terms (the INS's specification; it also fixes the gauge the spheres leave free: a sphere of
unknown position cannot tell where the whole scan is).  Batch: Levenberg-Marquardt on the finished scan.
Online: iSAM2, one sphere passage at a time, as the scan proceeds (each sphere is added once the scan plane has
left it).  The estimated error terms then correct every clock, i.e. the whole point set A.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from selfcal.factors import scan as fs
from selfcal.core.solve import DegenerateDataError, dense_joint_covariance, optimize
from selfcal.models import scan as ms
from selfcal.core.sphere import SphereNotFoundError, fit_sphere

log = logging.getLogger(__name__)

X_KEY, O_KEY = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.O
THETA = gtsam.symbol_shorthand.D(0)
EXT_KEYS = {"accel_scale": gtsam.symbol_shorthand.A(0), "gyro_scale": gtsam.symbol_shorthand.G(0),
            "time_offset": gtsam.symbol_shorthand.T(0), "extrinsic_rotation": gtsam.symbol_shorthand.E(0),
            "sphere_radius": gtsam.symbol_shorthand.R(0)}
EXT_DIM = {"accel_scale": 3, "gyro_scale": 3, "time_offset": 1, "extrinsic_rotation": 3, "sphere_radius": 1}
#: variable units of the extension blocks (the graph holds value / scale)
EXTENSION_SCALE = {"accel_scale": 1e-3, "gyro_scale": 1e-3, "time_offset": 1.0, "extrinsic_rotation": 1.0,
                   "sphere_radius": 1.0}
#: weak priors on the extensions (what a user would call implausible): keep the graph positive definite
#: where the data hardly see an effect, far wider than any effect the audit is meant to find
EXTENSION_PRIOR = {"accel_scale": 0.05, "gyro_scale": 0.05, "time_offset": 1.0, "extrinsic_rotation": 0.1,
                   "sphere_radius": 0.05}


@dataclass
class SphereObservation:
    """The points of one clock on one sphere (a piece of set B)."""

    clock: int  # index into the scan's clocks
    sphere: int
    vision_p: np.ndarray  # (k, 3) m, vision frame
    sigmas_m: np.ndarray  # (k,) radial 1-sigma


@dataclass
class ScanProblem:
    """Everything the graph needs: INS, its error sensitivity, the clocks of set B and their observations."""

    ins_t_s: np.ndarray
    ins_R: np.ndarray
    ins_r: np.ndarray
    ins_v: np.ndarray
    ins_gyro: np.ndarray
    sensitivity: ms.ErrorSensitivity
    clock_t_s: np.ndarray  # (M,) all clocks (INS time base, s)
    observations: list[SphereObservation]
    centers0: np.ndarray  # (S, 3) initial sphere centres (fit in the INS-corrected cloud)
    radius_m: float
    imu_R_vision: np.ndarray
    imu_t_vision: np.ndarray
    prior_sigmas: np.ndarray  # (15,)
    jitter_sigmas: np.ndarray  # (6,) rad x3, m x3
    prior_mean: np.ndarray | None = None  # (15,) the prior's mean of the terms: -theta already removed from the INS
    #: frames registered against each other (ICP): used by the batch graphs when ``ScanModel.registration``
    registrations: list = field(default_factory=list)

    def b_clocks(self) -> np.ndarray:
        return np.unique([o.clock for o in self.observations])


@dataclass
class FrameRegistration:
    """Two frames (points of consecutive clocks, each in its anchor clock's IMU frame) registered by ICP."""

    clock_a: int  # anchor clock of the target frame
    clock_b: int  # anchor clock of the source frame
    a_T_b: np.ndarray  # (4, 4) registered relative pose (IMU at clock b into IMU at clock a)
    sqrt_information: np.ndarray  # (r, 6) on the directions the registration sees (tangent [omega, v])


@dataclass(frozen=True)
class ScanModel:
    """Which extensions of the base model (15 error terms) are estimated."""

    extensions: tuple[str, ...] = ()
    #: add :func:`selfcal.factors.scan.registration_theta_factor` for ``ScanProblem.registrations`` (batch only)
    registration: bool = False

    def has(self, name: str) -> bool:
        return name in self.extensions


@dataclass
class ScanSolution:
    theta: np.ndarray  # (15,) error terms, physical units
    theta_cov: np.ndarray  # (15, 15)
    centers: np.ndarray  # (S, 3)
    centers_cov: np.ndarray  # (S, 3, 3)
    extensions: dict = field(default_factory=dict)  # name -> (value (physical), cov)
    values: gtsam.Values | None = None
    graph: gtsam.NonlinearFactorGraph | None = None
    seconds: float = 0.0
    history: list = field(default_factory=list)  # online: (time s, theta) after each sphere
    #: joint covariance of the 15 terms (physical units) and all sphere centres (m), ``15 + 3 S`` square, NaN
    #: rows for a sphere without points: what the predicted accuracy of points and distances comes from
    terms_centers_cov: np.ndarray | None = None

    def extension_value(self, name: str) -> np.ndarray:
        return self.extensions[name][0] if name in self.extensions else np.zeros(EXT_DIM[name])


def clock_inputs(problem: ScanProblem, clocks: np.ndarray, dt_s: float = 0.0):
    """INS pose, sensitivity and body twist at the given clocks (stamp + dt)."""
    t = problem.clock_t_s[clocks] + dt_s
    R, r = ms.interpolate_poses(t, problem.ins_t_s, problem.ins_R, problem.ins_r)
    Phi = problem.sensitivity.at(t)
    twist = ms.body_twist(t, problem.ins_t_s, problem.ins_r, problem.ins_v, problem.ins_R, problem.ins_gyro)
    return R, r, Phi, twist


def _theta_blocks(problem: ScanProblem, model: ScanModel):
    blocks = [(THETA, np.arange(ms.N_TERMS), problem.prior_sigmas)]
    for name in ("accel_scale", "gyro_scale"):
        if model.has(name):
            s = ms.EXTENSIONS[name]
            blocks.append((EXT_KEYS[name], np.arange(s.start, s.stop), EXTENSION_SCALE[name]))
    return blocks


def factors_for_clocks(problem: ScanProblem, model: ScanModel, clocks, observations, initial_theta=None):
    """Tie factors for ``clocks`` and sphere factors for ``observations``; initial poses from the INS."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    clocks = np.asarray(clocks, dtype=int)
    if len(clocks):
        R, r, Phi, twist = clock_inputs(problem, clocks)
        blocks = _theta_blocks(problem, model)
        eta0 = np.zeros(sum(len(c) for _, c, _ in blocks)) if initial_theta is None else initial_theta
        cols = np.concatenate([c for _, c, _ in blocks])
        scale = np.concatenate([np.broadcast_to(s, len(c)) for _, c, s in blocks])
        for i, m in enumerate(clocks):
            graph.add(fs.inertial_tie_factor(problem.jitter_sigmas, R[i], r[i], Phi[i], X_KEY(int(m)), blocks,
                                             EXT_KEYS["time_offset"] if model.has("time_offset") else None,
                                             twist[i]))
            Rc, rc = ms.corrected_pose(R[i], r[i], Phi[i][:, cols] * scale, eta0)
            values.insert(X_KEY(int(m)), gtsam.Pose3(gtsam.Rot3(Rc), rc))
    for obs in observations:
        graph.add(fs.sphere_surface_factor(
            obs.sigmas_m, obs.vision_p, problem.imu_R_vision, problem.imu_t_vision, problem.radius_m,
            X_KEY(obs.clock), O_KEY(obs.sphere),
            EXT_KEYS["extrinsic_rotation"] if model.has("extrinsic_rotation") else None,
            EXT_KEYS["sphere_radius"] if model.has("sphere_radius") else None))
    return graph, values


def prior_factors(model: ScanModel, problem: ScanProblem | None = None):
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    mean = (np.zeros(ms.N_TERMS) if problem is None or problem.prior_mean is None
            else np.asarray(problem.prior_mean, float) / problem.prior_sigmas)
    graph.add(gtsam.PriorFactorVector(THETA, mean, gtsam.noiseModel.Unit.Create(ms.N_TERMS)))
    values.insert(THETA, np.zeros(ms.N_TERMS))
    for name in model.extensions:
        key, dim = EXT_KEYS[name], EXT_DIM[name]
        graph.add(gtsam.PriorFactorVector(key, np.zeros(dim), gtsam.noiseModel.Isotropic.Sigma(
            dim, EXTENSION_PRIOR[name] / EXTENSION_SCALE[name])))
        values.insert(key, np.zeros(dim))
    return graph, values


def build(problem: ScanProblem, model: ScanModel = ScanModel()):
    """The whole graph of a finished scan and its initial values."""
    if not problem.observations:
        raise DegenerateDataError("no sphere points (set B is empty): the scan cannot be corrected")
    graph, values = prior_factors(model, problem)
    g, v = factors_for_clocks(problem, model, problem.b_clocks(), problem.observations)
    graph.push_back(g)
    graph.push_back(registration_factors(problem, model))
    values.insert(v)
    for j, c in enumerate(problem.centers0):
        if any(o.sphere == j for o in problem.observations):
            values.insert(O_KEY(j), np.asarray(c, dtype=float))
    return graph, values


def registration_factors(problem: ScanProblem, model: ScanModel) -> gtsam.NonlinearFactorGraph:
    """One :func:`selfcal.factors.scan.registration_theta_factor` per registered frame pair (none unless
    ``model.registration``); the anchors are taken at their stamps (no clock-offset term)."""
    graph = gtsam.NonlinearFactorGraph()
    if not (model.registration and problem.registrations):
        return graph
    clocks = np.unique([[g.clock_a, g.clock_b] for g in problem.registrations])
    R, r, Phi, _ = clock_inputs(problem, clocks)
    row = {m: i for i, m in enumerate(clocks)}
    blocks = _theta_blocks(problem, model)
    for g in problem.registrations:
        a, b = row[g.clock_a], row[g.clock_b]
        graph.add(fs.registration_theta_factor(g.sqrt_information,
                                               ms.relative_jitter_covariance(g.a_T_b, problem.jitter_sigmas),
                                               g.a_T_b, (R[a], r[a]), (R[b], r[b]), Phi[a], Phi[b], blocks))
    return graph


def build_collapsed(problem: ScanProblem, model: ScanModel = ScanModel(), term_columns=None):
    """The graph without per-clock poses (:func:`selfcal.factors.scan.sphere_theta_factor`): error terms,
    centres and extensions only.  The INS jitter is marginalised into each factor's covariance (exact for the
    linearised tie); the audit uses this graph so its score tests handle tens of variables, not hundreds.
    ``term_columns``: per observation (index), the audit's generic radius terms ``[(key, phi over its points)]``."""
    term_columns = term_columns or {}
    if not problem.observations:
        raise DegenerateDataError("no sphere points (set B is empty): the scan cannot be corrected")
    graph, values = prior_factors(model, problem)
    clocks = problem.b_clocks()
    R, r, Phi, twist = clock_inputs(problem, clocks)
    row = {m: i for i, m in enumerate(clocks)}
    blocks = _theta_blocks(problem, model)
    for n_obs, obs in enumerate(problem.observations):
        i = row[obs.clock]
        # the INS jitter moves all points of the clock together: marginalised into a full covariance
        # C = diag(sigma^2) + J_pose diag(jitter^2) J_pose^T (linear, at the INS pose and the detected centre)
        p_I = obs.vision_p @ problem.imu_R_vision.T + problem.imu_t_vision
        _, d_pose, _, _ = ms.sphere_surface_residuals(R[i], r[i], p_I, problem.centers0[obs.sphere], problem.radius_m,
                                                      with_jacobians=True)
        cov = np.diag(obs.sigmas_m**2) + (d_pose * problem.jitter_sigmas**2) @ d_pose.T
        graph.add(fs.sphere_theta_factor(
            cov, obs.vision_p, problem.imu_R_vision, problem.imu_t_vision, problem.radius_m, R[i], r[i],
            Phi[i], O_KEY(obs.sphere), blocks, EXT_KEYS["time_offset"] if model.has("time_offset") else None,
            twist[i], EXT_KEYS["extrinsic_rotation"] if model.has("extrinsic_rotation") else None,
            EXT_KEYS["sphere_radius"] if model.has("sphere_radius") else None, term_columns.get(n_obs, ())))
    graph.push_back(registration_factors(problem, model))
    for j in sorted({o.sphere for o in problem.observations}):
        values.insert(O_KEY(j), np.asarray(problem.centers0[j], dtype=float))
    return graph, values


def _solution(problem, model, graph, values, seconds, covariance=True) -> ScanSolution:
    spheres = sorted({o.sphere for o in problem.observations})
    theta = values.atVector(THETA) * problem.prior_sigmas
    keys = [THETA] + [O_KEY(j) for j in spheres] + [EXT_KEYS[n] for n in model.extensions]
    if covariance:
        # the same information with the poses eliminated (the jitter folded into each clock's covariance): tens
        # of unknowns, solved densely with equilibration.  gtsam.Marginals on the full graph agrees but takes
        # seconds (the error terms join every pose into one root clique) and its Cholesky can refuse the graph
        joint = covariance_at(problem, model, values, keys)
    else:
        joint = np.full((sum(values.atVector(k).size for k in keys),) * 2, np.nan)
    cov, start = {}, 0
    for k in keys:
        n = values.atVector(k).size
        cov[k] = joint[start:start + n, start:start + n]
        start += n
    S = len(problem.centers0)
    centers = np.full((S, 3), np.nan)
    centers_cov = np.full((S, 3, 3), np.nan)
    for j in spheres:
        centers[j] = values.atVector(O_KEY(j))
        centers_cov[j] = cov[O_KEY(j)]
    s = problem.prior_sigmas
    ext = {}
    for n in model.extensions:
        k = EXT_KEYS[n]
        sc = EXTENSION_SCALE[n]
        ext[n] = (values.atVector(k) * sc, cov[k] * sc**2)
    # [theta (physical), every centre]: the joint block, rescaled; spheres without points stay NaN
    n_tc = ms.N_TERMS + 3 * len(spheres)
    index = np.r_[np.arange(ms.N_TERMS), ms.N_TERMS + 3 * np.repeat(spheres, 3) + np.tile(np.arange(3), len(spheres))]
    unit = np.r_[s, np.ones(3 * len(spheres))]
    terms_centers = np.full((ms.N_TERMS + 3 * S,) * 2, np.nan)
    terms_centers[np.ix_(index, index)] = joint[:n_tc, :n_tc] * np.outer(unit, unit)
    return ScanSolution(theta, cov[THETA] * np.outer(s, s), centers, centers_cov, ext, values, graph, seconds,
                        terms_centers_cov=terms_centers)


def covariance_at(problem: ScanProblem, model: ScanModel, values: gtsam.Values, keys) -> np.ndarray:
    """Joint covariance of ``keys`` (graph units) from the collapsed graph linearised at ``values``: the
    posterior of a solved scan, or, at the true values of a planned scan, its linear covariance analysis."""
    small, _ = build_collapsed(problem, model)
    reduced = gtsam.Values()
    for k in keys:
        reduced.insert(k, values.atVector(k))
    return dense_joint_covariance(small, reduced, keys, "the INS error terms and sphere centres")


def solve_batch(problem: ScanProblem, model: ScanModel = ScanModel(), covariance: bool = True) -> ScanSolution:
    """Levenberg-Marquardt on the finished scan."""
    start = time.perf_counter()
    graph, values = build(problem, model)
    # LM on the full graph crawls (stiff INS ties next to free poses: it spends 50 iterations in the valley);
    # the collapsed graph (tens of unknowns) solves the same problem with the jitter folded in, and the full graph
    # then converges from its solution in a few iterations
    small, small_values = build_collapsed(problem, model)
    small_result = optimize(small, small_values, max_iterations=100)
    eta = np.concatenate([small_result.atVector(k) for k, _, _ in _theta_blocks(problem, model)])
    _, poses = factors_for_clocks(problem, model, problem.b_clocks(), [], eta)
    initial = gtsam.Values()
    for k in values.keys():
        initial.insert(k, poses.atPose3(k)) if poses.exists(k) else initial.insert(k, small_result.atVector(k))
    # QR, not Cholesky: centres known to micrometres next to weakly seen terms make Cholesky's pivots
    # indeterminate, LM then holds lambda at 1e3 and crawls (10 M-point scan, 447 clocks: 29 iterations, 11 s,
    # stopped 87 um short of the optimum in the centres); QR reaches the lower minimum in 2 iterations
    result = optimize(graph, initial, max_iterations=50, linear_solver="MULTIFRONTAL_QR")
    log.debug("scan batch: error %.6g -> %.6g", graph.error(values), graph.error(result))
    return _solution(problem, model, graph, result, time.perf_counter() - start, covariance)


def solve_online(problem: ScanProblem, model: ScanModel = ScanModel(), covariance: bool = True) -> ScanSolution:
    """iSAM2, one sphere passage at a time in the order the scan reaches them."""
    start = time.perf_counter()
    if not problem.observations:
        raise DegenerateDataError("no sphere points (set B is empty): the scan cannot be corrected")
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(1e-4)  # poses move by millimetres: 0.01 (m, rad) would freeze them
    params.setFactorization("QR")  # Cholesky meets indeterminate systems: centres known to micrometres next to
    # error terms the spheres hardly see (information ratios ~1e12)
    isam = gtsam.ISAM2(params)
    first = {}
    for o in problem.observations:
        first[o.sphere] = min(first.get(o.sphere, o.clock), o.clock)
    done_clocks: set[int] = set()
    history = []
    graph_all = gtsam.NonlinearFactorGraph()
    estimate = None
    for n, j in enumerate(sorted(first, key=first.get)):
        obs = [o for o in problem.observations if o.sphere == j]
        clocks = sorted({o.clock for o in obs} - done_clocks)
        done_clocks.update(clocks)
        theta0 = None
        if estimate is not None:  # start the new poses from the current estimate of the error terms
            theta0 = np.concatenate([estimate.atVector(k) for k, _, _ in _theta_blocks(problem, model)])
        graph, values = factors_for_clocks(problem, model, clocks, obs, theta0)
        if n == 0:
            g, v = prior_factors(model, problem)
            graph.push_back(g)
            values.insert(v)
        values.insert(O_KEY(j), _center_for(problem, obs, values, estimate))
        isam.update(graph, values)
        isam.update()  # one more relinearisation pass: a new sphere can move the error terms a lot
        graph_all.push_back(graph)
        estimate = isam.calculateEstimate()
        t_now = problem.clock_t_s[max(o.clock for o in obs)]
        history.append((float(t_now), estimate.atVector(THETA) * problem.prior_sigmas))
    for _ in range(3):  # a few more relinearisation passes once the scan is over (each pass re-solves the
        # variables whose linearisation moved; iSAM2 makes one per update and can lag behind the batch)
        isam.update()
    estimate = isam.calculateEstimate()
    sol = _solution(problem, model, graph_all, estimate, time.perf_counter() - start, covariance)
    sol.history = history
    return sol


def _center_for(problem: ScanProblem, obs, new_values: gtsam.Values, estimate) -> np.ndarray:
    """Initial centre of a sphere consistent with its clocks' initial poses (the current error terms): the
    detection's centre sits in the uncorrected scan, centimetres away once the drift is being corrected."""
    pts = []
    for o in obs:
        X = new_values.atPose3(X_KEY(o.clock)) if new_values.exists(X_KEY(o.clock)) else estimate.atPose3(X_KEY(o.clock))
        pts.append(ms.world_points(X.rotation().matrix(), X.translation(), problem.imu_R_vision, problem.imu_t_vision,
                                   o.vision_p))
    try:
        return fit_sphere(np.concatenate(pts), radius_m=problem.radius_m).center_m
    except SphereNotFoundError:
        return np.asarray(problem.centers0[obs[0].sphere], dtype=float)


def corrected_clock_poses(problem: ScanProblem, solution: ScanSolution, clocks=None):
    """World poses of the IMU at every clock (default: all) from the estimated error terms (set A)."""
    clocks = np.arange(len(problem.clock_t_s)) if clocks is None else np.asarray(clocks)
    dt = float(solution.extension_value("time_offset")[0]) if "time_offset" in solution.extensions else 0.0
    R, r, Phi, _ = clock_inputs(problem, clocks, dt)
    theta = [solution.theta]
    cols = [np.arange(ms.N_TERMS)]
    for name in ("accel_scale", "gyro_scale"):
        if name in solution.extensions:
            theta.append(solution.extensions[name][0])
            s = ms.EXTENSIONS[name]
            cols.append(np.arange(s.start, s.stop))
    cols = np.concatenate(cols)
    return ms.corrected_pose(R, r, Phi[:, :, cols], np.concatenate(theta))


def sphere_residuals(problem: ScanProblem, values: gtsam.Values, model: ScanModel) -> list[np.ndarray]:
    """Unwhitened sphere residuals (m) per observation at ``values``."""
    out = []
    for obs in problem.observations:
        f = fs.sphere_surface_factor(obs.sigmas_m, obs.vision_p, problem.imu_R_vision, problem.imu_t_vision,
                                     problem.radius_m, X_KEY(obs.clock), O_KEY(obs.sphere),
                                     EXT_KEYS["extrinsic_rotation"] if model.has("extrinsic_rotation") else None,
                                     EXT_KEYS["sphere_radius"] if model.has("sphere_radius") else None)
        out.append(f.unwhitenedError(values))
    return out
