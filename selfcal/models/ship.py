"""Vessel attitude physics: tilt from the total force vector, known accelerations, Euler-angle conventions.

Frames: body x forward, y left, z up; world local-level, z up; ``R_W_S = Rz(yaw) Ry(pitch) Rx(roll)`` (ZYX).
At rest the accelerometer measures ``f_S = R_W_S^T (0, 0, g)``, which gives

    roll = atan2(f_y, f_z),   pitch = atan2(-f_x, sqrt(f_y^2 + f_z^2))

Heave changes only |f| and leaves both angles alone (the patent's point).  Known accelerations of the hull,
in the body frame for a level ship: surge ``dv/dt`` along x, centripetal ``v * yaw_rate`` along y (towards the
centre of a turn; left turns have yaw_rate > 0); they are subtracted from f before the tilt is taken.
"""
from __future__ import annotations

import numpy as np


def tilt_from_specific_force(f_S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch (rad) of the total force direction, ``f_S`` (N, 3) or (3,), any unit.

    ``Rz^T`` leaves ``(0, 0, g)`` unchanged, ``Ry(pitch)^T`` gives ``g (-sin pitch, 0, cos pitch)``, ``Rx(roll)^T``
    gives ``f = g (-sin pitch, sin roll cos pitch, cos roll cos pitch)``; pitch lies in [-pi/2, pi/2].
    """
    f = np.asarray(f_S, dtype=float)
    roll = np.arctan2(f[..., 1], f[..., 2])
    pitch = np.arctan2(-f[..., 0], np.hypot(f[..., 1], f[..., 2]))
    return roll, pitch


def known_acceleration_S(speed_m_s: np.ndarray, speed_rate_m_s2: np.ndarray, yaw_rate_rad_s: np.ndarray) -> np.ndarray:
    """Hull acceleration the speed log and the gyro already explain (N, 3): (dv/dt, v * yaw_rate, 0)."""
    v = np.asarray(speed_m_s, dtype=float)
    return np.stack([np.asarray(speed_rate_m_s2, dtype=float), v * np.asarray(yaw_rate_rad_s, dtype=float),
                     np.zeros_like(v)], axis=-1)


def level_residual(R_W_S: np.ndarray, f_S: np.ndarray, A_S: np.ndarray, r_m_S: np.ndarray,
                   a_known_S: np.ndarray, speed_scale: float = 0.0):
    """Horizontal part of the measured force direction in the world frame: zero when the hull's up is measured.

    The accelerometer sits at ``r_m_S`` from the centre of rotation, so it measures
    ``f_S = f_centre + A_S r``, ``A_S = [w_dot]x + [w]x^2`` (:func:`selfcal.models.imu.lever_arm_jacobian`),
    plus the known hull acceleration ``(1 + speed_scale) a_known_S`` (speed log scale error ``speed_scale``).
    With ``u = unit(f_S - A_S r - (1 + k) a_known_S)`` the tilt residual is ``e = [I2 0] R_W_S u`` (rad, 2):
    the world-frame horizontal components of the corrected force direction, zero when it is the world's up.

    Returns ``e`` and its Jacobians on a right perturbation ``R Exp(xi)`` (2x3), on ``r`` (2x3) and on ``k``
    (2x1): ``de/dxi = -P R [u]x``; ``du/df_c = (I - u u^T) / |f_c|``, ``df_c/dr = -A``, ``df_c/dk = -a_known``.
    """
    f_c = f_S - A_S @ r_m_S - (1.0 + speed_scale) * a_known_S
    norm = np.linalg.norm(f_c)
    u = f_c / norm
    P_R = R_W_S[:2, :]
    e = P_R @ u
    du_df = (np.eye(3) - np.outer(u, u)) / norm
    H_R = -P_R @ np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    H_r = -P_R @ du_df @ A_S
    H_k = -(P_R @ du_df @ a_known_S).reshape(2, 1)
    return e, H_R, H_r, H_k
