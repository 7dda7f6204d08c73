"""Ship factors.

* Tilt: the hull's up against the accelerometer's total force, corrected for the lever arm and the known hull
  acceleration (:func:`selfcal.models.ship.level_residual`).  GTSAM's ``AttitudeFactorRot3`` measures the same
  direction but cannot take the accelerometer's lever arm or the speed log's scale as unknowns; this factor can,
  and without them it is the same measurement.
* Gyro with a scale error: GTSAM's ``AHRSFactor`` between two keyframes' attitudes and the gyro bias, plus the
  gyro's per-axis scale error as a Vector3 unknown (:func:`selfcal.models.ship.scaled_gyro_rotation_residual`);
  at scale 0 it is the AHRSFactor's error.
"""
from __future__ import annotations

import gtsam
import numpy as np

from selfcal.models import ship


def tilt_factor(noise, rotation_key: int, f_S, A_S, surge_m_s2: float, vw_S, lever_arm_key: int | None = None,
                speed_scale_key: int | None = None, lever_arm_m=(0.0, 0.0, 0.0),
                speed_key: int | None = None, offset_channels=(), known_offsets=(),
                along_track_ratio: float = 0.0, scale_regressor=None) -> gtsam.CustomFactor:
    """Tilt of keyframe ``rotation_key`` (Rot3 R_W_S); optional Vector3 lever arm and Vector1 speed-log scale
    (without a lever-arm key, the known ``lever_arm_m`` is used).  The hull's known acceleration: the log's
    ``surge_m_s2`` (dv/dt) and ``vw_S`` (speed times body rate, :func:`selfcal.models.ship.hull_acceleration_W`).

    ``offset_channels`` ``(key, phi)``: a tilt offset ``k phi`` (``k`` a Vector2, rad per unit of ``phi``, this
    keyframe's value of a driver's basis function: the audit's generic terms); ``known_offsets`` ``(k, phi)`` ones
    already fitted (held-out prediction).  ``phi`` is a number, or a function of the attitude ``R_W_S -> (phi,
    dphi/dxi (3,))`` for a driver that is the attitude itself (roll, pitch, heading: the term follows the state).

    Without a speed source, ``speed_key`` (Vector1, the speed through the water in m/s) stands for the speed
    log: ``surge_m_s2`` is then 0 and ``vw_S`` the body rate (the acceleration per unit speed), and the speed is the gain
    ``1 + k`` of :func:`selfcal.models.ship.level_residual` (so its Jacobian is the one on ``k``).

    ``along_track_ratio``: the speed log rate's error along the heading over the isotropic sigma of ``noise``
    (both in rad of tilt); the residual is weighed down along the heading by it
    (:func:`selfcal.models.ship.along_track_weight`), so ``noise`` stays the cross-track sigma.

    ``scale_regressor`` ``(surge, vw_S)``: what the speed-log scale multiplies, when not the hull acceleration
    removed (a smoothed one: :func:`selfcal.models.ship.level_residual`)."""
    f_S, A_S, vw_S, known_r = (np.asarray(x, dtype=float) for x in (f_S, A_S, vw_S, lever_arm_m))
    surge_m_s2 = float(surge_m_s2)
    if speed_key is not None and speed_scale_key is not None:
        raise ValueError("a speed-log scale and an unknown speed exclude each other")
    gain_key = speed_key if speed_key is not None else speed_scale_key
    keys = [rotation_key] + [k for k in (lever_arm_key, gain_key) if k is not None]
    channels = [(key, phi if callable(phi) else float(phi)) for key, phi in offset_channels]
    keys += [key for key, _ in channels]
    known = [(np.asarray(k, dtype=float), phi) for k, phi in known_offsets]

    def error(this, values, H):
        r = values.atVector(lever_arm_key) if lever_arm_key is not None else known_r
        k = values.atVector(gain_key)[0] if gain_key is not None else 0.0
        if speed_key is not None:
            k -= 1.0  # gain (1 + k) = the speed
        R_W_S = values.atRot3(rotation_key).matrix()
        e, H_R, H_r, H_k = ship.level_residual(R_W_S, f_S, A_S, r, surge_m_s2, vw_S, k, scale_regressor)
        offset, H_offset, basis = np.zeros(2), np.zeros((2, 3)), []
        for coefficient, phi in known + [(values.atVector(key), phi) for key, phi in channels]:
            value, d_value = phi(R_W_S) if callable(phi) else (phi, np.zeros(3))
            offset += coefficient * value
            H_offset += np.outer(coefficient, d_value)
            basis.append(value)
        e = e - offset
        W, H_W = np.eye(2), np.zeros((2, 3))
        if along_track_ratio > 0.0:
            e, W, H_W = ship.along_track_weight(R_W_S, e, along_track_ratio)
        if H is not None:
            H[0] = W @ (H_R - H_offset) + H_W
            slot = 1
            if lever_arm_key is not None:
                H[slot] = W @ H_r
                slot += 1
            if gain_key is not None:
                H[slot] = W @ H_k
                slot += 1
            for j, value in enumerate(basis[len(known):]):
                H[slot + j] = -value * W
        return e

    return gtsam.CustomFactor(noise, keys, error)


def gyro_scale_rotation_factor(noise, rotation_i_key: int, rotation_j_key: int, bias_key: int, scale_key: int,
                               gyro_rad_s, dt_s, bias_hat_rad_s) -> gtsam.CustomFactor:
    """Gyro samples between keyframes i and j (Rot3 R_W_S each) with the bias (Vector3, rad/s) and the gyro's
    scale error ``s`` (Vector3, raw = (1 + s) x true).  ``noise``: the preintegrated rotation's (GTSAM's
    ``PreintegratedAhrsMeasurements.preintMeasCov()`` of the same samples, as the AHRSFactor uses)."""
    bias_hat = np.asarray(bias_hat_rad_s, dtype=float)
    delta_R, J_bias, J_correction = ship.scaled_gyro_preintegration(gyro_rad_s, dt_s, bias_hat)

    def error(this, values, H):
        e, *jacobians = ship.scaled_gyro_rotation_residual(
            values.atRot3(rotation_i_key).matrix(), values.atRot3(rotation_j_key).matrix(), delta_R, J_bias,
            J_correction, bias_hat, values.atVector(bias_key), values.atVector(scale_key))
        if H is not None:
            for slot, jacobian in enumerate(jacobians):
                H[slot] = jacobian
        return e

    return gtsam.CustomFactor(noise, [rotation_i_key, rotation_j_key, bias_key, scale_key], error)
