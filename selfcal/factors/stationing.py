"""Stationing factors: one factor per station block (all its waypoints), around :mod:`selfcal.models.stationing`.

Keys: station / base pose ``Pose3 W_T_S``; per-waypoint column tilt ``Vector2`` (rad); prism lever arm
``Point3 tool_t_prism``; pivot fraction ``Vector1``; accelerometer mounting ``Rot3 T_R_A``.  A block without
tilt keys is a rigid body (tilt zero): the base accelerometer, or the tilt-free baseline model.

``corrections`` (the audit's generic terms): a list of ``(key, M)`` with a ``Vector3`` key ``c`` and ``M``
(N, 3, 3); the prediction of waypoint ``i`` gains ``M[i] c`` (a correction whose shape in the driver is in
``M``, its size in ``c``).

GTSAM's ``Rot3AttitudeFactor`` measures the same direction but takes the sensor's mounting as a known constant,
and ``GPSFactorArm`` a known lever arm on a pose with no bend; here both are unknowns shared by every station.
"""
from __future__ import annotations

import gtsam
import numpy as np

from selfcal.models import stationing


def _add_corrections(values, corrections, predicted, H, slot) -> np.ndarray:
    """``predicted`` (N, 3) plus each correction ``M c``; its Jacobians into ``H[slot:]``."""
    for j, (key, M) in enumerate(corrections):
        predicted = predicted + np.einsum("nij,j->ni", M, values.atVector(key))
        if H is not None:
            H[slot + j] = M.reshape(-1, 3)
    return predicted


def prism_block_factor(noise, station_key: int, tilt_keys: list[int] | None, prism_key: int,
                       pivot_key: int | None, R_T_tool, t_T_tool, column_height_m, prism_W,
                       corrections=()) -> gtsam.CustomFactor:
    """Total-station prism positions (N, 3) of one station's waypoints; error ``predicted - measured`` (3N)."""
    R_T_tool, t_T_tool = np.asarray(R_T_tool, float), np.asarray(t_T_tool, float)
    h, prism_W = np.asarray(column_height_m, float), np.asarray(prism_W, float)
    n = len(h)
    rigid = tilt_keys is None
    corrections = [(k, np.asarray(M, float)) for k, M in corrections]
    keys = [station_key] + ([] if rigid else list(tilt_keys)) + [prism_key] + \
        ([pivot_key] if pivot_key is not None and not rigid else []) + [k for k, _ in corrections]

    def error(this, values, H):
        pose = values.atPose3(station_key)
        tilt = np.zeros((n, 2)) if rigid else np.array([values.atVector(k) for k in tilt_keys])
        lam = values.atVector(pivot_key)[0] if pivot_key is not None and not rigid else 0.0
        p_W, H_pose, H_tilt, H_prism, H_pivot = stationing.prism_position_W(
            pose.rotation().matrix(), pose.translation(), tilt, R_T_tool, t_T_tool,
            values.atPoint3(prism_key), h, lam)
        slot = 1 if rigid else 1 + n
        if H is not None:
            H[0] = H_pose.reshape(3 * n, 6)
            if not rigid:
                for i in range(n):  # waypoint i's tilt moves only its own 3 rows
                    block = np.zeros((3 * n, 2))
                    block[3 * i:3 * i + 3] = H_tilt[i]
                    H[1 + i] = block
            H[slot] = H_prism.reshape(3 * n, 3)
            if pivot_key is not None and not rigid:
                H[slot + 1] = H_pivot.reshape(3 * n, 1)
        slot += 1 + (pivot_key is not None and not rigid)
        p_W = _add_corrections(values, corrections, p_W, H, slot)
        return (p_W - prism_W).ravel()

    return gtsam.CustomFactor(noise, keys, error)


def accel_block_factor(noise, pose_key: int, tilt_keys: list[int] | None, mount_key: int,
                       accel_A, corrections=()) -> gtsam.CustomFactor:
    """Static accelerometer readings (N, 3) on the body of ``pose_key``; error ``predicted - measured`` (3N)."""
    accel_A = np.asarray(accel_A, float)
    n = len(accel_A)
    magnitude = np.linalg.norm(accel_A, axis=1)
    rigid = tilt_keys is None
    corrections = [(k, np.asarray(M, float)) for k, M in corrections]
    keys = [pose_key] + ([] if rigid else list(tilt_keys)) + [mount_key] + [k for k, _ in corrections]

    def error(this, values, H):
        R = values.atPose3(pose_key).rotation().matrix()
        tilt = np.zeros((n, 2)) if rigid else np.array([values.atVector(k) for k in tilt_keys])
        f_A, H_rot, H_tilt, H_mount = stationing.specific_force_A(R, tilt, values.atRot3(mount_key).matrix(),
                                                                  magnitude)
        slot = 1 if rigid else 1 + n
        if H is not None:
            H[0] = np.concatenate([H_rot.reshape(3 * n, 3), np.zeros((3 * n, 3))], axis=1)
            if not rigid:
                for i in range(n):
                    block = np.zeros((3 * n, 2))
                    block[3 * i:3 * i + 3] = H_tilt[i]
                    H[1 + i] = block
            H[slot] = H_mount.reshape(3 * n, 3)
        f_A = _add_corrections(values, corrections, f_A, H, slot + 1)
        return (f_A - accel_A).ravel()

    return gtsam.CustomFactor(noise, keys, error)
