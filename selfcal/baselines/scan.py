"""Baseline: the two-stage correction of patent seed 001 (CN106091980A, Tianjin University), as written.

Step 204: with the INS poses as the initial values and the sphere centres from a sphere fit of set B, solve
the "large nonlinear system" ``min sum_m sum_i (|T_m p_i^m - O| - R)^2`` over the poses ``T_m`` of the clocks of
set B and the centres ``O`` (Levenberg-Marquardt / Gauss-Newton, [0058]): the optimal poses ``T*_m``.

Step 205-206: the error correction model ``T_m = T~_m + dX(delta_1..delta_15)`` (here
:func:`selfcal.models.scan.corrected_pose`) is compared with ``T*_m`` and the 15 terms follow by an optimal
estimator ("e.g. a Kalman filter", [0067]): a batch least-squares with the INS's prior on the terms (the
smoothing form of that Kalman filter, for constant terms), each optimal pose taken as a measurement with the
INS output's jitter as its noise.

Step 207: every clock's pose corrected with the estimated terms (the whole point set A).

The patent's stage 1 has no term tying the poses to the INS, so a pose is free in every direction the points
of its own clock cannot see (a circle on a sphere turns about the centre: 3 of 6 per clock); Levenberg-Marquardt
leaves those at the INS values, and stage 2 then reads them as measurements of "no error".  That is the
method as written, and the structural difference the joint graph removes.  Pure numpy/scipy (no GTSAM), so it
stays an independent reference.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from selfcal.models import scan as ms
from selfcal.core import so3


@dataclass
class PatentScanResult:
    theta: np.ndarray  # (15,)
    theta_cov: np.ndarray
    stage1_R: np.ndarray  # (B, 3, 3) optimal poses of the clocks of set B
    stage1_r: np.ndarray
    centers: np.ndarray  # (S, 3) stage-1 centres
    seconds: float
    stage1_rms_m: float


def stage1_optimal_poses(ins_R, ins_r, observations, imu_R_vision, imu_t_vision, centers0, radius_m,
                         max_nfev: int = 200):
    """Step 204: poses of the clocks of set B and sphere centres from the sphere constraint alone.

    Parameters
    ----------
    ins_R, ins_r : (B, 3, 3), (B, 3) INS poses of the clocks of set B (the initial values).
    observations : list of ``(b, j, vision_p)``: clock b (0..B-1) saw points ``vision_p`` (k, 3) on sphere j.
    centers0 : (S, 3) initial centres.

    Returns
    -------
    R (B, 3, 3), r (B, 3), centers (S, 3), rms (m), information
        ``information``: per sphere, ``(clock indices, (6n, 6n) matrix)``: the information its points give on
        the poses of its n clocks (Pose3 tangent ``[omega, v]``, right perturbation, unit point weight) with
        its centre marginalised (Schur complement): what stage 1 really knows, relative poses only.
    """
    B, S = len(ins_R), len(centers0)
    p_I = [np.asarray(p) @ np.asarray(imu_R_vision).T + imu_t_vision for _, _, p in observations]
    n_res = sum(len(p) for p in p_I)

    def unpack(x):
        w, v = x[:6 * B].reshape(B, 6)[:, :3], x[:6 * B].reshape(B, 6)[:, 3:]
        R = ins_R @ so3.exp(w)
        r = ins_r + np.einsum("bij,bj->bi", ins_R, v)
        return w, R, r, x[6 * B:].reshape(S, 3)

    def fun(x):
        _, R, r, O = unpack(x)
        return np.concatenate([ms.sphere_surface_residuals(R[b], r[b], p, O[j], radius_m)
                               for (b, j, _), p in zip(observations, p_I)])

    def jac(x):
        w, R, r, O = unpack(x)
        Jr = so3.right_jacobian(w)
        J = lil_matrix((n_res, 6 * B + 3 * S))
        row = 0
        for (b, j, _), p in zip(observations, p_I):
            _, d_pose, d_c, _ = ms.sphere_surface_residuals(R[b], r[b], p, O[j], radius_m, with_jacobians=True)
            k = len(p)
            # x holds (w, v) with R = R~ Exp(w), r = r~ + R~ v: d/dw = d_pose_rot J_r(w); d/dv = u^T R~
            u_W = d_pose[:, 3:] @ R[b].T
            J[row:row + k, 6 * b:6 * b + 3] = d_pose[:, :3] @ Jr[b]
            J[row:row + k, 6 * b + 3:6 * b + 6] = u_W @ ins_R[b]
            J[row:row + k, 6 * B + 3 * j:6 * B + 3 * j + 3] = d_c
            row += k
        return J.tocsr()

    x0 = np.r_[np.zeros(6 * B), np.asarray(centers0, float).ravel()]
    sol = least_squares(fun, x0, jac=jac, method="trf", tr_solver="lsmr", max_nfev=max_nfev, x_scale=1.0)
    _, R, r, O = unpack(sol.x)
    info = []
    for j in range(S):
        mine = [(b, p) for (b, jj, _), p in zip(observations, p_I) if jj == j]
        clocks = sorted({b for b, _ in mine})
        col = {b: i for i, b in enumerate(clocks)}
        n = len(clocks)
        H = np.zeros((6 * n + 3, 6 * n + 3))
        for b, p in mine:
            _, d_pose, d_c, _ = ms.sphere_surface_residuals(R[b], r[b], p, O[j], radius_m, with_jacobians=True)
            Jrow = np.zeros((len(p), 6 * n + 3))
            Jrow[:, 6 * col[b]:6 * col[b] + 6] = d_pose
            Jrow[:, 6 * n:] = d_c
            H += Jrow.T @ Jrow
        Hpp, Hpc, Hcc = H[:6 * n, :6 * n], H[:6 * n, 6 * n:], H[6 * n:, 6 * n:]
        info.append((np.array(clocks), Hpp - Hpc @ np.linalg.solve(Hcc, Hpc.T)))
    return R, r, O, float(np.sqrt(np.mean(sol.fun**2))), info


def stage2_error_terms(ins_R, ins_r, Phi, opt_R, opt_r, prior_sigmas, weights, iterations: int = 3):
    """Steps 205-206: the 15 terms that bring the corrected INS poses onto the optimal poses (prior + LSQ).

    ``Phi`` (B, 9, 15) at the clocks; ``weights``: list of ``(clock indices, (6n, 6n) information)`` of
    groups of optimal poses (their measurement noise as the Kalman filter of [0067] would take it).
    Returns (theta, covariance).
    """
    theta = np.zeros(ms.N_TERMS)
    P0 = np.diag(1.0 / np.asarray(prior_sigmas, float) ** 2)
    for _ in range(iterations):
        R, r, J = ms.corrected_pose(ins_R, ins_r, Phi, theta, with_jacobian=True)
        # residual of the optimal pose in the corrected pose's tangent: [Log(R^T R*), R^T (r* - r)] ~ J dtheta
        e = np.concatenate([so3.log(np.swapaxes(R, 1, 2) @ opt_R), np.einsum("bji,bj->bi", R, opt_r - r)], axis=1)
        N, g = P0.copy(), -P0 @ theta
        for clocks, W in weights:
            Jg, eg = J[clocks].reshape(-1, ms.N_TERMS), e[clocks].ravel()
            N += Jg.T @ W @ Jg
            g += Jg.T @ W @ eg
        theta = theta + np.linalg.solve(N, g)
    return theta, np.linalg.inv(N)


def patent_two_stage(ins_R, ins_r, Phi, observations, imu_R_vision, imu_t_vision, centers0, radius_m,
                     prior_sigmas, pose_sigmas, weighting: str = "information") -> PatentScanResult:
    """The whole two-stage procedure on the clocks of set B (``Phi`` restricted to the 15 columns).

    ``weighting``: how stage 2 weighs the optimal poses, which the patent leaves open.  ``"information"``
    (default, the stronger baseline): the information stage 1 has on the poses of each sphere's clocks (centre
    marginalised) over the residual variance, so directions the spheres cannot see carry no weight.  ``"pose_sigmas"``: every optimal pose as a
    full measurement with the INS output noise ``pose_sigmas`` (6,) (the literal reading: then the unseen
    directions, left at the INS values by stage 1, pull the terms back to zero).
    """
    start = time.perf_counter()
    R, r, O, rms, info = stage1_optimal_poses(ins_R, ins_r, observations, imu_R_vision, imu_t_vision, centers0,
                                              radius_m)
    if weighting == "information":
        weights = [(c, W / max(rms, 1e-9) ** 2) for c, W in info]
    elif weighting == "pose_sigmas":
        W = np.diag(1.0 / np.asarray(pose_sigmas, float) ** 2)
        weights = [(np.array([b]), W) for b in range(len(ins_R))]
    else:
        raise ValueError(f"unknown weighting {weighting!r}: 'information' or 'pose_sigmas'")
    theta, cov = stage2_error_terms(ins_R, ins_r, Phi, R, r, prior_sigmas, weights)
    return PatentScanResult(theta, cov, R, r, O, time.perf_counter() - start, rms)
