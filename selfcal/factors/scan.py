"""GTSAM factors of the mobile scan (patent 001): thin adapters around :mod:`selfcal.models.scan`.

Variables (``gtsam.Values`` types):
  ``Pose3``   ``world_T_imu`` at one clock of set B (the clock's points lie on a sphere)
  vectors     sphere centre O (3, m, world); the error terms in units of their prior sigma (15, and the
              extension blocks ``accel_scale``/``gyro_scale`` (3 each)); camera-to-INS clock offset dt (1, s);
              extrinsic rotation error eps (3, rad, ``R_IV,true = R_IV Exp(eps)``); sphere radius error dR (1, m)

Factors:
  :func:`sphere_surface_factor` — ``e_i = |X (R_IV Exp(eps) p_V,i + t_IV) - O| - (R + dR)``, one factor per
  (clock, sphere), batched over the clock's points on that sphere (the patent's objective, step 204).
  :func:`inertial_tie_factor` — ``e = Log((T(theta) Exp(dt xi))^-1 X)``: the clock's pose against the INS pose
  corrected by the error model (step 205), ``xi`` the body twist for a clock offset.
  :func:`registration_theta_factor` — ``e = L Log(Z^-1 T_a(theta)^-1 T_b(theta))``: two frames registered
  against each other (ICP) give their relative pose ``Z``; ``L`` the square root of its information.
"""
from __future__ import annotations

import gtsam
import numpy as np

from selfcal.models import scan as ms
from selfcal.core import so3


def _points_in_imu(values, p_V, R_IV, t_IV, extrinsic_key):
    """(p_I, R_ext, eps): the clock's points in the IMU frame through the (possibly corrected) extrinsics."""
    if extrinsic_key is None:
        return p_V @ R_IV.T + t_IV, R_IV, None
    eps = values.atVector(extrinsic_key)
    R_ext = R_IV @ so3.exp(eps)
    return p_V @ R_ext.T + t_IV, R_ext, eps


def _extrinsic_and_radius_blocks(d_pI, R_ext, p_V, eps, extrinsic_key, radius_key) -> list:
    """Jacobian blocks of the sphere residuals on the extrinsic error and the radius error (where present)."""
    blocks = []
    if extrinsic_key is not None:
        # p_I(eps + d) = R_IV Exp(eps) Exp(J_r d) p_V + t: dp_I = -R_ext [p_V]x J_r d
        dp = -R_ext @ so3.hat(p_V) @ so3.right_jacobian(eps)  # (k, 3, 3)
        blocks.append(np.einsum("ni,nij->nj", d_pI, dp))
    if radius_key is not None:
        blocks.append(-np.ones((len(d_pI), 1)))
    return blocks


def sphere_surface_factor(sigmas_m, vision_p, imu_R_vision, imu_t_vision, radius_m, pose_key, center_key,
                          extrinsic_key=None, radius_key=None) -> gtsam.CustomFactor:
    """Points of one clock on one sphere of nominal radius ``radius_m`` (m); ``sigmas_m`` (k,) radial 1-sigmas."""
    p_V = np.asarray(vision_p, dtype=float)
    R_IV, t_IV = np.asarray(imu_R_vision, float), np.asarray(imu_t_vision, float)
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas_m, dtype=float))
    keys = [k for k in (pose_key, center_key, extrinsic_key, radius_key) if k is not None]

    def error(this, values, H):
        X = values.atPose3(pose_key)
        O = values.atVector(center_key)
        p_I, R_ext, eps = _points_in_imu(values, p_V, R_IV, t_IV, extrinsic_key)
        radius = radius_m + (values.atVector(radius_key)[0] if radius_key is not None else 0.0)
        if H is None:
            return ms.sphere_surface_residuals(X.rotation().matrix(), X.translation(), p_I, O, radius)
        e, d_pose, d_center, d_pI = ms.sphere_surface_residuals(X.rotation().matrix(), X.translation(), p_I, O,
                                                                 radius, with_jacobians=True)
        blocks = [d_pose, d_center]
        blocks += _extrinsic_and_radius_blocks(d_pI, R_ext, p_V, eps, extrinsic_key, radius_key)
        for i, J in enumerate(blocks):
            H[i] = J
        return e

    return gtsam.CustomFactor(noise, keys, error)


def inertial_tie_factor(sigmas, ins_R, ins_r, Phi_k, pose_key, theta_blocks, time_offset_key=None,
                        twist=None) -> gtsam.CustomFactor:
    """A clock's pose against the INS pose corrected by the error model.

    Parameters
    ----------
    sigmas : (6,) 1-sigma of the INS output beyond the error model (rad x3, m x3: jitter).
    ins_R, ins_r : the INS pose interpolated at the clock's stamp.
    Phi_k : (9, 21) sensitivity at the clock (:class:`selfcal.models.scan.ErrorSensitivity`).
    pose_key : key of the clock's Pose3.
    theta_blocks : list of ``(key, columns, scale)``: a vector variable holding ``theta[columns] / scale``
        (error terms in units of their prior sigma keep the normal equations well scaled).
    time_offset_key, twist : clock offset variable (s) and the body twist ``[omega, v]`` (6,) at the clock.
    """
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=float))
    cols = np.concatenate([c for _, c, _ in theta_blocks])
    scale = np.concatenate([np.broadcast_to(s, len(c)) for _, c, s in theta_blocks])
    Phi = np.asarray(Phi_k, float)[:, cols] * scale[None, :]
    widths = [len(c) for _, c, _ in theta_blocks]
    keys = [pose_key] + [k for k, _, _ in theta_blocks] + ([time_offset_key] if time_offset_key is not None else [])
    xi = np.asarray(twist, float) if twist is not None else np.zeros(6)

    def error(this, values, H):
        eta = np.concatenate([values.atVector(k) for k, _, _ in theta_blocks])
        R, r, J = ms.corrected_pose(ins_R, ins_r, Phi, eta, with_jacobian=True)
        T = gtsam.Pose3(gtsam.Rot3(R), r)
        dt = values.atVector(time_offset_key)[0] if time_offset_key is not None else 0.0
        H_exp = np.zeros((6, 6), order="F")
        D = gtsam.Pose3.Expmap(dt * xi, H_exp)
        H_c1, H_c2 = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
        A = T.compose(D, H_c1, H_c2)
        X = values.atPose3(pose_key)
        H_b1, H_b2 = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
        B = A.between(X, H_b1, H_b2)
        H_log = np.zeros((6, 6), order="F")
        e = gtsam.Pose3.Logmap(B, H_log)
        if H is not None:
            de_dA = H_log @ H_b1
            H[0] = H_log @ H_b2
            dtheta = de_dA @ H_c1 @ J
            start = 0
            for i, w in enumerate(widths):
                H[1 + i] = dtheta[:, start:start + w]
                start += w
            if time_offset_key is not None:
                H[len(keys) - 1] = (de_dA @ H_c2 @ H_exp @ xi)[:, None]
        return e

    return gtsam.CustomFactor(noise, keys, error)


def sphere_theta_factor(sigmas_m, vision_p, imu_R_vision, imu_t_vision, radius_m, ins_R, ins_r, Phi_k, center_key,
                        theta_blocks, time_offset_key=None, twist=None, extrinsic_key=None,
                        radius_key=None, radius_columns=()) -> gtsam.CustomFactor:
    """The sphere constraint with the clock's pose *replaced* by the corrected INS pose (no per-clock pose).

    ``e_i = |A (R_IV Exp(eps) p_V,i + t_IV) - O| - (R + dR)`` with ``A = T(theta) Exp(dt xi)``: the graph of
    :func:`sphere_surface_factor` + :func:`inertial_tie_factor` with the tie made rigid (INS jitter neglected
    against the point noise, or folded into ``sigmas_m`` given as a (k, k) covariance: the jitter's common
    effect on the clock's points, see :func:`selfcal.graphs.scan.build_collapsed`).  Few variables, so the
    audit's score tests stay cheap.  ``radius_columns`` ``(key, phi (k,))``: the radius varying over the points as
    ``k phi`` (``k`` a Vector1, m per unit of a driver's basis function: the audit's generic terms).
    """
    p_V = np.asarray(vision_p, dtype=float)
    R_IV, t_IV = np.asarray(imu_R_vision, float), np.asarray(imu_t_vision, float)
    sig = np.asarray(sigmas_m, dtype=float)
    noise = (gtsam.noiseModel.Gaussian.Covariance(sig) if sig.ndim == 2
             else gtsam.noiseModel.Diagonal.Sigmas(sig))
    cols = np.concatenate([c for _, c, _ in theta_blocks])
    scale = np.concatenate([np.broadcast_to(s, len(c)) for _, c, s in theta_blocks])
    Phi = np.asarray(Phi_k, float)[:, cols] * scale[None, :]
    widths = [len(c) for _, c, _ in theta_blocks]
    xi = np.asarray(twist, float) if twist is not None else np.zeros(6)
    keys = ([center_key] + [k for k, _, _ in theta_blocks]
            + [k for k in (time_offset_key, extrinsic_key, radius_key) if k is not None])
    terms = [(key, np.asarray(phi, dtype=float)) for key, phi in radius_columns]
    keys += [key for key, _ in terms]

    def error(this, values, H):
        eta = np.concatenate([values.atVector(k) for k, _, _ in theta_blocks])
        R, r, J = ms.corrected_pose(ins_R, ins_r, Phi, eta, with_jacobian=True)
        dt = values.atVector(time_offset_key)[0] if time_offset_key is not None else 0.0
        H_exp = np.zeros((6, 6), order="F")
        D = gtsam.Pose3.Expmap(dt * xi, H_exp)
        H_c1, H_c2 = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
        A = gtsam.Pose3(gtsam.Rot3(R), r).compose(D, H_c1, H_c2)
        p_I, R_ext, eps = _points_in_imu(values, p_V, R_IV, t_IV, extrinsic_key)
        radius = radius_m + (values.atVector(radius_key)[0] if radius_key is not None else 0.0)
        radius = radius + sum((phi * values.atVector(key)[0] for key, phi in terms), np.zeros(len(p_V)))
        O = values.atVector(center_key)
        e, d_pose, d_center, d_pI = ms.sphere_surface_residuals(A.rotation().matrix(), A.translation(), p_I, O,
                                                                 radius, with_jacobians=True)
        if H is not None:
            blocks = [d_center]
            dtheta = d_pose @ H_c1 @ J
            start = 0
            for w in widths:
                blocks.append(dtheta[:, start:start + w])
                start += w
            if time_offset_key is not None:
                blocks.append((d_pose @ H_c2 @ H_exp @ xi)[:, None])
            blocks += _extrinsic_and_radius_blocks(d_pI, R_ext, p_V, eps, extrinsic_key, radius_key)
            blocks += [-phi[:, None] for _, phi in terms]
            for i, Jb in enumerate(blocks):
                H[i] = Jb
        return e

    return gtsam.CustomFactor(noise, keys, error)


def registration_theta_factor(sqrt_information, jitter_covariance, measured_a_T_b, ins_a, ins_b, Phi_a, Phi_b,
                              theta_blocks) -> gtsam.CustomFactor:
    """Two frames registered against each other: their relative pose through the corrected INS poses.

    ``e = L Log(Z^-1 T_a(theta)^-1 T_b(theta))`` with ``T(theta)`` :func:`selfcal.models.scan.corrected_pose` at
    the anchor clocks a and b, ``Z`` the registered relative pose and ``L`` (r, 6) the square root of its
    information on the directions the registration sees (:func:`selfcal.models.scan.observable_square_root`).
    The residual's covariance is ``I + L C_j L^T``: the registration's own (unit, after ``L``) plus the INS
    output jitter of both anchors (``C_j``, :func:`selfcal.models.scan.relative_jitter_covariance`), which the
    error terms do not model.

    Parameters
    ----------
    sqrt_information : (r, 6); jitter_covariance : (6, 6); measured_a_T_b : (4, 4).
    ins_a, ins_b : ``(R, r)`` INS poses at the anchor clocks; Phi_a, Phi_b : (9, 21) sensitivities there.
    theta_blocks : as for :func:`inertial_tie_factor`.
    """
    L = np.asarray(sqrt_information, float)
    noise = gtsam.noiseModel.Gaussian.Covariance(np.eye(len(L)) + L @ np.asarray(jitter_covariance, float) @ L.T)
    Z = gtsam.Pose3(np.asarray(measured_a_T_b, float))
    cols = np.concatenate([c for _, c, _ in theta_blocks])
    scale = np.concatenate([np.broadcast_to(s, len(c)) for _, c, s in theta_blocks])
    Phis = [np.asarray(P, float)[:, cols] * scale[None, :] for P in (Phi_a, Phi_b)]
    widths = [len(c) for _, c, _ in theta_blocks]
    keys = [k for k, _, _ in theta_blocks]

    def error(this, values, H):
        eta = np.concatenate([values.atVector(k) for k in keys])
        poses, jacobians = [], []
        for (R_ins, r_ins), Phi in zip((ins_a, ins_b), Phis):
            R, r, J = ms.corrected_pose(R_ins, r_ins, Phi, eta, with_jacobian=True)
            poses.append(gtsam.Pose3(gtsam.Rot3(R), r))
            jacobians.append(J)
        H_a, H_b = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
        a_T_b = poses[0].between(poses[1], H_a, H_b)
        H_z = np.zeros((6, 6), order="F")
        D = Z.between(a_T_b, np.zeros((6, 6), order="F"), H_z)
        H_log = np.zeros((6, 6), order="F")
        e = gtsam.Pose3.Logmap(D, H_log)
        if H is not None:
            dtheta = L @ H_log @ H_z @ (H_a @ jacobians[0] + H_b @ jacobians[1])
            start = 0
            for i, w in enumerate(widths):
                H[i] = dtheta[:, start:start + w]
                start += w
        return L @ e

    return gtsam.CustomFactor(noise, keys, error)
