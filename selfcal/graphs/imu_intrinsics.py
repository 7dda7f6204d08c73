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
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from selfcal.factors import imu as fimu
from selfcal.graphs.solve import DegenerateDataError, marginal_covariances, optimize, robust
from selfcal.models import imu, so3

U = gtsam.symbol_shorthand.U  # up-direction of static pose k
ACCEL_BIAS, ACCEL_M = gtsam.symbol("a", 0), gtsam.symbol("a", 1)
GYRO_BIAS, GYRO_M, GYRO_A = gtsam.symbol("g", 0), gtsam.symbol("g", 1), gtsam.symbol("g", 2)


@dataclass
class StaticPose:
    """Mean raw outputs of one static interval and the 1-sigma of those means (per axis)."""

    accel_mean: np.ndarray
    gyro_mean: np.ndarray
    accel_sigma: np.ndarray
    gyro_sigma: np.ndarray


@dataclass
class Move:
    """Raw samples of the motion between two consecutive static poses."""

    gyro_raw: np.ndarray  # (n, 3) rad/s
    accel_raw: np.ndarray  # (n, 3) m/s^2
    dt_s: np.ndarray  # (n,) hold time of each sample
    angle_sigma_rad: float  # 1-sigma of the integrated angle from gyro white noise


@dataclass(frozen=True)
class IntrinsicsModel:
    """Which blocks are estimated (biases always are)."""

    accel_M: bool = True
    gyro_M: bool = True
    gyro_A: bool = True


@dataclass
class IntrinsicsEstimate:
    accel: imu.AccelIntrinsics
    gyro: imu.GyroIntrinsics
    covariance: dict[str, np.ndarray]  # block name -> marginal covariance
    up_S: np.ndarray  # (K, 3) estimated up-directions of the static poses
    accel_norm_residual_m_s2: np.ndarray  # (K,) |f_k| - g
    gyro_direction_residual_rad: np.ndarray  # (K-1,) angle between integrated and measured up-directions
    model: IntrinsicsModel = field(default_factory=IntrinsicsModel)

    def sigma(self, block: str) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance[block]))


MIN_POSES_FULL_ACCEL = 9  # bias (3) + upper-triangular M (6); each pose adds one net equation (|f| = g)


def check_pose_geometry(poses: list[StaticPose], model: IntrinsicsModel) -> None:
    """Refuse geometry that cannot determine the accelerometer model, saying what poses to add."""
    up = np.array([p.accel_mean / np.linalg.norm(p.accel_mean) for p in poses])
    needed = MIN_POSES_FULL_ACCEL if model.accel_M else 3
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
    if model.accel_M and np.linalg.svd(up - up.mean(axis=0), compute_uv=False)[2] / np.sqrt(len(up)) < 0.05:
        # directions on one cone (e.g. turning only about one axis): bias and scale trade off along the cone axis
        raise DegenerateDataError(
            "the static gravity directions lie on one cone (rotation about a single axis): add poses turned "
            "about another axis")


def solve_intrinsics(poses: list[StaticPose], moves: list[Move], gravity_m_s2: float,
                     model: IntrinsicsModel = IntrinsicsModel(), huber_k: float | None = 3.0,
                     nominal_accel: imu.AccelIntrinsics | None = None,
                     nominal_gyro: imu.GyroIntrinsics | None = None) -> IntrinsicsEstimate:
    """Estimate accelerometer and gyro intrinsics from static poses and the moves between them.

    ``moves[k]`` joins ``poses[k]`` and ``poses[k + 1]``; pass ``moves=[]`` for accelerometer only.
    """
    check_pose_geometry(poses, model)
    if moves and len(moves) != len(poses) - 1:
        raise ValueError(f"{len(moves)} moves for {len(poses)} poses: need one move between consecutive poses")
    nominal_accel = nominal_accel or imu.AccelIntrinsics()
    nominal_gyro = nominal_gyro or imu.GyroIntrinsics()
    accel_keys = fimu.AccelKeys(bias=ACCEL_BIAS, M=ACCEL_M if model.accel_M else None)

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    values.insert(ACCEL_BIAS, nominal_accel.bias.copy())
    if model.accel_M:
        values.insert(ACCEL_M, fimu.free_entries(nominal_accel.M, accel_keys))
    for k, pose in enumerate(poses):
        f0 = nominal_accel.specific_force(pose.accel_mean[None])[0]
        values.insert(U(k), gtsam.Unit3(f0 / np.linalg.norm(f0)))
        graph.add(fimu.static_accel_factor(robust(pose.accel_sigma, huber_k), pose.accel_mean, gravity_m_s2,
                                           U(k), accel_keys, nominal_accel))
    values = optimize(graph, values)
    accel_stage1 = fimu.accel_from_values(values, accel_keys, nominal_accel)

    gyro_keys = fimu.GyroKeys(bias=GYRO_BIAS, M=GYRO_M if model.gyro_M and moves else None,
                              A=GYRO_A if model.gyro_A else None)
    values.insert(GYRO_BIAS, np.mean([p.gyro_mean for p in poses], axis=0))
    if gyro_keys.M is not None:
        values.insert(GYRO_M, fimu.free_entries(nominal_gyro.M, gyro_keys))
    if gyro_keys.A is not None:
        values.insert(GYRO_A, nominal_gyro.A.ravel().copy())
    for k, pose in enumerate(poses):
        graph.add(fimu.static_gyro_factor(robust(pose.gyro_sigma, huber_k), pose.gyro_mean, gravity_m_s2, U(k),
                                          gyro_keys, nominal_gyro))
    for k, move in enumerate(moves):
        f_S = accel_stage1.specific_force(move.accel_raw)
        graph.add(fimu.gyro_motion_factor(robust(np.full(3, move.angle_sigma_rad), huber_k), move.gyro_raw, f_S,
                                          move.dt_s, U(k), U(k + 1), gyro_keys, nominal_gyro))
    values = optimize(graph, values)

    blocks = {"accel_bias": ACCEL_BIAS, "gyro_bias": GYRO_BIAS}
    if model.accel_M:
        blocks["accel_M"] = ACCEL_M
    if gyro_keys.M is not None:
        blocks["gyro_M"] = GYRO_M
    if gyro_keys.A is not None:
        blocks["gyro_A"] = GYRO_A
    cov = marginal_covariances(graph, values, blocks.values(), "the IMU intrinsics")
    covariance = {name: cov[key] for name, key in blocks.items()}
    _check_gyro_excitation(covariance)

    accel = fimu.accel_from_values(values, accel_keys, nominal_accel)
    gyro = fimu.gyro_from_values(values, gyro_keys, nominal_gyro)
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
                              gyro_direction_residual_rad=np.array(gyro_residual), model=model)


def _check_gyro_excitation(covariance: dict[str, np.ndarray]) -> None:
    """A gyro scale that the moves did not excite has a huge sigma: say which rotation is missing."""
    if "gyro_M" not in covariance:
        return
    sigma_diag = np.sqrt(np.diag(covariance["gyro_M"]))[[0, 4, 8]]
    weak = [axis for axis, s in zip("xyz", sigma_diag) if s > 0.05]
    if weak:
        raise DegenerateDataError(
            f"gyro scale about {', '.join(weak)} is not determined (sigma {sigma_diag.max():.2g}): "
            f"rotate the IMU about its {', '.join(weak)} axis between static poses")
