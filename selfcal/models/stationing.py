"""Total-station stationing of a mobile manipulator: prism on the arm, tilt accelerometers on base and column.

Frames
------
``W``   total station, levelled: z up (its gravity alignment is good to 4.8e-5 rad).
``B``   robot base (URDF ``column_base``: the column's foot on the tracked base).
``T``   column tip (URDF ``column_tip``), ``B_t_T = (0, 0, h)`` for column extension ``h`` (the prismatic joint).
``S``   one *station*: the column tip's pose at one column height and arm solution space, ``W_T_S``.
``A``   an accelerometer frame (``A_b`` on the base, ``A_c`` at the column tip).

At a waypoint the arm's weight bends the column: the tip tilts by a small rotation ``Exp([tx, ty, 0])`` about
a pivot ``lambda * h`` below the tip (``lambda = 1/2`` for a pure end moment, ``2/3`` for an end force on a
uniform cantilever) relative to the station pose.  The arm's forward kinematics ``T_T_tool(q)`` come from the
URDF; the prism sits at ``tool_t_prism``.

Measurement equations
---------------------
prism        ``W_p = W_t_S + W_R_S (Exp(d) (T_p + lambda h e_z) - lambda h e_z)``,  ``T_p = T_R_tool tool_t_prism
             + T_t_tool``,  ``d = (tx, ty, 0)`` rad
tilt accel   ``f_A = |f_meas| A_R_T Exp(d)^T W_R_S^T e_z`` (m s^-2): at rest an accelerometer measures the
             specific force ``+g`` along the up direction; the measured norm is used as the magnitude, so the
             residual holds the *direction* only (2 degrees of freedom) and neither the local gravity nor a
             scale error enters.

A small horizontal accelerometer bias ``b`` reads as a mounting tilt ``b / g``; the two differ only by
``(1 - cos theta)`` over the tilt ``theta`` the sensor sees (1.5e-3 relative at the 3 deg of the steepest
dataset), so the mounting tilt estimated here *includes* the horizontal bias, and the vertical bias is
absorbed in the magnitude.

Jacobians are with respect to GTSAM's right perturbations: ``R Exp(w)`` for rotations, ``(R Exp(w), t + R v)``
with tangent ``[w, v]`` for poses, plain addition for vectors.

References
----------
Hilti construction-robot stationing datasets (Trailblazer prototype), README and ``trailblazer.urdf``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfcal.core import so3

E_Z = np.array([0.0, 0.0, 1.0])


def tilt_rotation(tilt_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Exp([tx, ty, 0])`` (N, 3, 3) and its right Jacobian's first two columns (N, 3, 2)."""
    tilt = np.atleast_2d(np.asarray(tilt_rad, dtype=float))
    d = np.concatenate([tilt, np.zeros((len(tilt), 1))], axis=1)
    return so3.exp(d).reshape(-1, 3, 3), so3.right_jacobian(d).reshape(-1, 3, 3)[:, :, :2]


def prism_position_W(R_W_S, t_W_S, tilt_rad, R_T_tool, t_T_tool, tool_t_prism, column_height_m, pivot_fraction):
    """Prism positions in the total-station frame and Jacobians (see the module's prism equation).

    Parameters
    ----------
    R_W_S, t_W_S : (3, 3), (3,)
        Station pose (column tip at the station).
    tilt_rad : (N, 2)
        Column-tip tilt of each waypoint relative to the station, rad.
    R_T_tool, t_T_tool : (N, 3, 3), (N, 3)
        Arm forward kinematics, tip -> tool flange.
    tool_t_prism : (3,)
        Prism in the tool frame, m.
    column_height_m : (N,)
        Column extension ``h``.
    pivot_fraction : float
        ``lambda``: the tilt pivot lies ``lambda h`` below the tip.

    Returns
    -------
    p_W : (N, 3)
    H_pose : (N, 3, 6)     wrt the station pose ``[w, v]``
    H_tilt : (N, 3, 2)
    H_prism : (N, 3, 3)
    H_pivot : (N, 3, 1)
    """
    R_W_S = np.asarray(R_W_S, dtype=float)
    h = np.asarray(column_height_m, dtype=float)
    Rd, Jr = tilt_rotation(tilt_rad)
    pivot = (pivot_fraction * h)[:, None] * E_Z
    x_T = np.einsum("nij,j->ni", R_T_tool, tool_t_prism) + t_T_tool
    z = x_T + pivot
    y = np.einsum("nij,nj->ni", Rd, z) - pivot  # prism in the station frame
    p_W = y @ R_W_S.T + t_W_S
    H_pose = np.empty((len(h), 3, 6))
    H_pose[:, :, :3] = -np.einsum("ij,njk->nik", R_W_S, so3.hat(y))
    H_pose[:, :, 3:] = R_W_S
    H_tilt = -np.einsum("ij,njk,nkl,nlm->nim", R_W_S, Rd, so3.hat(z), Jr)
    H_prism = np.einsum("ij,njk,nkl->nil", R_W_S, Rd, R_T_tool)
    H_pivot = (np.einsum("nij,j->ni", Rd, E_Z) - E_Z) @ R_W_S.T * h[:, None]
    return p_W, H_pose, H_tilt, H_prism, H_pivot[:, :, None]


def specific_force_A(R_W_S, tilt_rad, R_T_A, magnitude_m_s2):
    """Accelerometer reading at rest, ``|f| A_R_T Exp(d)^T W_R_S^T e_z``, and Jacobians.

    Parameters
    ----------
    R_W_S : (3, 3)
        Orientation of the body the sensor sits on (station / base), world from body.
    tilt_rad : (N, 2)
        Tilt of the body at each reading relative to ``R_W_S`` (zeros for a rigid body).
    R_T_A : (3, 3)
        Mounting: body from accelerometer.
    magnitude_m_s2 : (N,)
        The measured norm of each reading.

    Returns
    -------
    f_A : (N, 3)
    H_rot : (N, 3, 3)    wrt the body rotation (right perturbation)
    H_tilt : (N, 3, 2)
    H_mount : (N, 3, 3)
    """
    R_W_S, R_T_A = np.asarray(R_W_S, dtype=float), np.asarray(R_T_A, dtype=float)
    g = np.asarray(magnitude_m_s2, dtype=float)[:, None, None]
    Rd, Jr = tilt_rotation(tilt_rad)
    u = R_W_S.T @ E_Z  # up in the body frame
    v = np.einsum("nji,j->ni", Rd, u)  # up in the tilted body frame
    w = v @ R_T_A  # up in the accelerometer frame (rows: R_T_A^T v)
    f_A = g[:, :, 0] * w
    H_rot = g * np.einsum("ji,nkj,kl->nil", R_T_A, Rd, so3.hat(u))
    H_tilt = g * np.einsum("ji,njk,nkl->nil", R_T_A, so3.hat(v), Jr)
    H_mount = g * so3.hat(w)
    return f_A, H_rot, H_tilt, H_mount


# ------------------------------------------------------------------------------------------ robot kinematics

@dataclass(frozen=True)
class Joint:
    """One URDF joint: fixed origin ``parent_T_joint``, then the motion along/about ``axis``."""

    name: str
    kind: str  # fixed, revolute, continuous, prismatic
    origin: np.ndarray  # (4, 4)
    axis: np.ndarray  # (3,)


def chain_transforms(joints: list[Joint], q: np.ndarray) -> np.ndarray:
    """``first_T_last`` (N, 4, 4) of a serial chain for N joint vectors ``q`` (N, n_moving), in chain order."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    T = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
    k = 0
    for j in joints:
        T = T @ j.origin
        if j.kind == "fixed":
            continue
        motion = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
        if j.kind == "prismatic":
            motion[:, :3, 3] = q[:, k, None] * j.axis
        else:
            motion[:, :3, :3] = so3.exp(q[:, k, None] * j.axis).reshape(-1, 3, 3)
        T = T @ motion
        k += 1
    if k != q.shape[1]:
        raise ValueError(f"chain has {k} moving joints, joint vectors have {q.shape[1]}")
    return T


def origin_transform(xyz, rpy) -> np.ndarray:
    """URDF ``<origin xyz rpy>``: ``R = Rz(yaw) Ry(pitch) Rx(roll)``, as a 4x4 transform."""
    T = np.eye(4)
    r, p, y = rpy
    T[:3, :3] = so3.exp([0.0, 0.0, y]) @ so3.exp([0.0, p, 0.0]) @ so3.exp([r, 0.0, 0.0])
    T[:3, 3] = xyz
    return T
