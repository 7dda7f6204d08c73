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
