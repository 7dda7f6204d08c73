"""Rotation helpers on SO(3) that scipy does not provide: hat, right Jacobian, integration with Jacobians.

Conventions match GTSAM: perturbations are on the right, ``R(x + dx) = R(x) Exp(J dx)``.
Exp and Log themselves come from :class:`scipy.spatial.transform.Rotation`, imported when first used (scipy.spatial
costs ~0.5 s of start-up that the online tracker, which needs neither, would pay).
"""
from __future__ import annotations

import numpy as np


def hat(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix(es) [v]x with [v]x w = v x w; v has shape (3,) or (N, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix(es) Exp(phi) for rotation vector(s) phi in rad."""
    from scipy.spatial.transform import Rotation
    return Rotation.from_rotvec(np.asarray(phi, dtype=float)).as_matrix()


def log(R: np.ndarray) -> np.ndarray:
    """Rotation vector(s) Log(R) in rad."""
    from scipy.spatial.transform import Rotation
    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_rotvec()


def right_jacobian(phi: np.ndarray) -> np.ndarray:
    """Right Jacobian J_r(phi): Exp(phi + d) = Exp(phi) Exp(J_r(phi) d) to first order; phi (3,) or (N, 3).

    J_r = I - (1 - cos t)/t^2 [phi]x + (t - sin t)/t^3 [phi]x^2, t = |phi| (Forster et al. 2017, eq. 8).
    """
    phi = np.asarray(phi, dtype=float)
    t = np.linalg.norm(phi, axis=-1)[..., None, None]
    small = t < 1e-6
    t_safe = np.where(small, 1.0, t)
    a = np.where(small, 0.5, (1.0 - np.cos(t_safe)) / t_safe**2)
    b = np.where(small, 1.0 / 6.0, (t_safe - np.sin(t_safe)) / t_safe**3)
    K = hat(phi)
    return np.eye(3) - a * K + b * (K @ K)


def integrate_rates(w_rad_s: np.ndarray, dt_s: np.ndarray, with_jacobians: bool = False):
    """Integrate body angular rates into the rotation body(start) <- body(end).

    ``delta_R = Exp(w_1 dt_1) Exp(w_2 dt_2) ... Exp(w_n dt_n)`` (zero-order hold per sample).

    Parameters
    ----------
    w_rad_s : (N, 3) angular rate of the body in the body frame, rad/s.
    dt_s : (N,) duration each sample is held, s.
    with_jacobians : also return ``J`` with ``delta_R(w_i + d) = delta_R Exp(J[i] d)``.

    Returns
    -------
    delta_R : (3, 3)
    J : (N, 3, 3), only when ``with_jacobians``.
    """
    phi = np.asarray(w_rad_s, dtype=float) * np.asarray(dt_s, dtype=float)[:, None]
    if len(phi) == 0:
        return (np.eye(3), np.zeros((0, 3, 3))) if with_jacobians else np.eye(3)
    # prefix products P_i = Exp(phi_1) ... Exp(phi_i) by a log-depth scan (Hillis–Steele): each pass is one
    # batched matmul, so n samples cost log2(n) numpy calls instead of n
    prefix = exp(phi)
    shift = 1
    while shift < len(prefix):
        prefix[shift:] = prefix[:-shift] @ prefix[shift:]
        shift *= 2
    R = prefix[-1]
    if not with_jacobians:
        return R
    # delta_R = P_i S_i with suffix S_i = P_i^T delta_R; perturbing step i gives Exp(S_i^T J_r(phi_i) dt_i d).
    suffix_T = np.einsum("ij,njk->nik", R.T, prefix)
    J = suffix_T @ right_jacobian(phi) * np.asarray(dt_s, dtype=float)[:, None, None]
    return R, J
