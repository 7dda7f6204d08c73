"""Inertial error model of the mobile stereo scanner (patent 001): 15 error terms, their effect on the poses.

Frames and conventions
----------------------
``W`` world, local level, z up (at the start of the scan x points along the track, y left); ``I`` the IMU
(body) frame; ``V`` the vision frame (left line camera).  ``world_T_imu = (R, r)`` maps ``p_I`` to
``R p_I + r``; ``imu_T_vision`` is the calibrated extrinsic of the patent ([0045], V-to-I rotation and
translation).  Poses are perturbed on the right as in GTSAM, tangent ``xi = [omega, v]`` (rotation first):
``T Exp(xi)``.

The INS solution ``(R~, v~, r~)`` carries errors defined by::

    R~ = Exp(psi) R        v~ = v + dv        r~ = r + dr            (psi: attitude error, world frame, rad)

The 15 error terms (patent [0060]-[0062]: "15 main errors ... delta_1 pitch error, delta_2 roll error ...";
the rest were lost in extraction and are the standard 15-state strapdown error vector, Titterton & Weston,
*Strapdown Inertial Navigation Technology*, ch. 12; Groves, *Principles of GNSS, Inertial and Multisensor
Integrated Navigation*, ch. 14), at the start of the scan:

=====  ===================  ==========  ==========================================================
index  name                 unit        meaning
=====  ===================  ==========  ==========================================================
0      ``pitch``            rad         initial attitude error about world y (psi_y)
1      ``roll``             rad         initial attitude error about world x (psi_x)
2      ``heading``          rad         initial attitude error about world z (psi_z)
3-5    ``vel_x..z``         m s^-1      initial velocity error dv (world)
6-8    ``pos_x..z``         m           initial position error dr (world)
9-11   ``gyro_bias_x..z``   rad s^-1    gyro bias b_g (body), constant over the scan
12-14  ``accel_bias_x..z``  m s^-2      accelerometer bias b_a (body), constant over the scan
=====  ===================  ==========  ==========================================================

Two more blocks extend the model for the audit (not part of the patent's 15): ``accel_scale`` (3,
dimensionless, ``f~ = (I + diag(s_a)) f + b_a``) and ``gyro_scale`` (3, ``w~ = (I + diag(s_g)) w + b_g``).

Error dynamics (first order, scan durations of minutes: no Earth rate, no Schuler loop, no gravity error),
driven by the INS's own attitude ``R~_k`` and specific force ``f~_k`` (body) at its samples ``t_k``::

    psi'  =  R (b_g + diag(w) s_g)
    dv'   = -[R f]x psi + R (b_a + diag(f) s_a)
    dr'   =  dv

discretised exactly as the strapdown integration it describes (explicit Euler, the INS's own step), so the
model reproduces a simulated strapdown's error to first order in the errors.  The state ``z = [psi, dv, dr]``
then obeys ``z(t_k) = Phi(t_k) theta`` with ``theta`` the 15 terms (plus the extension blocks): one linear
sensitivity matrix per INS sample, computed once for a scan.

Correction (patent [0069]: ``X_n = X~_n + dX(delta_1..delta_15)``): the corrected pose is
``R = Exp(-psi) R~``, ``r = r~ - dr``, for every clock of the scan (the whole point set A).

References
----------
CN106091980A (Tianjin University), "Accuracy control method for autonomous mobile 3D shape measurement"
(seed 001), steps 204-207.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfcal.core import so3

GRAVITY_W_M_S2 = np.array([0.0, 0.0, -9.80665])  # gravity vector in the world frame (z up)

ERROR_TERMS = ("pitch", "roll", "heading", "vel_x", "vel_y", "vel_z", "pos_x", "pos_y", "pos_z",
               "gyro_bias_x", "gyro_bias_y", "gyro_bias_z", "accel_bias_x", "accel_bias_y", "accel_bias_z")
ERROR_UNITS = ("rad",) * 3 + ("m s^-1",) * 3 + ("m",) * 3 + ("rad s^-1",) * 3 + ("m s^-2",) * 3
N_TERMS = 15
#: extension blocks (column ranges of the full sensitivity after the 15 terms)
EXTENSIONS = {"accel_scale": slice(15, 18), "gyro_scale": slice(18, 21)}
N_FULL = 21

#: prior 1-sigma of the 15 error terms (a tactical-grade INS after a static alignment): tilt 50 urad,
#: heading 1 mrad, velocity 5 mm/s, position 0 (the world frame is the INS's start), gyro 2 urad/s
#: (0.4 deg/h), accelerometer 100 ug.
DEFAULT_PRIOR_SIGMAS = np.array([5e-5, 5e-5, 1e-3, 5e-3, 5e-3, 5e-3, 1e-4, 1e-4, 1e-4,
                                 2e-6, 2e-6, 2e-6, 1e-3, 1e-3, 1e-3])

# psi = _ATT @ theta[0:3]: theta holds (pitch, roll, heading) = (psi_y, psi_x, psi_z) in the patent's order
_ATT = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class ErrorSensitivity:
    """``z(t_k) = Phi[k] theta``: the INS error state at each INS sample, linear in the error terms.

    Attributes
    ----------
    t_s : (K,) INS sample times, s.
    Phi : (K, 9, 21) rows ``[psi (rad), dv (m s^-1), dr (m)]``, columns the 15 terms then the extensions.
    """

    t_s: np.ndarray
    Phi: np.ndarray

    def at(self, t_s) -> np.ndarray:
        """Phi at arbitrary times (M, 9, 21), linear interpolation between INS samples (clamped at the ends)."""
        t = np.asarray(t_s, dtype=float)
        flat = self.Phi.reshape(len(self.t_s), -1)
        out = np.empty((t.size, flat.shape[1]))
        for j in range(flat.shape[1]):
            out[:, j] = np.interp(t.ravel(), self.t_s, flat[:, j])
        return out.reshape(t.shape + self.Phi.shape[1:])


def error_sensitivity(t_s, world_R_imu, accel_m_s2, gyro_rad_s) -> ErrorSensitivity:
    """Integrate the error dynamics (module docstring) along the INS solution.

    Parameters
    ----------
    t_s : (K,) INS sample times, s (strictly increasing).
    world_R_imu : (K, 3, 3) INS attitude.
    accel_m_s2 : (K, 3) specific force measured in the body frame (the INS's accelerometer), m s^-2.
    gyro_rad_s : (K, 3) body angular rate (the INS's gyro), rad s^-1.

    Returns
    -------
    ErrorSensitivity
    """
    t = np.asarray(t_s, dtype=float)
    R = np.asarray(world_R_imu, dtype=float)
    f = np.asarray(accel_m_s2, dtype=float)
    w = np.asarray(gyro_rad_s, dtype=float)
    K = len(t)
    f_w = np.einsum("kij,kj->ki", R, f)
    # d z_k / d theta (9 x 21), propagated sample by sample: z_{k+1} = z_k + dt (F_k z_k + G_k p)
    Phi = np.zeros((K, 9, N_FULL))
    z = np.zeros((9, N_FULL))
    z[0:3, 0:3] = _ATT
    z[3:6, 3:6] = np.eye(3)
    z[6:9, 6:9] = np.eye(3)
    Phi[0] = z
    dt = np.diff(t)
    neg_f_hat = -so3.hat(f_w)
    for k in range(K - 1):
        h = dt[k]
        psi, dv = z[0:3], z[3:6]
        new = z.copy()
        new[0:3] += h * _param_rate(R[k], w[k], gyro=True)
        new[3:6] += h * (neg_f_hat[k] @ psi + _param_rate(R[k], f[k], gyro=False))
        new[6:9] += h * dv
        z = new
        Phi[k + 1] = z
    return ErrorSensitivity(t, Phi)


def _param_rate(R_k, x_k, gyro: bool) -> np.ndarray:
    """d(psi')/d theta (gyro) or the R (b_a + diag(f) s_a) part of d(dv')/d theta (accelerometer): (3, 21)."""
    out = np.zeros((3, N_FULL))
    if gyro:
        out[:, 9:12] = R_k
        out[:, EXTENSIONS["gyro_scale"]] = R_k * x_k[None, :]
    else:
        out[:, 12:15] = R_k
        out[:, EXTENSIONS["accel_scale"]] = R_k * x_k[None, :]
    return out


def columns(extensions=()) -> np.ndarray:
    """Indices into the 21 columns of :class:`ErrorSensitivity` for the 15 terms plus the named extensions."""
    cols = list(range(N_TERMS))
    for name in extensions:
        s = EXTENSIONS[name]
        cols += list(range(s.start, s.stop))
    return np.array(cols, dtype=int)


def pose_error(Phi_k, theta) -> tuple[np.ndarray, np.ndarray]:
    """Attitude error psi (..., 3) rad and position error dr (..., 3) m: ``Phi_k[..., rows, :] theta``.

    ``Phi_k`` (..., 9, n) with n = len(theta) (already restricted to the estimated columns).
    """
    z = np.asarray(Phi_k) @ np.asarray(theta, dtype=float)
    return z[..., 0:3], z[..., 6:9]


def corrected_pose(ins_R, ins_r, Phi_k, theta, with_jacobian: bool = False):
    """The corrected pose ``R = Exp(-psi) R~``, ``r = r~ - dr`` (patent [0069]); batched over leading axes.

    Parameters
    ----------
    ins_R : (..., 3, 3), ins_r : (..., 3)  the INS pose world_T_imu at the clock.
    Phi_k : (..., 9, n)  sensitivity at the clock, restricted to the estimated columns.
    theta : (n,) error terms.
    with_jacobian : also return ``J`` (..., 6, n): ``T(theta + d) = T(theta) Exp(J d)`` (GTSAM tangent
        ``[omega, v]``, right perturbation).

    Returns
    -------
    R (..., 3, 3), r (..., 3)[, J]
    """
    psi, dr = pose_error(Phi_k, theta)
    E = so3.exp(np.reshape(-psi, (-1, 3))).reshape(np.shape(psi)[:-1] + (3, 3))
    R = E @ ins_R
    r = np.asarray(ins_r) - dr
    if not with_jacobian:
        return R, r
    # Exp(-psi - dpsi) = Exp(-psi) Exp(-J_r(-psi) dpsi), so R(theta + d) = R Exp(-R~^T J_r(-psi) dpsi);
    # r(theta + d) = r - ddr = r + R (R^T (-ddr)): tangent v = -R^T ddr
    Jr = so3.right_jacobian(np.reshape(-psi, (-1, 3))).reshape(np.shape(psi)[:-1] + (3, 3))
    ins_R_T = np.swapaxes(np.asarray(ins_R), -1, -2)
    J_rot = -ins_R_T @ Jr @ np.asarray(Phi_k)[..., 0:3, :]
    J_pos = -np.swapaxes(R, -1, -2) @ np.asarray(Phi_k)[..., 6:9, :]
    return R, r, np.concatenate([J_rot, J_pos], axis=-2)


def erroneous_pose(R, r, Phi_k, theta) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`corrected_pose`: the INS pose a true pose becomes (``R~ = Exp(psi) R``, ``r~ = r + dr``)."""
    psi, dr = pose_error(Phi_k, theta)
    E = so3.exp(np.reshape(psi, (-1, 3))).reshape(np.shape(psi)[:-1] + (3, 3))
    return E @ R, np.asarray(r) + dr


def strapdown(R0, v0, r0, gyro_rad_s, accel_m_s2, t_s):
    """Explicit-Euler strapdown (local level, no Earth rate): ``R+ = R Exp(w h)``, ``v+ = v + (R f + g) h``,
    ``r+ = r + v h`` over the sample steps ``h`` of ``t_s``; returns R (K, 3, 3), v (K, 3), r (K, 3)."""
    gyro, accel = np.asarray(gyro_rad_s, float), np.asarray(accel_m_s2, float)
    h = np.diff(np.asarray(t_s, float))
    K = len(gyro)
    R, v, r = np.empty((K, 3, 3)), np.empty((K, 3)), np.empty((K, 3))
    R[0], v[0], r[0] = R0, v0, r0
    steps = so3.exp(gyro[:-1] * h[:, None])
    for k in range(K - 1):
        R[k + 1] = R[k] @ steps[k]
        v[k + 1] = v[k] + (R[k] @ accel[k] + GRAVITY_W_M_S2) * h[k]
        r[k + 1] = r[k] + v[k] * h[k]
    return R, v, r


def remechanized(t_s, ins_R, ins_v, ins_r, gyro_rad_s, accel_m_s2, theta):
    """The INS solution with the error terms ``theta`` (15) removed *through the mechanisation* (exact, not linear).

    The strapdown is run twice, from the INS's first state with its raw IMU (A) and from that state corrected by
    the initial errors with the biases removed from the IMU (B); the INS's own output is then moved by B - A
    (attitude ``R B_R A_R^T`` applied in the world frame).  Working on the difference keeps whatever the INS's own
    mechanisation does beyond this simple one.  Returns R, v, r at the INS samples.
    """
    th = np.asarray(theta, float)
    psi0 = _ATT @ th[0:3]
    R0, v0, r0 = ins_R[0], ins_v[0], ins_r[0]
    A_R, A_v, A_r = strapdown(R0, v0, r0, gyro_rad_s, accel_m_s2, t_s)
    B_R, B_v, B_r = strapdown(so3.exp(-psi0) @ R0, v0 - th[3:6], r0 - th[6:9], np.asarray(gyro_rad_s) - th[9:12],
                              np.asarray(accel_m_s2) - th[12:15], t_s)
    D = B_R @ np.swapaxes(A_R, 1, 2)
    return D @ ins_R, ins_v + B_v - A_v, ins_r + B_r - A_r


def world_points(world_R_imu, world_t_imu, imu_R_vision, imu_t_vision, vision_p) -> np.ndarray:
    """Points of one clock in the world: ``p_W = R (R_IV p_V + t_IV) + r``; vision_p (N, 3) -> (N, 3)."""
    p_I = np.asarray(vision_p) @ np.asarray(imu_R_vision).T + imu_t_vision
    return p_I @ np.asarray(world_R_imu).T + world_t_imu


def sphere_surface_residuals(world_R_imu, world_t_imu, imu_p, center_W, radius_m, with_jacobians: bool = False):
    """The patent's sphere constraint for the points of one clock: ``e_i = |R p_I,i + r - O| - R_s`` (m).

    Parameters
    ----------
    world_R_imu, world_t_imu : pose of the IMU at the clock.
    imu_p : (N, 3) the clock's points on the sphere, IMU frame (``R_IV p_V + t_IV``), m.
    center_W : (3,) sphere centre O, world, m.
    radius_m : sphere radius, m.
    with_jacobians : also return ``de/dxi`` (N, 6) for the pose (right perturbation ``[omega, v]``),
        ``de/dO`` (N, 3) and ``de/dp_I`` (N, 3).

    Notes
    -----
    With ``u`` the unit vector from O to the world point and ``u_I = R^T u``, ``d p_W = R (-[p_I]x omega + v)``
    gives ``de/domega = (p_I x u_I)^T`` and ``de/dv = u_I^T``.
    """
    p_I = np.asarray(imu_p, dtype=float)
    p_W = p_I @ np.asarray(world_R_imu).T + world_t_imu
    d = p_W - center_W
    dist = np.linalg.norm(d, axis=1)
    e = dist - radius_m
    if not with_jacobians:
        return e
    u = d / np.maximum(dist, np.finfo(float).tiny)[:, None]
    u_I = u @ np.asarray(world_R_imu)  # R^T u, row-wise
    d_pose = np.concatenate([np.cross(p_I, u_I), u_I], axis=1)
    return e, d_pose, -u, u_I


def interpolate_poses(t_query_s, t_s, world_R_imu, world_t_imu) -> tuple[np.ndarray, np.ndarray]:
    """Poses at arbitrary times: positions linear, attitudes by slerp (scipy), clamped to the INS span."""
    from scipy.spatial.transform import Rotation, Slerp
    t = np.clip(np.asarray(t_query_s, dtype=float), t_s[0], t_s[-1])
    R = Slerp(t_s, Rotation.from_matrix(world_R_imu))(t).as_matrix()
    r = np.column_stack([np.interp(t, t_s, world_t_imu[:, j]) for j in range(3)])
    return R, r


def body_twist(t_query_s, t_s, world_t_imu, velocity_W, world_R_imu, gyro_rad_s) -> np.ndarray:
    """Body twist ``[omega_I, v_I]`` (M, 6) at clock times: the pose's rate, ``T(t + dt) ~ T(t) Exp(dt xi)``.

    Used for a camera-to-INS clock offset: a point stamped ``t`` on the camera clock was taken at ``t + dt``.
    """
    R, _ = interpolate_poses(t_query_s, t_s, world_R_imu, world_t_imu)
    w = np.column_stack([np.interp(t_query_s, t_s, gyro_rad_s[:, j]) for j in range(3)])
    v_W = np.column_stack([np.interp(t_query_s, t_s, velocity_W[:, j]) for j in range(3)])
    v_I = np.einsum("kji,kj->ki", R, v_W)
    return np.concatenate([w, v_I], axis=1)


def stereo_point_covariance(points_V, cameras, pixel_sigma: float) -> np.ndarray:
    """First-order covariance (N, 3, 3) of points triangulated by two line cameras sharing the scan plane.

    Each camera measures one angle in the plane through its pixel ``u``; a pixel error ``du`` turns its ray by
    ``du / (du/dalpha)``, which slides the intersection along the *other* ray by ``r dalpha / sin(gamma)``
    (``r``: range from the turning camera, ``gamma``: angle between the rays).  ``du/dalpha`` is taken through
    OpenCV's projection (distortion included) by a central difference.

    Parameters
    ----------
    points_V : (N, 3) points in the vision frame (scan plane ``y_V = 0``).
    cameras : two objects with ``K``, ``dist``, ``vision_R_cam``, ``vision_t_cam`` (left, right).
    pixel_sigma : 1-sigma of one matched pixel coordinate along the line, px.
    """
    import cv2
    p = np.asarray(points_V, dtype=float)
    centers = [np.asarray(c.vision_t_cam, float) for c in cameras]
    rays = [p - c for c in centers]
    ranges = [np.linalg.norm(d, axis=1) for d in rays]
    units = [d / r[:, None] for d, r in zip(rays, ranges)]
    sin_gamma = np.linalg.norm(np.cross(units[0], units[1]), axis=1)
    cov = np.zeros((len(p), 3, 3))
    h = 1e-5  # rad
    for i, cam in enumerate(cameras):
        R_vc = np.asarray(cam.vision_R_cam, float)
        rvec, _ = cv2.Rodrigues(R_vc.T)
        tvec = -R_vc.T @ centers[i]
        u_pm = []
        for s in (h, -h):  # rotate the point about the camera centre, about the plane normal (y_V)
            q = centers[i] + rays[i] @ so3.exp(np.array([0.0, s, 0.0])).T
            uv, _ = cv2.projectPoints(q.reshape(-1, 1, 3), rvec, tvec, cam.K, cam.dist)
            u_pm.append(uv.reshape(-1, 2)[:, 0])
        du_dalpha = np.abs(u_pm[0] - u_pm[1]) / (2 * h)
        slide = ranges[i] * pixel_sigma / du_dalpha / np.maximum(sin_gamma, 1e-9)
        other = units[1 - i]
        cov += slide[:, None, None] ** 2 * np.einsum("ni,nj->nij", other, other)
    return cov


def radial_sigmas(points_V, imu_R_vision, world_R_imu, center_W, world_p, covariance_V) -> np.ndarray:
    """1-sigma (N,) of the sphere residual of each point: ``sqrt(u_V^T C_V u_V)`` with ``u`` the radial direction."""
    u = np.asarray(world_p) - center_W
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u_V = u @ np.asarray(world_R_imu) @ np.asarray(imu_R_vision)
    return np.sqrt(np.einsum("ni,nij,nj->n", u_V, covariance_V, u_V))


# --------------------------------------------------------------------------------------- predicted accuracy

def corrected_pose_covariance(pose_jacobian, terms_cov, jitter_sigmas) -> np.ndarray:
    """Covariance (..., 6, 6) of the corrected pose (tangent ``[omega, v]``, right perturbation) at clocks.

    ``C = J Sigma J^T + diag(jitter^2)``: the error terms' posterior ``Sigma`` (n, n) through the correction's
    Jacobian ``J`` (..., 6, n) (:func:`corrected_pose`), plus the INS's white output jitter, which the terms do
    not model and every clock keeps.
    """
    J = np.asarray(pose_jacobian, float)
    return J @ np.asarray(terms_cov, float) @ np.swapaxes(J, -1, -2) + np.diag(np.asarray(jitter_sigmas) ** 2)


def rigid_gauge(velocity0_W) -> np.ndarray:
    """The directions (15, 4) of the error terms that move the whole corrected scan rigidly: the initial
    position (3) and a heading turn about the start, ``psi_z = 1`` with the velocity error ``z x v_0`` (then
    ``dv(t) = psi_z z x v(t)`` and ``dr(t) = psi_z z x (r(t) - r_0)`` under the error dynamics: gravity is along
    z, so a turn about z leaves the specific force consistent).  No sphere of unknown position sees them."""
    G = np.zeros((N_TERMS, 4))
    G[6:9, 0:3] = np.eye(3)
    G[2, 3] = 1.0
    G[3:6, 3] = np.cross([0.0, 0.0, 1.0], np.asarray(velocity0_W, float))
    return G


def shape_covariance(terms_cov, gauge) -> np.ndarray:
    """Covariance of the error terms with their rigid part (:func:`rigid_gauge`) taken out:
    ``Sigma - G (G^T Sigma^-1 G)^-1 G^T``, the covariance of ``P dtheta`` where ``P`` removes the rigid motion
    that best (Mahalanobis) explains ``dtheta``: the scan's error *as a shape*, wherever the INS put it."""
    S = np.asarray(terms_cov, float)
    G = np.asarray(gauge, float)
    SiG = np.linalg.solve(S, G)
    out = S - G @ np.linalg.solve(G.T @ SiG, G.T)
    return 0.5 * (out + out.T)


def largest_eigenvalue_sym3(C) -> np.ndarray:
    """Largest eigenvalue (...,) of symmetric 3x3 matrices, closed form (trigonometric solution of the
    characteristic cubic; Smith, Comm. ACM 4(4) 168, 1961): elementwise, no LAPACK call per matrix."""
    C = np.asarray(C, float)
    a, b, c = C[..., 0, 0], C[..., 1, 1], C[..., 2, 2]
    d, e, f = C[..., 0, 1], C[..., 1, 2], C[..., 0, 2]
    q = (a + b + c) / 3.0
    p1 = d * d + e * e + f * f
    p2 = (a - q) ** 2 + (b - q) ** 2 + (c - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    safe = np.where(p > 0, p, 1.0)
    # det((C - q I) / p) / 2 = cos(3 phi)
    ba, bb, bc = (a - q) / safe, (b - q) / safe, (c - q) / safe
    bd, be, bf = d / safe, e / safe, f / safe
    r = 0.5 * (ba * (bb * bc - be * be) - bd * (bd * bc - be * bf) + bf * (bd * be - bb * bf))
    phi = np.arccos(np.clip(r, -1.0, 1.0)) / 3.0
    return np.where(p > 0, q + 2.0 * p * np.cos(phi), q)


def point_error_sigmas(world_R_imu, world_t_imu, pose_cov, points_W, clock_of_point) -> np.ndarray:
    """Predicted 1-sigma (N,) of each corrected point along its worst direction, m.

    A pose error ``[omega, v]`` (body, right perturbation) moves a point ``p_W = R p_I + r`` by
    ``dp = R (omega x p_I + v) = -[a]x omega_W + v_W`` with the lever ``a = p_W - r``.  With the pose
    covariance in the world frame ``[[W, X], [X^T, V]]`` (omega first) the point's covariance is
    ``C(a) = V + [a]x X^T... `` written as a quadratic polynomial in ``a``::

        C(a) = V + sum_m a_m (X^T E_m - E_m X) - sum_{m,n} a_m a_n E_m W E_n        (E_m = [e_m]x)

    whose ten coefficient matrices are formed once per clock; each point then costs one small gather and a
    few multiply-adds (10 M points: seconds, where a per-point 3x6 product took tens).  The sigma is the square
    root of the largest eigenvalue of ``C(a)``: any one-dimensional error of the point (a deviation along a
    surface normal, a coordinate) has a 1-sigma of at most this.

    Parameters
    ----------
    world_R_imu, world_t_imu : (M, 3, 3), (M, 3) corrected clock poses.
    pose_cov : (M, 6, 6) their covariance (:func:`corrected_pose_covariance`).
    points_W : (N, 3) corrected points; clock_of_point : (N,) the clock of each point.
    """
    R = np.asarray(world_R_imu, float)
    C = np.asarray(pose_cov, float)
    W = R @ C[:, 0:3, 0:3] @ np.swapaxes(R, 1, 2)
    X = R @ C[:, 0:3, 3:6] @ np.swapaxes(R, 1, 2)
    V = R @ C[:, 3:6, 3:6] @ np.swapaxes(R, 1, 2)
    E = so3.hat(np.eye(3))  # E[m] = [e_m]x
    XT = np.swapaxes(X, 1, 2)
    coef = [V]
    coef += [XT @ E[m] - E[m] @ X for m in range(3)]
    coef += [-(E[m] @ W @ E[m]) for m in range(3)]
    coef += [-(E[m] @ W @ E[n] + E[n] @ W @ E[m]) for m, n in ((0, 1), (0, 2), (1, 2))]
    upper = ([0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2])  # (xx, yy, zz, xy, xz, yz)
    coef = np.stack([c[:, upper[0], upper[1]] for c in coef], axis=1)  # (M, 10, 6)
    P = np.asarray(points_W, float)
    t = np.asarray(world_t_imu, float)
    clock = np.asarray(clock_of_point)
    order = None if np.all(np.diff(clock) >= 0) else np.argsort(clock, kind="stable")
    if order is not None:
        P, clock = P[order], clock[order]
    bounds = np.searchsorted(clock, np.arange(len(R) + 1))
    out = np.empty(len(P))
    for m in np.flatnonzero(np.diff(bounds)):  # one (n_m, 10) @ (10, 6) product per clock: no per-point gather
        seg = slice(bounds[m], bounds[m + 1])
        a = P[seg] - t[m]
        mono = np.column_stack([np.ones(len(a)), a, a * a, a[:, 0] * a[:, 1], a[:, 0] * a[:, 2], a[:, 1] * a[:, 2]])
        e = mono @ coef[m]
        full = np.stack([e[:, [0, 3, 4]], e[:, [3, 1, 5]], e[:, [4, 5, 2]]], axis=1)
        out[seg] = np.sqrt(np.maximum(largest_eigenvalue_sym3(full), 0.0))
    if order is not None:
        out[order] = out.copy()
    return out


def distance_sigmas(centers_W, centers_cov, pairs) -> tuple[np.ndarray, np.ndarray]:
    """Distances between sphere centres and their 1-sigma: ``d = |c_i - c_j|``, ``var d = g^T (C_ii + C_jj -
    C_ij - C_ji) g`` with ``g`` the unit vector between them (first order).

    Parameters
    ----------
    centers_W : (S, 3) centres, m; centers_cov : (3 S, 3 S) their joint covariance; pairs : (P, 2) indices.

    Returns
    -------
    distances (P,) m, sigmas (P,) m
    """
    c = np.asarray(centers_W, float)
    C = np.asarray(centers_cov, float).reshape(len(c), 3, len(c), 3)
    i, j = np.asarray(pairs, dtype=int).T
    diff = c[i] - c[j]
    d = np.linalg.norm(diff, axis=1)
    g = diff / d[:, None]
    block = C[i, :, i, :] + C[j, :, j, :] - C[i, :, j, :] - C[j, :, i, :]
    return d, np.sqrt(np.einsum("pi,pij,pj->p", g, block, g))


# --------------------------------------------------------------------------------------- frame registration

def point_to_plane_information(source_p, target_n, target_a_T_source_b, residual_sigma_m) -> np.ndarray:
    """Information (6, 6) of a relative pose from point-to-plane correspondences (tangent ``[omega, v]``).

    The residual of a correspondence is ``e_i = n_i . (Z Exp(xi) p_i - q_i)`` with ``Z = (R, t)`` the relative
    pose ``a_T_b`` (source frame b into target frame a), ``p_i`` a source point, ``q_i``, ``n_i`` its target
    point and unit normal; ``de_i/dxi = [(p_i x R^T n_i)^T, (R^T n_i)^T]``.  With independent residuals of
    1-sigma ``s_i`` (the point-to-plane noise of both points) the Gauss-Newton information is
    ``sum g_i g_i^T / s_i^2``.

    Unlike ``open3d.pipelines.registration.get_information_matrix_from_point_clouds`` (point-to-point: three
    rows per correspondence, unit weight) this keeps only the normal component: on a surface extruded along the
    track (a tunnel) the tangential nearest-neighbour offsets carry no information about the motion along it,
    and the point-to-point matrix would claim they do.

    Parameters
    ----------
    source_p : (N, 3) source points (frame b) that found a correspondence, m.
    target_n : (N, 3) unit normals of their target points (frame a).
    target_a_T_source_b : (4, 4) the registered relative pose.
    residual_sigma_m : 1-sigma of the point-to-plane residuals, m: one for all, or (N,).
    """
    Z = np.asarray(target_a_T_source_b, float)
    n_b = np.asarray(target_n, float) @ Z[:3, :3]  # rows R^T n_i
    g = np.concatenate([np.cross(np.asarray(source_p, float), n_b), n_b], axis=1)
    g = g / np.reshape(np.asarray(residual_sigma_m, float), (-1, 1))
    return g.T @ g


def observable_square_root(information, relative_floor: float = 1e-6) -> np.ndarray:
    """``L`` (r, 6) with ``L^T L`` the information restricted to its eigen-directions above
    ``relative_floor`` times the largest: the directions the registration does not see (along an extruded
    surface) are left out instead of being given a made-up small information."""
    w, V = np.linalg.eigh(0.5 * (information + np.asarray(information).T))
    keep = w > relative_floor * w.max()
    return (V[:, keep] * np.sqrt(w[keep])).T


def relative_jitter_covariance(a_T_b, jitter_sigmas) -> np.ndarray:
    """Covariance (6, 6) of ``Log(a_T_b^-1 (a Exp(j_a))^-1 b Exp(j_b))`` from the white INS output jitter of
    both ends (``j ~ N(0, diag(jitter^2))``, right perturbation): ``Ad(b_T_a) D Ad(b_T_a)^T + D``."""
    Z = np.asarray(a_T_b, float)
    R, t = Z[:3, :3].T, -Z[:3, :3].T @ Z[:3, 3]  # b_T_a
    Ad = np.zeros((6, 6))
    Ad[0:3, 0:3] = R
    Ad[3:6, 3:6] = R
    Ad[3:6, 0:3] = so3.hat(t) @ R
    D = np.diag(np.asarray(jitter_sigmas, float) ** 2)
    return Ad @ D @ Ad.T + D
