"""GTSAM factors of the laser-tracker target (patent 004): GTSAM's own where it has them, two custom ones.

Variables: ``X`` (Pose3 ``world_T_body``, body = IMU), ``V`` (velocity, world frame, m/s), ``B``
(``imuBias.ConstantBias``), as GTSAM's navigation examples.

=========================  ===============================================  ==========================
measurement                factor                                           error
=========================  ===============================================  ==========================
IMU between keyframes      ``gtsam.CombinedImuFactor``                      GTSAM's (15)
prism position (tracker)   ``gtsam.GPSFactorArm`` (lever arm r_P_B)          ``p + R r - z`` (m, 3)
inclinometer               ``gtsam.AttitudeFactorPose3``                    Unit3 error of up (rad, 2)
prism velocity (tracker)   :func:`prism_velocity_factor` (custom)           ``v + R (w x r) - z`` (m/s, 3)
beam spot (camera)         :func:`beam_bearing_factor` (custom)             bearing error (rad, 2)
=========================  ===============================================  ==========================

The custom factors return the unwhitened error, fill right-perturbation Jacobians only when ``H`` is given,
and call :mod:`selfcal.models.tracker` for the physics.
"""
from __future__ import annotations

import gtsam
import numpy as np

from selfcal.models import tracker as mt

UP_W = gtsam.Unit3(np.array([0.0, 0.0, 1.0]))


def prism_position_factor(noise, pose_key: int, p_P_W, r_P_B) -> gtsam.NonlinearFactor:
    """Tracker position of the prism at lever arm ``r_P_B``: GTSAM's ``GPSFactorArm`` (``p + R r - z``)."""
    return gtsam.GPSFactorArm(pose_key, np.asarray(p_P_W, dtype=float), np.asarray(r_P_B, dtype=float), noise)


def inclinometer_factor(noise, pose_key: int, up_B) -> gtsam.NonlinearFactor:
    """Inclinometer: the measured up direction in the body frame against the world's up (``AttitudeFactorPose3``)."""
    return gtsam.AttitudeFactorPose3(pose_key, UP_W, noise, gtsam.Unit3(np.asarray(up_B, dtype=float)))


def prism_velocity_factor(noise, pose_key: int, velocity_key: int, v_P_W, w_B, r_P_B) -> gtsam.CustomFactor:
    """Tracker velocity of the prism: ``e = v_B + R (w x r) - v_P`` (m/s, world frame).

    ``w_B`` is the body rate at the sample (bias-corrected gyro), taken as known: its noise enters through the
    noise model, not as a variable.
    """
    z = np.asarray(v_P_W, dtype=float)
    w, r = np.asarray(w_B, dtype=float), np.asarray(r_P_B, dtype=float)

    def error(this, values, H):
        R = values.atPose3(pose_key).rotation().matrix()
        v = values.atVector(velocity_key)
        e = mt.prism_velocity_W(R, v, w, r) - z
        if H is not None:
            H[0], H[1] = mt.prism_velocity_jacobians(R, w, r)
        return e

    return gtsam.CustomFactor(noise, [pose_key, velocity_key], error)


def beam_bearing_factor(noise, pose_key: int, bearing_C, r_C_B, R_B_C, tracker_W=np.zeros(3)) -> gtsam.CustomFactor:
    """Beam-spot camera: the measured unit bearing of the tracker (camera frame) against the pose's prediction.

    ``e = basis(b_meas)^T normalise(R_B_C^T (R^T (t_W - p) - r_C_B))`` (rad, 2): zero when the predicted bearing
    equals the measured one.  The pixel is turned into ``bearing_C`` once, outside (``cv2.undistortPoints``).
    """
    b = np.asarray(bearing_C, dtype=float)
    basis = gtsam.Unit3(b).basis()
    r, R_BC, t_W = np.asarray(r_C_B, dtype=float), np.asarray(R_B_C, dtype=float), np.asarray(tracker_W, dtype=float)

    def error(this, values, H):
        pose = values.atPose3(pose_key)
        if H is None:
            return mt.beam_bearing_residual(pose.rotation().matrix(), pose.translation(), r, R_BC, b, basis, t_W)
        e, J = mt.beam_bearing_residual(pose.rotation().matrix(), pose.translation(), r, R_BC, b, basis, t_W,
                                        with_jacobian=True)
        H[0] = J
        return e

    return gtsam.CustomFactor(noise, [pose_key], error)
