"""Laser-tracker target physics (patent 004): prism, inclinometer, beam-spot camera and IMU on one rigid body.

Frames
------
``W``  the tracker (world) frame: origin at the tracker's rotation centre, levelled, z up.
``B``  the body frame = the IMU frame (the strapdown unit defines the target's body).
``C``  the camera (OpenCV convention: z along the optical axis, x right, y down in the image).
``I``  the inclinometer, assumed aligned with and co-located with ``B`` (one board with the IMU).

Attitude ``R_W_B = Rz(yaw) Ry(pitch) Rx(roll)`` (ZYX, as :mod:`selfcal.models.ship`).  Pose perturbations are
GTSAM's Pose3 right perturbations ``(R Exp(w), p + R dt)``, tangent order ``[w, dt]``.

Measurement equations
---------------------
prism (tracker)          ``p_P_W = p_B_W + R_W_B r_P_B``                         (GPSFactorArm)
prism velocity           ``v_P_W = v_B_W + R_W_B (w_B x r_P_B)``
inclinometer             ``(roll, pitch) = tilt(f_B)``,  ``f_B = R_W_B^T (a_W + g e_z)``: the direction of the
                         *specific force*, so any non-gravitational acceleration ``a_W`` tilts the reading by
                         about ``|a_horizontal| / g`` rad (the vibration problem of the patent)
beam spot (camera)       the tracker's centre seen from the camera: ``d_C = R_B_C^T (R_W_B^T (t_W - p_B_W) - r_C_B)``,
                         projected with the OpenCV model (``cv2.projectPoints``); the bearing ``d_C / |d_C|``
                         is recovered from the pixel with ``cv2.undistortPoints``.

The patent's azimuth comes from "double-vector attitude determination": the gravity direction (inclinometer)
and the beam direction (camera), each known in both frames, give the whole attitude (:func:`attitude_from_tilt_and_beam`).

References
----------
CN 115574815 A (seed 004), "Six-degree-of-freedom laser target measurement system and its dynamic performance
improvement method", steps S101-S103.
"""
from __future__ import annotations


import cv2
import numpy as np

from selfcal.core import so3
from selfcal.core.inertial import tilt_from_specific_force

__all__ = ["up_direction_B", "tilt_from_axis_angles", "axis_angles_from_tilt",
           "cross", "prism_position_W", "prism_velocity_W", "prism_velocity_jacobians", "beam_direction_C",
           "beam_bearing_residual", "pixel_from_direction_C", "bearing_from_pixel", "attitude_from_tilt_and_beam",
           "rotation_from_euler", "euler_from_rotation",
           "tilt_of_rotation", "inclinometer_reading", "prism_position_delayed"]

E_Z = np.array([0.0, 0.0, 1.0])


def rotation_from_euler(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """``R_W_B = Rz(yaw) Ry(pitch) Rx(roll)``, (3, 3) or (N, 3, 3)."""
    from scipy.spatial.transform import Rotation  # here: scipy.spatial costs the online tracker ~0.5 s start-up
    return Rotation.from_euler("ZYX", np.stack([yaw_rad, pitch_rad, roll_rad], axis=-1)).as_matrix()


def euler_from_rotation(R_W_B) -> np.ndarray:
    """(roll, pitch, yaw) in rad of ``R_W_B`` (ZYX), shape (..., 3)."""
    from scipy.spatial.transform import Rotation
    ypr = Rotation.from_matrix(np.asarray(R_W_B)).as_euler("ZYX")
    return ypr[..., ::-1]


def up_direction_B(roll_rad, pitch_rad) -> np.ndarray:
    """World up in the body frame for a tilt: ``R_W_B^T e_z = (-sin p, sin r cos p, cos r cos p)``, (..., 3)."""
    r, p = np.asarray(roll_rad, dtype=float), np.asarray(pitch_rad, dtype=float)
    return np.stack([-np.sin(p), np.sin(r) * np.cos(p), np.cos(r) * np.cos(p)], axis=-1)


def tilt_from_axis_angles(theta_x_rad, theta_y_rad) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch from a dual-axis inclinometer's two axis inclinations (patent S101).

    Each axis reports its angle to the horizontal plane: ``sin theta_x = (R_W_B e_x) . e_z = -sin pitch``,
    ``sin theta_y = (R_W_B e_y) . e_z = sin roll cos pitch``; hence ``pitch = -theta_x`` and
    ``roll = asin(sin theta_y / cos pitch)`` (the patent's geometric relation, up to its axis naming).
    """
    pitch = -np.asarray(theta_x_rad, dtype=float)
    roll = np.arcsin(np.clip(np.sin(theta_y_rad) / np.cos(pitch), -1.0, 1.0))
    return roll, pitch


def axis_angles_from_tilt(roll_rad, pitch_rad) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`tilt_from_axis_angles`: the two axis inclinations (rad)."""
    pitch = np.asarray(pitch_rad, dtype=float)
    return -pitch, np.arcsin(np.sin(roll_rad) * np.cos(pitch))


def cross(a, b) -> np.ndarray:
    """``a x b`` for (..., 3) arrays (np.cross costs ~30 us per call: too slow inside a factor)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.ndim == 1 and b.ndim == 1:  # one pair (the online estimator's case): Python floats beat np.stack 5x
        a0, a1, a2 = a.tolist()
        b0, b1, b2 = b.tolist()
        return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def prism_position_W(R_W_B, p_B_W, r_P_B) -> np.ndarray:
    """``p_P_W = p_B_W + R_W_B r_P_B`` (m); R (..., 3, 3), p (..., 3)."""
    return np.asarray(p_B_W) + np.einsum("...ij,j->...i", R_W_B, np.asarray(r_P_B, dtype=float))


def prism_velocity_W(R_W_B, v_B_W, w_B, r_P_B) -> np.ndarray:
    """``v_P_W = v_B_W + R_W_B (w_B x r_P_B)`` (m s^-1): rotation adds ``w x r`` to the body's velocity."""
    if np.ndim(R_W_B) == 2 and np.ndim(w_B) == 1:  # one instant: plain products (einsum costs ~4 us a call)
        return np.asarray(v_B_W) + np.asarray(R_W_B) @ cross(w_B, r_P_B)
    return np.asarray(v_B_W) + np.einsum("...ij,...j->...i", R_W_B, cross(w_B, r_P_B))


def prism_velocity_jacobians(R_W_B, w_B, r_P_B) -> tuple[np.ndarray, np.ndarray]:
    """d v_P / d(pose tangent) (3, 6) and d v_P / d v_B (3, 3) of :func:`prism_velocity_W` at one instant.

    ``R Exp(e) (w x r) ~ R (w x r) - R [w x r]x e``; translation does not enter.
    """
    H_pose = np.zeros((3, 6))
    H_pose[:, :3] = -R_W_B @ so3.hat(cross(w_B, r_P_B))
    return H_pose, np.eye(3)


def beam_direction_C(R_W_B, p_B_W, r_C_B, R_B_C, tracker_W=np.zeros(3)) -> np.ndarray:
    """Vector from the camera to the tracker in the camera frame (m, not normalised).

    ``d_C = R_B_C^T (R_W_B^T (t_W - p_B_W) - r_C_B)``.
    """
    if np.ndim(R_W_B) == 2 and np.ndim(p_B_W) == 1:  # one pose: plain products (einsum costs ~4 us a call)
        return np.asarray(R_B_C).T @ (np.asarray(R_W_B).T @ (np.asarray(tracker_W) - p_B_W) - np.asarray(r_C_B))
    d_B = np.einsum("...ji,...j->...i", R_W_B, np.asarray(tracker_W) - np.asarray(p_B_W)) - np.asarray(r_C_B)
    return np.einsum("ji,...j->...i", R_B_C, d_B)


def beam_bearing_residual(R_W_B, p_B_W, r_C_B, R_B_C, bearing_C, basis_C, tracker_W=np.zeros(3),
                          with_jacobian: bool = False):
    """Bearing residual ``e = basis^T b`` (2,), ``b = d_C / |d_C|``, against a measured unit bearing.

    ``basis_C`` (3, 2) spans the tangent plane of the measured bearing (``gtsam.Unit3.basis()``), so ``e`` is
    the angle (rad, small) between the measured and predicted beam directions, resolved on two axes.  With
    ``with_jacobian`` also returns de/d(pose tangent [w, dt]) (2, 6):

    ``d_B(R Exp(w), p + R dt) ~ d_B + [d_B + r_C_B]x w - dt``;  ``db/dd = (I - b b^T) / |d|``.
    """
    d_B = R_W_B.T @ (np.asarray(tracker_W) - p_B_W) - r_C_B
    d_C = R_B_C.T @ d_B
    n = float(np.sqrt(d_C @ d_C))
    b = d_C / n
    e = basis_C.T @ b
    if not with_jacobian:
        return e
    # basis^T (I - b b^T) / |d| R_B_C^T, then times [[d_B + r_C_B]x, -I]
    G = (basis_C.T - np.outer(e, b)) @ R_B_C.T / n
    return e, np.hstack([G @ so3.hat(d_B + r_C_B), -G])


def tilt_of_vector(u, with_jacobian: bool = False):
    """(roll, pitch) (rad) of the direction of ``u`` (3,), any length (:func:`tilt_from_specific_force`); with the
    (2, 3) Jacobian ``d tilt / d u``: the derivatives of ``roll = atan2(u_y, u_z)``, ``pitch = atan2(-u_x, rho)``,
    ``rho = hypot(u_y, u_z)`` (both unchanged by the length, so the Jacobian is orthogonal to ``u``)."""
    u = np.asarray(u, dtype=float)
    z = np.array(tilt_from_specific_force(u))
    if not with_jacobian:
        return z
    rho2 = u[1] ** 2 + u[2] ** 2
    rho, n2 = np.sqrt(rho2), rho2 + u[0] ** 2
    return z, np.array([[0.0, u[2] / rho2, -u[1] / rho2],
                        [-rho / n2, u[0] * u[1] / (rho * n2), u[0] * u[2] / (rho * n2)]])


def tilt_of_rotation(R_W_B, with_jacobian: bool = False):
    """(roll, pitch) (rad) of gravity seen in the body, ``tilt(R_W_B^T e_z)``; with the (2, 3) Jacobian on the
    rotation's right perturbation ``R Exp(w)``: ``d up/dw = [up]x``, then :func:`tilt_of_vector`'s."""
    u = np.asarray(R_W_B)[2]
    if not with_jacobian:
        return tilt_of_vector(u)
    z, D = tilt_of_vector(u, True)
    return z, D @ so3.hat(u)


def vibration_disturbance(R_W_B, f_B, turn_B, accel_bias_B, weight: float, with_jacobian: bool = False):
    """The inclinometer's predicted disturbance ``d = weight (tilt(f') - tilt(R_W_B))`` (2,) rad: the tilt the
    accelerometer's mean specific force shows beyond the attitude's, times its Wiener weight.

    ``f' = turn_B (f_B - accel_bias_B)``: the mean raw specific force (m/s^2) over the inclinometer's window,
    bias-corrected and turned to the keyframe by ``turn_B`` (3, 3; ``I - c [w]x`` for a body rate ``w`` and lead
    ``c``).  With the Jacobians ``{"rotation" (2, 3), "accel_bias" (2, 3)}``: both the attitude and the
    accelerometer bias are states, so the disturbance follows them as a fit moves them.
    """
    f = np.asarray(turn_B) @ (np.asarray(f_B, dtype=float) - np.asarray(accel_bias_B, dtype=float))
    out_f, out_R = tilt_of_vector(f, with_jacobian), tilt_of_rotation(R_W_B, with_jacobian)
    if not with_jacobian:
        return weight * (out_f - out_R)
    (tilt_f, D_f), (tilt_R, J_R) = out_f, out_R
    return weight * (tilt_f - tilt_R), {"rotation": -weight * J_R, "accel_bias": -weight * D_f @ np.asarray(turn_B)}


def inclinometer_reading(R_W_B, disturbance_rad, bias_rad=np.zeros(2), scale: float = 0.0,
                         accel_sensitivity: float = 0.0, with_jacobian: bool = False):
    """Predicted (roll, pitch) reading (rad) of an inclinometer with calibration errors.

    ``z = (1 + scale) (tilt_g + (1 + accel_sensitivity) d) + bias``: ``tilt_g`` is the true tilt
    (:func:`tilt_of_rotation`), ``d`` (2,) the tilt the non-gravitational acceleration adds to the specific
    force's direction (what a perfect inclinometer also reads).  The simulator's model, term by term.  With the
    Jacobians ``{"rotation" (2, 3), "bias" (2, 2), "scale" (2, 1), "accel_sensitivity" (2, 1), "disturbance" (2, 2)}``.
    """
    d = np.asarray(disturbance_rad, dtype=float)
    out = tilt_of_rotation(R_W_B, with_jacobian)
    tilt, J = out if with_jacobian else (out, None)
    inner = tilt + (1.0 + accel_sensitivity) * d
    z = (1.0 + scale) * inner + np.asarray(bias_rad, dtype=float)
    if not with_jacobian:
        return z
    return z, {"rotation": (1.0 + scale) * J, "bias": np.eye(2), "scale": inner[:, None],
               "accel_sensitivity": ((1.0 + scale) * d)[:, None],
               "disturbance": (1.0 + scale) * (1.0 + accel_sensitivity) * np.eye(2)}


def prism_position_delayed(R_W_B, p_B_W, r_P_B, v_W, dt_s: float) -> np.ndarray:
    """Prism position a tracker stamping ``dt_s`` late reports: ``p + R r - dt v`` (m; first order in dt, the
    target moves mm/s to cm/s); ``v_W`` (3,) or (n, 3) gives (3,) or (n, 3)."""
    return np.asarray(p_B_W) + np.asarray(R_W_B) @ np.asarray(r_P_B, dtype=float) - dt_s * np.asarray(v_W)


def pixel_from_direction_C(d_C, camera_matrix, dist_coeffs) -> np.ndarray:
    """Pixel (N, 2) of points/directions d_C (N, 3) in the camera frame, OpenCV model (``cv2.projectPoints``)."""
    d = np.ascontiguousarray(np.atleast_2d(d_C), dtype=np.float64)
    uv, _ = cv2.projectPoints(d, np.zeros(3), np.zeros(3), np.asarray(camera_matrix, dtype=float),
                              np.asarray(dist_coeffs, dtype=float))
    return uv.reshape(-1, 2)


def bearing_from_pixel(uv_px, camera_matrix, dist_coeffs) -> np.ndarray:
    """Unit bearing(s) (N, 3) in the camera frame of pixel(s) (N, 2): ``cv2.undistortPoints`` then normalise."""
    uv = np.ascontiguousarray(np.atleast_2d(uv_px), dtype=np.float64).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(uv, np.asarray(camera_matrix, dtype=float), np.asarray(dist_coeffs, dtype=float),
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def attitude_from_tilt_and_beam(roll_rad: float, pitch_rad: float, beam_B, beam_W) -> np.ndarray:
    """The patent's double-vector attitude: ``R_W_B`` from the gravity direction (exact) and the beam direction.

    Roll and pitch come from the inclinometer; the beam direction known in the body (camera bearing rotated by
    ``R_B_C``) and in the world (tracker position of the target) fixes the azimuth.  Solved as Wahba's
    problem with the gravity pair as the primary (infinitely weighted) vector, i.e. TRIAD.
    """
    up_B = up_direction_B(roll_rad, pitch_rad)
    # TRIAD: the same orthonormal triad (primary, primary x secondary, their cross product) in both frames;
    # R_W_B = T_W T_B^T takes up_B onto E_Z exactly and beam_B into the plane of E_Z and beam_W
    return _triad(E_Z, np.asarray(beam_W, dtype=float)) @ _triad(up_B, np.asarray(beam_B, dtype=float)).T


def _triad(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """(3, 3) columns: unit ``primary``, unit ``primary x secondary``, their cross product."""
    t1 = primary / np.linalg.norm(primary)
    t2 = cross(t1, secondary)
    t2 = t2 / np.linalg.norm(t2)
    return np.column_stack([t1, t2, cross(t1, t2)])
