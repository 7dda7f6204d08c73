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

The audit (:mod:`selfcal.audit.tracker`) rebuilds the tracker and inclinometer factors with calibration
effects as variables: :func:`calibrated_prism_factor` (lever-arm correction, clock offset; one block of samples
per keyframe), :func:`calibrated_prism_velocity_factor` (clock offset), :func:`calibrated_inclinometer_factor`
(bias, scale, acceleration sensitivity, in roll/pitch).

The custom factors return the unwhitened error, fill right-perturbation Jacobians only when ``H`` is given,
and call :mod:`selfcal.models.tracker` for the physics.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from selfcal.core import so3
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
    # w and r are constants of the factor: w x r and its model Jacobian once, not at every linearisation
    w_x_r = mt.cross(w, r)
    H_pose_B, H_velocity = mt.prism_velocity_jacobians(np.eye(3), w, r)  # (3, 6) at R = I; then R times it

    def error(this, values, H):
        R = values.atPose3(pose_key).rotation().matrix()
        e = values.atVector(velocity_key) + R @ w_x_r - z  # mt.prism_velocity_W(R, v, w, r) - z
        if H is not None:
            H[0], H[1] = R @ H_pose_B, H_velocity  # mt.prism_velocity_jacobians(R, w, r)
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


def calibrated_prism_factor(noise, pose_key: int, p_P_W, r_P_B, v_W, lever_key: int | None = None,
                            offset_key: int | None = None, lever_fixed=np.zeros(3), offset_fixed: float = 0.0,
                            start_velocity_key: int | None = None, lead_s=None, v_start=None,
                            velocity_keys: tuple[int, int] | None = None,
                            velocity_fraction=None, term_columns=()) -> gtsam.CustomFactor:
    """Tracker positions with the audit's calibration effects: ``e_i = p + R (r + dr) - dt v_i - z_i`` (m, world).

    ``p_P_W`` (n, 3): the n samples of one keyframe, each moved to the keyframe's time (one factor per block);
    ``v_W`` (n, 3) the target's velocity at each sample.  ``dr`` (m, body; variable ``lever_key`` or the
    constant ``lever_fixed``) corrects the nominal prism lever arm ``r_P_B``; ``dt`` (s; variable ``offset_key``
    or ``offset_fixed``) is the tracker's clock offset (``t_tracker = t_imu + dt``: a sample shows the prism
    ``dt`` earlier).  With ``start_velocity_key`` the move to the keyframe is redone with that velocity variable
    (the previous keyframe's, where the IMU propagation started) instead of ``v_start`` (the one used):
    ``z_i + lead_i (V - v_start)``, ``lead_i`` (s) = keyframe time - sample time.
    With ``velocity_keys = (V_prev, V_k)`` (the velocity variables of the previous keyframe and this one) the
    offset's regressor is the state velocity interpolated at each sample, ``v_i = (1 - f_i) V_prev + f_i V_k +
    v_W_i`` (``f_i``: ``velocity_fraction``, 0 at the previous keyframe, 1 at this one; ``v_W`` then holds only
    the known remainder, e.g. the lever arm's rotation velocity ``R (w x r)``), instead of a measured velocity: a
    noisy regressor (the tracker's own velocity, 2 mm/s per sample, against a within-block change of a few
    mm/s) attenuates the offset towards 0 (errors in variables).  Keys: the pose, then the lever arm, the offset,
    the start velocity, then those of ``velocity_keys`` not already there, then the terms'.  Error (3 n,).

    ``term_columns``: the audit's generic terms, ``[(key, G)]`` with ``G`` (3 n, q) the known columns of a
    correction linear in the key's q coefficients (a range error ``k phi(range)`` along each sample's line of
    sight): ``e += G c``.
    """
    z, r0, v = np.atleast_2d(p_P_W).astype(float), np.asarray(r_P_B, dtype=float), np.atleast_2d(v_W).astype(float)
    n = len(z)
    keys = [pose_key] + [key for key in (lever_key, offset_key, start_velocity_key) if key is not None]
    if velocity_keys is not None:
        keys += [key for key in velocity_keys if key not in keys]
    terms = [(key, np.asarray(G, dtype=float).reshape(3 * n, -1)) for key, G in term_columns]
    keys += [key for key, _ in terms]
    lead = np.zeros(n) if lead_s is None else np.asarray(lead_s, dtype=float)
    v0 = np.zeros(3) if v_start is None else np.asarray(v_start, dtype=float)
    frac = None if velocity_keys is None else np.broadcast_to(np.asarray(velocity_fraction, dtype=float), (n,))
    # the constant parts of the Jacobian blocks, built once (the audit linearises each block many times)
    lead_block = -np.kron(lead[:, None], np.eye(3))
    weight_blocks = None if frac is None else [np.kron(w[:, None], np.eye(3)) for w in (1.0 - frac, frac)]

    def error(this, values, H):
        pose = values.atPose3(pose_key)
        R = pose.rotation().matrix()
        dr = values.atVector(lever_key) if lever_key is not None else np.asarray(lever_fixed, dtype=float)
        dt = float(values.atVector(offset_key)[0]) if offset_key is not None else float(offset_fixed)
        r = r0 + dr
        moved = z if start_velocity_key is None else z + np.outer(lead, values.atVector(start_velocity_key) - v0)
        vi = v
        if velocity_keys is not None:  # the state velocity interpolated at each sample, plus the known remainder
            vi = np.outer(1.0 - frac, values.atVector(velocity_keys[0])) + np.outer(frac, values.atVector(
                velocity_keys[1])) + v
        e = (mt.prism_position_delayed(R, pose.translation(), r, vi, dt) - moved).ravel()
        for key, G in terms:
            e = e + G @ values.atVector(key)
        if H is not None:
            blocks = {pose_key: np.tile(np.hstack([-R @ so3.hat(r), R]), (n, 1))}
            if lever_key is not None:
                blocks[lever_key] = np.tile(R, (n, 1))
            if offset_key is not None:
                blocks[offset_key] = -np.broadcast_to(vi, (n, 3)).reshape(-1, 1)
            if start_velocity_key is not None:
                blocks[start_velocity_key] = lead_block
            if velocity_keys is not None:  # one key may also be the start velocity: the blocks add up
                for key, weight in zip(velocity_keys, weight_blocks):
                    block = -dt * weight
                    blocks[key] = blocks[key] + block if key in blocks else block
            blocks.update(terms)
            for i, key in enumerate(keys):
                H[i] = blocks[key]
        return e

    return gtsam.CustomFactor(noise, keys, error)


def calibrated_prism_velocity_factor(noise, pose_key: int, velocity_key: int, v_P_W, w_B, r_P_B, a_W,
                                     offset_key: int | None = None, offset_fixed: float = 0.0,
                                     previous_velocity_key: int | None = None, fraction: float = 1.0,
                                     span_s: float | None = None, lever_key: int | None = None,
                                     lever_fixed=(0.0, 0.0, 0.0)) -> gtsam.CustomFactor:
    """Tracker velocity with the audit's clock offset and lever arm: ``e = v + R (w x (r + dr)) - dt a - z``
    (m/s, world).

    A tracker stamping ``dt`` late reports the velocity of ``dt`` earlier, ``v - dt a`` (``a_W``: the target's
    acceleration over the keyframe interval, from the IMU, known).  A prism displaced by ``dr`` from sensor.yaml's
    lever arm moves with the rotation by ``R (w x dr)`` more (``lever_key``, or ``lever_fixed`` known): without it
    a wrong lever arm left its rotation velocity in these factors, where an attitude offset could take it (a 3 cm
    height error was named as a 1 mrad inclinometer bias).  Keys: pose, velocity, the lever arm, the offset.

    With ``previous_velocity_key`` (the previous keyframe's velocity variable, ``span_s`` before) ``v`` is the
    state velocity interpolated at the samples' mean position ``fraction`` in the interval, ``(1 - f) V_prev +
    f V``, and ``a = (V - V_prev) / span_s``; ``z`` is then the samples' mean minus what the IMU adds to a linear
    change over the interval (the Brownian bridge of its noise: uncorrelated with the IMU factor's own
    velocity increment, where samples moved to the keyframe with the IMU share its noise).  Keys: pose,
    velocity, the lever arm, the offset, then the previous velocity.
    """
    z, w, r0, a = (np.asarray(x, dtype=float) for x in (v_P_W, w_B, r_P_B, a_W))
    keys = [pose_key, velocity_key] + [key for key in (lever_key, offset_key, previous_velocity_key)
                                       if key is not None]
    f = float(fraction)

    def error(this, values, H):
        R = values.atPose3(pose_key).rotation().matrix()
        dr = values.atVector(lever_key) if lever_key is not None else np.asarray(lever_fixed, dtype=float)
        dt = float(values.atVector(offset_key)[0]) if offset_key is not None else float(offset_fixed)
        r = r0 + dr
        v = values.atVector(velocity_key)
        acc = a
        if previous_velocity_key is not None:
            v_prev = values.atVector(previous_velocity_key)
            acc = (v - v_prev) / span_s
            v = (1.0 - f) * v_prev + f * v
        e = mt.prism_velocity_W(R, v, w, r) - dt * acc - z
        if H is not None:
            H_pose, H_v = mt.prism_velocity_jacobians(R, w, r)
            blocks = {pose_key: H_pose, velocity_key: H_v}
            if previous_velocity_key is not None:
                blocks[velocity_key] = (f - dt / span_s) * H_v
                blocks[previous_velocity_key] = (1.0 - f + dt / span_s) * np.eye(3)
            if lever_key is not None:  # d(R (w x dr)) / d dr = R [w]x
                blocks[lever_key] = R @ so3.hat(w)
            if offset_key is not None:
                blocks[offset_key] = -acc[:, None]
            for i, key in enumerate(keys):
                H[i] = blocks[key]
        return e

    return gtsam.CustomFactor(noise, keys, error)


@dataclass(frozen=True)
class AccelerometerTilt:
    """What the inclinometer factor needs to predict the vibration disturbance from the states
    (:func:`selfcal.models.tracker.vibration_disturbance`): the accelerometer's mean raw specific force ``f_B``
    (m/s^2) over the inclinometer's window, ``turn_B`` (3, 3) turning it to the keyframe, the Wiener ``weight``
    and the keyframe's IMU bias variable (ConstantBias: accelerometer part used)."""

    f_B: np.ndarray
    turn_B: np.ndarray
    weight: float
    bias_key: int


def calibrated_inclinometer_factor(noise, pose_key: int, z_rad, disturbance_rad, effect_keys: dict,
                                   fixed: dict, term_columns=(), vibration: AccelerometerTilt | None = None
                                   ) -> gtsam.CustomFactor:
    """Inclinometer reading ``z = (roll, pitch)`` (rad) with the audit's calibration effects
    (:func:`selfcal.models.tracker.inclinometer_reading`): ``e = pred - z``.

    The disturbance is ``disturbance_rad`` (known) plus, with ``vibration``, the one the accelerometer predicts at
    the pose's attitude and the IMU bias variable (then a key after the pose's).  ``effect_keys`` maps 'bias'
    (2), 'scale' (1), 'accel_sensitivity' (1) to variable keys; an effect without a key takes its constant from
    ``fixed`` (0 when absent).  Keys: the pose, the IMU bias (with ``vibration``), the effects in that order, then
    the terms'.  ``term_columns``: the audit's generic terms, ``[(key, G)]`` with ``G`` (2, q) known (a reading
    error ``k phi(yaw)`` in roll and pitch: ``G = phi I``): ``e += G c``.
    """
    z, d0 = np.asarray(z_rad, dtype=float), np.asarray(disturbance_rad, dtype=float)
    names = [name for name in ("bias", "scale", "accel_sensitivity") if effect_keys.get(name) is not None]
    terms = [(key, np.asarray(G, dtype=float).reshape(2, -1)) for key, G in term_columns]
    state_keys = [pose_key] + ([vibration.bias_key] if vibration is not None else [])
    keys = state_keys + [effect_keys[name] for name in names] + [key for key, _ in terms]
    const = {"bias": np.asarray(fixed.get("bias", np.zeros(2)), dtype=float),
             "scale": float(fixed.get("scale", 0.0)), "accel_sensitivity": float(fixed.get("accel_sensitivity", 0.0))}

    def error(this, values, H):
        R = values.atPose3(pose_key).rotation().matrix()
        p = dict(const)
        for name in names:
            v = values.atVector(effect_keys[name])
            p[name] = v if name == "bias" else float(v[0])
        d, J_d = d0, None
        if vibration is not None:
            accel_bias = values.atConstantBias(vibration.bias_key).accelerometer()
            d_vib, J_d = mt.vibration_disturbance(R, vibration.f_B, vibration.turn_B, accel_bias, vibration.weight,
                                                  with_jacobian=True)
            d = d0 + d_vib
        pred, J = mt.inclinometer_reading(R, d, p["bias"], p["scale"], p["accel_sensitivity"], with_jacobian=True)
        if H is not None:
            H_rotation = J["rotation"]
            if J_d is not None:
                H_rotation = H_rotation + J["disturbance"] @ J_d["rotation"]
                H[1] = np.hstack([J["disturbance"] @ J_d["accel_bias"], np.zeros((2, 3))])
            H[0] = np.hstack([H_rotation, np.zeros((2, 3))])
            for i, name in enumerate(names, start=len(state_keys)):
                H[i] = J[name]
            for i, (_, G) in enumerate(terms, start=len(state_keys) + len(names)):
                H[i] = G
        return pred - z + sum((G @ values.atVector(key) for key, G in terms), np.zeros(2))

    return gtsam.CustomFactor(noise, keys, error)
