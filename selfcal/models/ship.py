"""Vessel attitude physics: tilt from the total force vector, known accelerations, Euler-angle conventions.

Frames: body x forward, y left, z up; world local-level, z up; ``R_W_S = Rz(yaw) Ry(pitch) Rx(roll)`` (ZYX).
At rest the accelerometer measures ``f_S = R_W_S^T (0, 0, g)``, which gives

    roll = atan2(f_y, f_z),   pitch = atan2(-f_x, sqrt(f_y^2 + f_z^2))

Heave changes only |f| and leaves both angles alone (the patent's point).  Known accelerations of the hull
(:func:`hull_acceleration_W`): the hull moves along its heading ``psi`` (the ZYX yaw), so in the world frame it
accelerates by ``dv/dt h + v psi_dot h_perp`` (surge along the heading ``h``, centripetal towards the centre of a
turn; left turns have psi_dot > 0); they are subtracted from the force before the tilt is taken.  The body-frame
form for a level ship, ``(dv/dt, v w_z, 0)`` (:func:`known_acceleration_S`), is only a first-order guide (drivers,
sigmas, start values): rolling and pitching, ``w_z`` is not ``psi_dot`` (``psi_dot = (sin(roll) w_y + cos(roll) w_z)
/ cos(pitch)``) and the body's y axis is not horizontal; on a 6 m/s heave voyage rolling 10 deg the level form
left 0.48 mrad RMS of tilt on exact data, more than the tilt noise, which the audit found as structure in time.
A gyro that reads ``(1 + s)`` times the true rate per axis over- or under-rotates the attitude it carries
between keyframes: :func:`scaled_gyro_preintegration` and :func:`scaled_gyro_rotation_residual`.
"""
from __future__ import annotations

import numpy as np

from selfcal.core import so3


def known_acceleration_S(speed_m_s: np.ndarray, speed_rate_m_s2: np.ndarray, yaw_rate_rad_s: np.ndarray) -> np.ndarray:
    """Hull acceleration the speed log and the gyro already explain (N, 3): (dv/dt, v * yaw_rate, 0)."""
    v = np.asarray(speed_m_s, dtype=float)
    return np.stack([np.asarray(speed_rate_m_s2, dtype=float), v * np.asarray(yaw_rate_rad_s, dtype=float),
                     np.zeros_like(v)], axis=-1)


HAT_E = tuple(so3.hat(e) for e in np.eye(3))  # [e_x]x, [e_y]x, [e_z]x


def hull_acceleration_W(R_W_S: np.ndarray, surge_m_s2: float, vw_S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The hull's acceleration the speed log and the gyro explain, world frame (3,) m/s^2, and its Jacobian on a
    right perturbation ``R Exp(xi)`` (3x3).

    The hull moves along its heading at the log's speed ``v``: ``a_W = dv/dt h + v psi_dot h_perp`` with ``h =
    (cos psi, sin psi, 0)``, ``h_perp = (-sin psi, cos psi, 0)``.  The heading rate comes from the body rate ``w_S``
    and the attitude: the bow ``c = R e_x`` turns as ``dc/dt = R (w_S x e_x)``, so ``psi_dot = (c x dc/dt)_z /
    (c_x^2 + c_y^2)`` (the ZYX yaw rate, exactly).  ``vw_S = v w_S`` (rad m s^-2), averaged over the keyframe as the
    force is (the residual is linear in it); ``surge_m_s2 = dv/dt``.
    """
    c = R_W_S[:, 0]
    vw_x_ex = np.array([0.0, vw_S[2], -vw_S[1]])  # vw_S x e_x, written out: np.cross costs 40 us a call, and the
    # audit's tilt factors call this a quarter of a million times per voyage
    d = R_W_S @ vw_x_ex
    n = c[0] ** 2 + c[1] ** 2
    psi = np.arctan2(c[1], c[0])
    h, h_perp = np.array([np.cos(psi), np.sin(psi), 0.0]), np.array([-np.sin(psi), np.cos(psi), 0.0])
    v_psi_dot = (c[0] * d[1] - c[1] * d[0]) / n
    dc = -R_W_S @ HAT_E[0]  # d c / d xi
    dd = -R_W_S @ so3.hat(vw_x_ex)
    dpsi = (c[0] * dc[1] - c[1] * dc[0]) / n
    dv_psi_dot = (dc[0] * d[1] + c[0] * dd[1] - dc[1] * d[0] - c[1] * dd[0]
                  - 2.0 * v_psi_dot * (c[0] * dc[0] + c[1] * dc[1])) / n
    a_W = surge_m_s2 * h + v_psi_dot * h_perp
    H = np.outer(surge_m_s2 * h_perp - v_psi_dot * h, dpsi) + np.outer(h_perp, dv_psi_dot)
    return a_W, H


def euler_zyx(R_W_S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(roll, pitch, yaw) of ``R_W_S = Rz(yaw) Ry(pitch) Rx(roll)``, rad, and their Jacobian (3x3) on a right
    perturbation ``R Exp(xi)``: each entry moves as ``d R_ij = -(R [e_j]x xi)_i``."""
    dR = [-R_W_S @ hat for hat in HAT_E]  # d (R e_j) / d xi, column j of R
    roll = np.arctan2(R_W_S[2, 1], R_W_S[2, 2])
    pitch = -np.arcsin(np.clip(R_W_S[2, 0], -1.0, 1.0))
    yaw = np.arctan2(R_W_S[1, 0], R_W_S[0, 0])
    m = R_W_S[2, 1] ** 2 + R_W_S[2, 2] ** 2
    n = R_W_S[0, 0] ** 2 + R_W_S[1, 0] ** 2
    d_roll = (R_W_S[2, 2] * dR[1][2] - R_W_S[2, 1] * dR[2][2]) / m
    d_pitch = -dR[0][2] / np.sqrt(max(1.0 - R_W_S[2, 0] ** 2, 1e-300))
    d_yaw = (R_W_S[0, 0] * dR[0][1] - R_W_S[1, 0] * dR[0][0]) / n
    return np.array([roll, pitch, yaw]), np.vstack([d_roll, d_pitch, d_yaw])


def level_residual(R_W_S: np.ndarray, f_S: np.ndarray, A_S: np.ndarray, r_m_S: np.ndarray,
                   surge_m_s2: float = 0.0, vw_S=(0.0, 0.0, 0.0), speed_scale: float = 0.0, scale_regressor=None):
    """Horizontal part of the measured force direction in the world frame: zero when the hull's up is measured.

    The accelerometer sits at ``r_m_S`` from the centre of rotation, so it measures
    ``f_S = f_centre + A_S r``, ``A_S = [w_dot]x + [w]x^2`` (:func:`selfcal.core.inertial.lever_arm_jacobian`),
    plus the known hull acceleration ``(1 + speed_scale) a_W`` (:func:`hull_acceleration_W` of ``surge_m_s2``
    and ``vw_S``; speed log scale error ``speed_scale``).  With ``g = R_W_S (f_S - A_S r) - (1 + k) a_W`` and
    ``u = unit(g)`` the tilt residual is ``e = [I2 0] u`` (rad, 2): the world-frame horizontal components of the
    corrected force direction, zero when it is the world's up.

    ``scale_regressor`` ``(surge, vw_S)``: the scale multiplies the hull acceleration of these instead,
    ``g = R (f_S - A_S r) - a_W - k a_W'``: the same quantities smoothed over seconds.  The gyro's white noise in
    ``v w`` sits in the residual and, unsmoothed, in the regressor too, which pulls ``k`` by
    ``-Var(noise) / Var(regressor)``: errors in the variables (a null voyage read a 5 % scale).

    Returns ``e`` and its Jacobians on a right perturbation ``R Exp(xi)`` (2x3), on ``r`` (2x3) and on ``k``
    (2x1): ``du/dg = (I - u u^T) / |g|``, ``dg/dxi = -R [f_c]x - da_W/dxi - k da_W'/dxi``, ``dg/dr = -R A``,
    ``dg/dk = -a_W'`` (``a_W' = a_W`` without a regressor).
    """
    a_W, H_a = hull_acceleration_W(R_W_S, surge_m_s2, np.asarray(vw_S, dtype=float))
    a_k, H_ak = (a_W, H_a) if scale_regressor is None else hull_acceleration_W(
        R_W_S, float(scale_regressor[0]), np.asarray(scale_regressor[1], dtype=float))
    f_c = f_S - A_S @ r_m_S
    g = R_W_S @ f_c - a_W - speed_scale * a_k
    norm = np.linalg.norm(g)
    u = g / norm
    P_du = ((np.eye(3) - np.outer(u, u)) / norm)[:2]
    H_R = P_du @ (-R_W_S @ so3.hat(f_c) - H_a - speed_scale * H_ak)
    H_r = -P_du @ R_W_S @ A_S
    H_k = -(P_du @ a_k).reshape(2, 1)
    return u[:2], H_R, H_r, H_k


def along_track_weight(R_W_S: np.ndarray, e: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A tilt residual ``e`` (2, world horizontal) weighed down along the hull's heading: ``W e`` and the
    Jacobians of ``W e`` on ``e`` (``W``, 2x2) and on a right perturbation ``R Exp(xi)`` of the attitude (2x3).

    The speed log's rate (``dv/dt``, error ``sigma_a``) corrects the force along the heading ``h = (cos psi,
    sin psi)`` only, so a keyframe's tilt covariance is ``sigma^2 I + (sigma_a / g)^2 h h^T``, not isotropic.
    With ``ratio = sigma_a / (g sigma)`` the residual ``W e``, ``W = I + (s - 1) h h^T``, ``s = 1 / sqrt(1 +
    ratio^2)``, has covariance ``sigma^2 I``: across the track it keeps the tilt's own precision.  ``W``
    turns with the state's heading (``dW/dpsi = (s - 1)(h' h^T + h h'^T)``, ``h' = (-sin psi, cos psi)``);
    ``det W`` does not, so the least-squares cost needs no log-determinant term.
    """
    s = 1.0 / np.sqrt(1.0 + ratio**2)
    c = R_W_S[:, 0]
    n = c[0] ** 2 + c[1] ** 2
    psi = np.arctan2(c[1], c[0])
    h, h_perp = np.array([np.cos(psi), np.sin(psi)]), np.array([-np.sin(psi), np.cos(psi)])
    W = np.eye(2) + (s - 1.0) * np.outer(h, h)
    dc = -R_W_S @ HAT_E[0]  # d c / d xi
    dpsi = (c[0] * dc[1] - c[1] * dc[0]) / n
    dW_e = (s - 1.0) * (h_perp * (h @ e) + h * (h_perp @ e))
    return W @ e, W, np.outer(dW_e, dpsi)


# --- gyro scale error on the rotation preintegrated between keyframes ---------------------------------------------

def gyro_scale_correction(gyro_scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rate correction ``c = s / (1 + s)`` per axis of a gyro that reads ``(1 + s)`` times the true rate, and
    ``dc/ds = 1 / (1 + s)^2`` (diagonal, (3,)): ``w = (1 - c) (w_raw - b)`` is the true rate, exactly."""
    s = np.asarray(gyro_scale, dtype=float)
    return s / (1.0 + s), 1.0 / (1.0 + s) ** 2


def scaled_gyro_preintegration(gyro_rad_s: np.ndarray, dt_s: np.ndarray, bias_hat_rad_s: np.ndarray):
    """Rotation preintegrated from raw gyro samples, with its first-order sensitivity to the bias and the scale.

    Sensor model, per axis i of the body frame S (x forward, y left, z up): ``w_raw_i = (1 + s_i) w_i + b_i``
    (+ noise), ``w`` the true body rate (rad/s), ``s`` the dimensionless scale error (0 = nominal, the audit's
    ``scale``), ``b`` the bias (rad/s).  Written with the correction ``c_i = s_i / (1 + s_i)``
    (:func:`gyro_scale_correction`) the true rate is *linear* in it: ``w = (1 - c) (w_raw - b)``.  The rotation
    body(k) <- body(k+1) held over the samples (zero-order hold, as GTSAM's ``PreintegratedRotation``)::

        dR(b, c) = prod_n Exp((1 - c) (w_n - b) dt_n)
                 ~ dR_meas Exp(J_b (b - b_hat) + J_c c)          (first order in b - b_hat and c)

    ``dR_meas = prod_n Exp(u_n dt_n)``, ``u_n = w_n - b_hat``.  Both Jacobians accumulate along the samples like
    GTSAM's bias Jacobian ``delRdelBiasOmega`` (Forster et al. 2017, eq. 44), with the rate's own derivative
    ``dw/db = -I`` and ``dw/dc = -diag(u_n)``::

        J <- Exp(u_n dt_n)^T J + Jr(u_n dt_n) (dw/d.) dt_n

    (here summed in closed form by :func:`selfcal.core.so3.integrate_rates`).  For rotation about one fixed
    axis the first-order form is exact in ``c`` (all the Exp's commute), whatever the angle; the remainder is of
    order ``c |theta|^2`` times the non-commuting part of the motion between two keyframes.

    Parameters
    ----------
    gyro_rad_s : (N, 3) raw gyro samples since the previous keyframe, rad/s.
    dt_s : (N,) how long each sample is held, s.
    bias_hat_rad_s : (3,) bias the samples are preintegrated about, rad/s.

    Returns
    -------
    delta_R : (3, 3) ``dR_meas``.
    J_bias : (3, 3) ``J_b``, rad per rad/s.
    J_correction : (3, 3) ``J_c``, rad per unit of c.
    """
    u = np.asarray(gyro_rad_s, dtype=float).reshape(-1, 3) - np.asarray(bias_hat_rad_s, dtype=float)
    delta_R, J = so3.integrate_rates(u, np.asarray(dt_s, dtype=float).reshape(-1), with_jacobians=True)
    # J[n] d moves sample n's rate by d: bias moves every rate by -db, the correction rate n by -diag(u_n) dc
    return delta_R, -J.sum(axis=0), -np.einsum("nij,nj->ij", J, u)


def scaled_gyro_rotation_residual(R_W_Si: np.ndarray, R_W_Sj: np.ndarray, delta_R: np.ndarray, J_bias: np.ndarray,
                                  J_correction: np.ndarray, bias_hat_rad_s: np.ndarray, bias_rad_s: np.ndarray,
                                  gyro_scale: np.ndarray):
    """GTSAM's AHRSFactor residual with a gyro scale error: ``e = Log(R_W_Sj^T R_W_Si dR(b, s))`` (rad, 3).

    The attitude the gyro carries from keyframe i, ``R_W_Si dR(b, s)``, against keyframe j's, in j's tangent
    space (GTSAM 4.3: ``Rj.localCoordinates(predicted_Rj)``).  ``dR(b, s) = delta_R Exp(phi)``,
    ``phi = J_bias (b - b_hat) + J_correction c(s)`` (:func:`scaled_gyro_preintegration`,
    :func:`gyro_scale_correction`); with ``s = 0`` it is the AHRSFactor's error (no Coriolis term: a ship's
    rates dwarf the earth's).  Attitudes ``R_W_S`` map body to local level.

    Returns ``e`` and its Jacobians on right perturbations ``R Exp(xi)`` of ``R_W_Si`` and ``R_W_Sj`` (3x3 each),
    on ``b`` (3x3, rad per rad/s) and on ``s`` (3x3); with ``E = Exp(e)``::

        de/dxi_i = Jr^-1(e) dR(b, s)^T,   de/dxi_j = -Jr^-1(e) E^T,
        de/dphi = Jr^-1(e) Jr(phi),   de/db = de/dphi J_bias,   de/ds = de/dphi J_correction diag(1 / (1 + s)^2).
    """
    c, dc_ds = gyro_scale_correction(gyro_scale)
    phi = J_bias @ (np.asarray(bias_rad_s, dtype=float) - bias_hat_rad_s) + J_correction @ c
    predicted = delta_R @ so3.exp(phi)
    E = R_W_Sj.T @ R_W_Si @ predicted
    e = so3.log(E)
    Jr_inv = np.linalg.inv(so3.right_jacobian(e))
    H_phi = Jr_inv @ so3.right_jacobian(phi)
    return e, Jr_inv @ predicted.T, -Jr_inv @ E.T, H_phi @ J_bias, H_phi @ J_correction * dc_ds


def averaged_specific_force(accel_m_s2: np.ndarray, n_average: int, n_noise: int) -> tuple[np.ndarray, np.ndarray]:
    """The tilt measurement of each sample's keyframe: the force averaged over ``n_average`` samples centred on
    it, and the variance (m^2 s^-4, per axis) of one sample's error across the force direction.

    A centred mean of a force that changes linearly (a hull rolling through the window) is its value at the
    centre, so averaging removes the accelerometer's white noise (and any vibration) by ``n_average`` without
    a lag.  The noise across the force direction -- the part that tilts it -- is measured from the data:
    first differences cancel the slow motion of the hull, and a white sequence's differences have twice its
    variance, so ``var = mean |d_perp|^2 / 4`` over ``n_noise`` samples (two axes across ``f``).  Heave and
    every acceleration along ``f`` change only ``|f|`` and do not enter.

    Parameters
    ----------
    accel_m_s2 : (N, 3) specific force samples on a uniform grid, m s^-2.
    n_average, n_noise : centred window lengths in samples (clipped at the ends).

    Returns
    -------
    f_mean : (N, 3) averaged force, m s^-2.
    noise_var : (N,) per-axis variance of one sample across the force, m^2 s^-4.
    """
    from scipy.ndimage import uniform_filter1d
    a = np.asarray(accel_m_s2, dtype=float)
    f_mean = uniform_filter1d(a, size=max(1, n_average), axis=0, mode="nearest")
    if len(a) < 2:
        return f_mean, np.zeros(len(a))
    u = f_mean / np.linalg.norm(f_mean, axis=1, keepdims=True)
    d = np.diff(a, axis=0)
    d_perp_sq = np.sum(d**2, axis=1) - np.sum(d * u[1:], axis=1) ** 2
    d_perp_sq = np.concatenate([d_perp_sq[:1], d_perp_sq])
    return f_mean, uniform_filter1d(d_perp_sq, size=max(2, n_noise), mode="nearest") / 4.0
