"""Single-IMU intrinsics without external equipment, as one factor graph.

Variables: the up-direction ``u_k`` (Unit3, sensor frame) of every static pose, accelerometer bias and
upper-triangular M, gyro bias, M and (optionally) g-sensitivity A.  Factors:

* static accelerometer, per pose:  ``M_a (a_k - b_a) = g u_k``          (|f| = g and its direction)
* static gyro, per pose:            ``w_k = b_g + A g u_k``             (no rotation)
* gyro motion, per move k -> k+1:   ``u_{k+1} = delta_R(M_g, b_g, A)^T u_k``
  (Tedaldi et al. 2014 compare the integrated gyro with the accelerometer's gravity directions in a second
  stage; here both live in one graph, so the gyro also informs the directions and every sigma is joint.)

The specific force during a move (needed only for the small A f term) comes from a first, accelerometer-only
solve; this keeps the motion factor independent of the accelerometer blocks at a cost of second order in A.

Gaps in a move.  A stamp step longer than :data:`GAP_PERIODS` nominal sample periods (sensor.yaml ``rate_hz``) is
either samples lost (the rotation over the gap is unmeasured: holding the last rate over it is a guess) or a clock
jump (the rotation over it is zero); with one IMU nobody can tell which.  Either way the rotation over the gap's
excess ``dt - 1/rate_hz`` is unknown by up to ``|w| (dt - 1/rate_hz)``, ``|w|`` the bias-removed rate around it,
so that is added in quadrature to the move's 1-sigma angle (:func:`gap_angle_sigma_rad`).  Still, it is
harmless (``|w|`` is noise); turning, the move's rotation constraint weakens to what the data do know, and a
note names the move.  The real recordings' clocks step at most 1.04 nominal periods (Xsens MTi: 9.0-10.4 ms at
100 Hz; the MPU-6050 and Xsens DOT recordings are uniform), so 3 periods is a gap and never jitter.  A bursty USB
logger (the sunsided MPU-6050 logs: stalls of ~6 periods, then a burst) would have its turning moves weakened
(honestly: its stamps do not say when the samples were taken); none of its logs is a multi-position one.

Saturation in a move.  A gyro axis held at its limit (:func:`selfcal.core.sanity.saturated_samples`: the
column's extreme repeated) under-reads the rotation by an unknown amount: the true rate is beyond the limit.
Its 1-sigma is taken as the limit itself over the time held there (a true rate up to about twice the limit),
root sum square over the axes, added in quadrature to the move's angle sigma, and a note names the move.  The
real MPU-6050 recording (+-250 deg/s range) holds w_x at -4.3657 rad/s for 10 samples and w_z for 6: two of
its moves are weakened so, the others unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from selfcal.factors import imu as fimu
from selfcal.core.solve import DegenerateDataError, marginal_covariances, optimize, robust
from selfcal.io.recording import ImuData
from selfcal.models import imu
from selfcal.core import so3
from selfcal.core.sanity import saturated_samples
from selfcal.core.static_intervals import detect_static_intervals, require_static_poses, static_poses

U = gtsam.symbol_shorthand.U  # up-direction of static pose k
ACCEL_BIAS, ACCEL_M = gtsam.symbol("a", 0), gtsam.symbol("a", 1)
GYRO_BIAS, GYRO_M, GYRO_A = gtsam.symbol("g", 0), gtsam.symbol("g", 1), gtsam.symbol("g", 2)
ACCEL_DIAGONAL, ACCEL_OFF_DIAGONAL = (0, 3, 5), (1, 2, 4)  # in the 6 upper-triangular entries
GYRO_DIAGONAL, GYRO_OFF_DIAGONAL = (0, 4, 8), (1, 2, 3, 5, 6, 7)  # in the 9 row-major entries


@dataclass
class StaticPose:
    """Mean raw outputs of one static interval, the 1-sigma of those means (per axis), time and channels."""

    accel_mean: np.ndarray
    gyro_mean: np.ndarray
    accel_sigma: np.ndarray
    gyro_sigma: np.ndarray
    time_s: float = 0.0
    channels: dict = field(default_factory=dict)  # channel name -> mean over the pose


@dataclass
class Move:
    """Raw samples of the motion between two consecutive static poses."""

    gyro_raw: np.ndarray  # (n, 3) rad/s
    accel_raw: np.ndarray  # (n, 3) m/s^2
    dt_s: np.ndarray  # (n,) hold time of each sample
    angle_sigma_rad: float  # 1-sigma of the integrated angle from gyro white noise
    time_s: np.ndarray | None = None  # (n,)
    channels: dict = field(default_factory=dict)  # channel name -> (n,) samples


@dataclass
class IntrinsicsProblem:
    """Everything the graph needs from one IMU recording."""

    poses: list[StaticPose]
    moves: list[Move]  # moves[k] joins poses[k] and poses[k + 1]
    gravity_m_s2: float
    channel_units: dict = field(default_factory=dict)
    channel_refs: dict = field(default_factory=dict)  # reference value of each channel (mean over poses)
    notes: list[str] = field(default_factory=list)  # moves whose gaps weaken their rotation constraint

    def pose_deviation(self, k: int) -> dict:
        return {name: self.poses[k].channels[name] - ref for name, ref in self.channel_refs.items()}

    def move_deviation(self, k: int) -> dict:
        return {name: self.moves[k].channels[name] - ref for name, ref in self.channel_refs.items()}


@dataclass(frozen=True)
class IntrinsicsSpec:
    """Which blocks are estimated beyond the biases (which always are)."""

    accel_M_free: tuple[int, ...] = fimu.ALL_ACCEL_M
    gyro_M_free: tuple[int, ...] = fimu.ALL_GYRO_M
    gyro_A: bool = True
    accel_channels: tuple[str, ...] = ()  # accelerometer bias linear in these channels
    gyro_channels: tuple[str, ...] = ()

    @classmethod
    def bias_only(cls) -> "IntrinsicsSpec":
        return cls((), (), False)


@dataclass
class IntrinsicsEstimate:
    accel: imu.AccelIntrinsics
    gyro: imu.GyroIntrinsics
    covariance: dict[str, np.ndarray]  # block name -> marginal covariance
    up_S: np.ndarray  # (K, 3) estimated up-directions of the static poses
    accel_norm_residual_m_s2: np.ndarray  # (K,) |f_k| - g
    gyro_direction_residual_rad: np.ndarray  # (K-1,) angle between integrated and measured up-directions
    spec: IntrinsicsSpec = field(default_factory=IntrinsicsSpec)

    def sigma(self, block: str) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance[block]))


GAP_PERIODS = 3.0  # a stamp step longer than this many nominal sample periods is a gap (module docstring)
GAP_RATE_SAMPLES = 5  # the rate at a gap: the mean of this many samples either side (white noise / sqrt(10))


def gap_angle_sigma_rad(gyro_rad_s: np.ndarray, dt_s: np.ndarray, period_s: float) -> float:
    """1-sigma (rad) of the rotation a move's gaps leave unknown: the root sum square over every step ``dt_s[i]``
    longer than ``GAP_PERIODS * period_s`` of ``|w| (dt_s[i] - period_s)``, ``|w|`` the norm of the mean rate
    over the :data:`GAP_RATE_SAMPLES` samples either side of the gap (a single sample's noise would read as
    turning while the unit is still).

    ``gyro_rad_s`` (n, 3): bias-removed rates; sample i is held for ``dt_s[i]``.
    """
    gaps = np.flatnonzero(dt_s > GAP_PERIODS * period_s)
    speed = np.array([np.linalg.norm(np.mean(gyro_rad_s[max(0, i + 1 - GAP_RATE_SAMPLES):i + 1 + GAP_RATE_SAMPLES],
                                             axis=0)) for i in gaps])
    return float(np.sqrt(np.sum((speed * (dt_s[gaps] - period_s)) ** 2)))


MIN_POSES_FULL_ACCEL = 9  # bias (3) + upper-triangular M (6); each pose adds one net equation (|f| = g)


def problem_from_imu(data: ImuData, gravity_m_s2: float, **detector_options) -> IntrinsicsProblem:
    """Static poses (sigmas of their means, channel means) and the moves between them, from a recording.

    Raises TooFewStaticPosesError when the recording holds too few distinct static orientations.
    """
    t_s = data.t_s
    intervals = detect_static_intervals(t_s, data.accel_m_s2, **detector_options)
    stats = static_poses(t_s, data.accel_m_s2, data.gyro_rad_s, intervals)
    require_static_poses(stats, MIN_POSES_FULL_ACCEL)
    # pooled median: robust to one slightly moving pose; a tiny floor keeps noise-free (simulated exact) data
    # a regular system
    accel_std = np.maximum(np.median([p.accel_std for p in stats], axis=0), 1e-9)
    gyro_std = np.maximum(np.median([p.gyro_std for p in stats], axis=0), 1e-9)
    channels = {name: np.asarray(v, dtype=float) for name, v in data.channels.items()}
    poses = [StaticPose(p.accel_mean, p.gyro_mean, accel_std / np.sqrt(p.n_samples), gyro_std / np.sqrt(p.n_samples),
                        float(np.mean(t_s[p.start:p.end])),
                        {name: float(np.mean(v[p.start:p.end])) for name, v in channels.items()}) for p in stats]
    dt_all = np.diff(t_s, append=t_s[-1] + np.median(np.diff(t_s)))
    saturated = np.column_stack([saturated_samples(w) for w in data.gyro_rad_s.T])  # (n, 3)
    moves, notes = [], []
    for k, ((_, end), (start, _)) in enumerate(zip(intervals[:-1], intervals[1:])):
        # the last static sample is held until the first moving one: include it, so the whole move integrates
        idx = np.arange(end - 1, start)
        dt = dt_all[idx]
        noise_sigma = float(np.sqrt(np.mean(gyro_std**2) * np.sum(dt**2)))
        # rest output of the nearer pose (bias + its g-sensitivity) removed, so that still reads as noise only:
        # the mean of 2 GAP_RATE_SAMPLES noise samples, |w| ~ 0.55 sigma_w, against the held sample's own
        # sigma_w dt in noise_sigma: a gap while still stays under the noise and is not named
        rest = np.where((np.arange(len(idx)) < len(idx) / 2)[:, None], stats[k].gyro_mean, stats[k + 1].gyro_mean)
        gap_sigma = gap_angle_sigma_rad(data.gyro_rad_s[idx] - rest, dt, 1.0 / data.rate_hz)
        if gap_sigma > noise_sigma:  # turning across the gap: say so
            notes.append(f"{data.name}: move {k} ({t_s[idx[0]] - t_s[0]:.1f}-{t_s[idx[-1]] - t_s[0]:.1f} s) has a "
                         f"{float(dt.max()):.3g} s gap while turning: its rotation is known to {gap_sigma:.2g} rad "
                         f"only (gyro noise alone: {noise_sigma:.2g} rad)")
        held_s = np.sum(saturated[idx] * dt[:, None], axis=0)  # time each gyro axis sits at its limit
        saturation_sigma = float(np.linalg.norm(np.max(np.abs(data.gyro_rad_s), axis=0) * held_s))
        if saturation_sigma > 0.0:
            axes = ", ".join(f"w_{a} {held:.2g} s" for a, held in zip("xyz", held_s) if held > 0)
            notes.append(f"{data.name}: move {k} ({t_s[idx[0]] - t_s[0]:.1f}-{t_s[idx[-1]] - t_s[0]:.1f} s) has its "
                         f"gyro at the limit of its range ({axes}): its rotation is known to {saturation_sigma:.2g} "
                         f"rad only (gyro noise alone: {noise_sigma:.2g} rad)")
        moves.append(Move(data.gyro_rad_s[idx], data.accel_m_s2[idx], dt,
                          float(np.sqrt(noise_sigma**2 + gap_sigma**2 + saturation_sigma**2)),
                          t_s[idx], {name: v[idx] for name, v in channels.items()}))
    refs = {name: float(np.mean([p.channels[name] for p in poses])) for name in channels}
    return IntrinsicsProblem(poses, moves, gravity_m_s2, dict(data.channel_units), refs, notes)


def check_pose_geometry(poses: list[StaticPose], spec: IntrinsicsSpec) -> None:
    """Refuse geometry that cannot determine the accelerometer model, saying what poses to add."""
    up = np.array([p.accel_mean / np.linalg.norm(p.accel_mean) for p in poses])
    full = len(spec.accel_M_free) > 0
    needed = MIN_POSES_FULL_ACCEL if full else 3
    if len(poses) < needed:
        raise DegenerateDataError(
            f"{len(poses)} static poses, at least {needed} needed: hold the IMU still for a few seconds in more "
            "orientations (each of its 6 faces down, then tilted ones in between)")
    singular = np.linalg.svd(up, compute_uv=False) / np.sqrt(len(up))
    if singular[1] < 0.1:
        raise DegenerateDataError(
            "all static poses have (nearly) the same gravity direction: turn the IMU onto other faces")
    if singular[2] < 0.1:
        raise DegenerateDataError(
            "the static gravity directions lie in one plane: add poses with the remaining axis up and down")
    if full and np.linalg.svd(up - up.mean(axis=0), compute_uv=False)[2] / np.sqrt(len(up)) < 0.05:
        # directions on one cone (e.g. turning only about one axis): bias and scale trade off along the cone axis
        raise DegenerateDataError(
            "the static gravity directions lie on one cone (rotation about a single axis): add poses turned "
            "about another axis")


def channel_key(quantity: str, index: int) -> int:
    return gtsam.symbol("c" if quantity == "accel" else "d", index)


@dataclass
class IntrinsicsGraph:
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    accel_keys: fimu.AccelKeys
    gyro_keys: fimu.GyroKeys
    nominal_accel: imu.AccelIntrinsics
    nominal_gyro: imu.GyroIntrinsics
    pose_indices: list[int]

    def accel(self, values=None) -> imu.AccelIntrinsics:
        return fimu.accel_from_values(values or self.values, self.accel_keys, self.nominal_accel)

    def gyro(self, values=None) -> imu.GyroIntrinsics:
        return fimu.gyro_from_values(values or self.values, self.gyro_keys, self.nominal_gyro)

    def channel_slopes(self, values=None) -> dict[str, dict[str, np.ndarray]]:
        values = values or self.values
        return {"accel": {n: values.atVector(k) for n, k in self.accel_keys.channels},
                "gyro": {n: values.atVector(k) for n, k in self.gyro_keys.channels}}


def build_graph(problem: IntrinsicsProblem, spec: IntrinsicsSpec, huber_k: float | None = 3.0,
                pose_indices=None, nominal_accel: imu.AccelIntrinsics | None = None,
                nominal_gyro: imu.GyroIntrinsics | None = None) -> IntrinsicsGraph:
    """The intrinsics graph over a subset of poses (default all) and the moves between consecutive ones in it,
    with initial values from an accelerometer-only solve (which also gives the specific force in the moves)."""
    poses = list(range(len(problem.poses))) if pose_indices is None else list(pose_indices)
    nominal_accel = nominal_accel or imu.AccelIntrinsics()
    nominal_gyro = nominal_gyro or imu.GyroIntrinsics()
    g = problem.gravity_m_s2
    accel_keys = fimu.AccelKeys(bias=ACCEL_BIAS, M=ACCEL_M if spec.accel_M_free else None,
                                M_free=spec.accel_M_free,
                                channels=tuple((n, channel_key("accel", i)) for i, n in enumerate(spec.accel_channels)))
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    values.insert(ACCEL_BIAS, nominal_accel.bias.copy())
    if accel_keys.M is not None:
        values.insert(ACCEL_M, fimu.free_entries(nominal_accel.M, accel_keys))
    for _, key in accel_keys.channels:
        values.insert(key, np.zeros(3))
    for k in poses:
        pose = problem.poses[k]
        f0 = nominal_accel.specific_force(pose.accel_mean[None])[0]
        values.insert(U(k), gtsam.Unit3(f0 / np.linalg.norm(f0)))
        graph.add(fimu.static_accel_factor(robust(pose.accel_sigma, huber_k), pose.accel_mean, g, U(k), accel_keys,
                                           nominal_accel, problem.pose_deviation(k)))
    values = optimize(graph, values)
    accel_stage1 = fimu.accel_from_values(values, accel_keys, nominal_accel)

    moves = [k for k in poses[:-1] if k + 1 in poses and k < len(problem.moves)]
    gyro_keys = fimu.GyroKeys(bias=GYRO_BIAS, M=GYRO_M if spec.gyro_M_free and moves else None,
                              M_free=spec.gyro_M_free, A=GYRO_A if spec.gyro_A else None,
                              channels=tuple((n, channel_key("gyro", i)) for i, n in enumerate(spec.gyro_channels)))
    values.insert(GYRO_BIAS, np.mean([problem.poses[k].gyro_mean for k in poses], axis=0))
    if gyro_keys.M is not None:
        values.insert(GYRO_M, fimu.free_entries(nominal_gyro.M, gyro_keys))
    if gyro_keys.A is not None:
        values.insert(GYRO_A, nominal_gyro.A.ravel().copy())
    for _, key in gyro_keys.channels:
        values.insert(key, np.zeros(3))
    for k in poses:
        pose = problem.poses[k]
        graph.add(fimu.static_gyro_factor(robust(pose.gyro_sigma, huber_k), pose.gyro_mean, g, U(k), gyro_keys,
                                          nominal_gyro, problem.pose_deviation(k)))
    for k in moves:
        move = problem.moves[k]
        graph.add(fimu.gyro_motion_factor(robust(np.full(3, move.angle_sigma_rad), huber_k), move.gyro_raw,
                                          accel_stage1.specific_force(move.accel_raw), move.dt_s, U(k), U(k + 1),
                                          gyro_keys, nominal_gyro, problem.move_deviation(k)))
    return IntrinsicsGraph(graph, values, accel_keys, gyro_keys, nominal_accel, nominal_gyro, poses)


def solve_intrinsics(poses: list[StaticPose], moves: list[Move], gravity_m_s2: float,
                     spec: IntrinsicsSpec = IntrinsicsSpec(), huber_k: float | None = 3.0,
                     nominal_accel: imu.AccelIntrinsics | None = None,
                     nominal_gyro: imu.GyroIntrinsics | None = None) -> IntrinsicsEstimate:
    """Estimate accelerometer and gyro intrinsics from static poses and the moves between them.

    ``moves[k]`` joins ``poses[k]`` and ``poses[k + 1]``; pass ``moves=[]`` for accelerometer only.
    """
    check_pose_geometry(poses, spec)
    if moves and len(moves) != len(poses) - 1:
        raise ValueError(f"{len(moves)} moves for {len(poses)} poses: need one move between consecutive poses")
    problem = IntrinsicsProblem(poses, moves, gravity_m_s2,
                                channel_refs={n: float(np.mean([p.channels[n] for p in poses]))
                                              for n in set(spec.accel_channels) | set(spec.gyro_channels)})
    built = build_graph(problem, spec, huber_k, None, nominal_accel, nominal_gyro)
    values = optimize(built.graph, built.values)
    blocks = {"accel_bias": ACCEL_BIAS, "gyro_bias": GYRO_BIAS}
    for name, key, present in (("accel_M", ACCEL_M, built.accel_keys.M), ("gyro_M", GYRO_M, built.gyro_keys.M),
                               ("gyro_A", GYRO_A, built.gyro_keys.A)):
        if present is not None:
            blocks[name] = key
    cov = marginal_covariances(built.graph, values, blocks.values(), "the IMU intrinsics")
    covariance = {name: cov[key] for name, key in blocks.items()}
    _check_gyro_excitation(covariance, built.gyro_keys.M_free)

    accel, gyro = built.accel(values), built.gyro(values)
    up = np.array([values.atUnit3(U(k)).point3() for k in range(len(poses))])
    f = accel.specific_force(np.array([p.accel_mean for p in poses]))
    gyro_residual = []
    for k, move in enumerate(moves):
        w = gyro.rate(move.gyro_raw, accel.specific_force(move.accel_raw))
        delta_R = so3.integrate_rates(w, move.dt_s)
        predicted = delta_R.T @ (f[k] / np.linalg.norm(f[k]))
        gyro_residual.append(np.arccos(np.clip(predicted @ f[k + 1] / np.linalg.norm(f[k + 1]), -1, 1)))
    return IntrinsicsEstimate(accel=accel, gyro=gyro, covariance=covariance, up_S=up,
                              accel_norm_residual_m_s2=np.linalg.norm(f, axis=1) - gravity_m_s2,
                              gyro_direction_residual_rad=np.array(gyro_residual), spec=spec)


def _check_gyro_excitation(covariance: dict[str, np.ndarray], free: tuple[int, ...]) -> None:
    """A gyro scale that the moves did not excite has a huge sigma: say which rotation is missing."""
    if "gyro_M" not in covariance or not set(GYRO_DIAGONAL) <= set(free):
        return
    sigma_all = np.sqrt(np.diag(covariance["gyro_M"]))
    sigma_diag = sigma_all[[free.index(i) for i in GYRO_DIAGONAL]]
    weak = [axis for axis, s in zip("xyz", sigma_diag) if s > 0.05]
    if weak:
        raise DegenerateDataError(
            f"gyro scale about {', '.join(weak)} is not determined (sigma {sigma_diag.max():.2g}): "
            f"rotate the IMU about its {', '.join(weak)} axis between static poses")
