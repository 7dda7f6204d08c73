"""Calibration results in the files the next tools read: Kalibr's ``imu.yaml`` and imu-chain, OpenVINS's
``kalibr_imu_chain.yaml``.  The equations and their sources are in ``docs/exports.md``.

Our IMU calibration (``selfcal calibrate imu``, frame S)::

    f_S = M_a (a_raw - b_a)          w_S = M_g (w_raw - b_g - A f_S)          (M_a upper triangular)

Kalibr's ``scale-misalignment`` model (IccSensors.py, IccScaledMisalignedImu), in its IMU frame i::

    a_raw = M_acc f_i + b_a          w_raw = M_gyr C_gyro_i w_i + A_k C_gyro_i f_i + b_g

with ``M_acc``, ``M_gyr`` lower triangular (the entries Kalibr estimates) and ``C_gyro_i`` a rotation.  Both
describe the same sensor when ``f_i = C_i_S f_S``, ``w_i = C_i_S w_S`` and::

    inv(M_a) = M_acc C_i_S                       (LQ decomposition: M_acc lower, C_i_S a rotation)
    inv(M_g) C_i_S^T = M_gyr C_gyro_i            (LQ decomposition)
    A_k = A C_i_S^T C_gyro_i^T

``C_i_S`` (Kalibr's frame i against ours) goes into ``T_i_b``: our frame S plays Kalibr's body frame b.

OpenVINS (Propagator.cpp; VioManagerOptions.h reads ``Tw``, ``Ta``, ``R_IMUtoGYRO``, ``R_IMUtoACC``, ``Tg``)::

    a_I = R_ACCtoIMU Da (a_m - b_a)           w_I = R_GYROtoIMU Dw (w_m - b_g - Tg a_I)

with ``Dw = inv(Tw)``, ``Da = inv(Ta)``, ``R_XtoIMU = R_IMUtoX^T``.  Its ``kalibr`` model keeps the lower
triangles of ``Dw`` and ``Da`` and ``R_ACCtoIMU = I``; in Kalibr's frame i that is ``Ta = M_acc``, ``Tw = M_gyr``,
``R_IMUtoGYRO = C_gyro_i``, ``R_IMUtoACC = I``, ``Tg = A_k C_gyro_i = A C_i_S^T``.

Biases are in neither file: Kalibr and OpenVINS estimate them as states.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import yaml

KALIBR_NOISE_KEYS = ("accelerometer_noise_density", "accelerometer_random_walk", "gyroscope_noise_density",
                     "gyroscope_random_walk")


def lq(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``M = L Q``: L lower triangular with a positive diagonal, Q orthogonal (a rotation when det M > 0)."""
    q, r = np.linalg.qr(np.asarray(M, dtype=float).T)
    signs = np.where(np.diag(r) < 0, -1.0, 1.0)
    return (signs[:, None] * r).T, (q * signs).T


@dataclass
class KalibrIntrinsics:
    """Our IMU intrinsics in Kalibr's ``scale-misalignment`` parametrisation (module notes)."""

    M_acc: np.ndarray  # lower triangular
    M_gyr: np.ndarray  # lower triangular
    A: np.ndarray  # rad s^-1 per m s^-2, applied to the specific force in the gyro frame
    C_gyro_i: np.ndarray  # rotation, Kalibr's IMU frame i -> gyro frame
    C_i_S: np.ndarray  # rotation, our frame S -> Kalibr's IMU frame i


def kalibr_intrinsics(M_a, M_g, A) -> KalibrIntrinsics:
    """Kalibr's matrices from ours (``f_S = M_a (a_raw - b_a)``, ``w_S = M_g (w_raw - b_g - A f_S)``)."""
    M_acc, C_i_S = lq(np.linalg.inv(M_a))
    M_gyr, C_gyro_i = lq(np.linalg.inv(M_g) @ C_i_S.T)
    return KalibrIntrinsics(M_acc, M_gyr, np.asarray(A, dtype=float) @ C_i_S.T @ C_gyro_i.T, C_gyro_i, C_i_S)


def homogeneous(R, t) -> list:
    """4x4 ``[[R, t], [0, 0, 0, 1]]`` as nested lists."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return _matrix(T)


def _matrix(M) -> list:
    return (np.asarray(M, dtype=float) + 0.0).tolist()  # + 0.0: no "-0.0" in the files


def _noise_keys(meta: dict) -> dict:
    """Kalibr's noise keys, as far as a sensor.yaml declares them."""
    return {k: float(meta[k]) for k in KALIBR_NOISE_KEYS if k in meta}


def kalibr_imu_entry(meta: dict, rostopic: str, rate_hz: float, T_i_b=None, time_offset_s: float = 0.0,
                     intrinsics: KalibrIntrinsics | None = None) -> dict:
    """One IMU of a Kalibr imu-chain (``ImuSetParameters``: ``imu0``, ``imu1`` ...).

    ``model: calibrated`` without ``intrinsics``, else ``scale-misalignment`` with ``accelerometers: {M}`` and
    ``gyroscopes: {M, A, C_gyro_i}``.  ``T_i_b`` defaults to the identity.
    """
    entry = {"T_i_b": T_i_b if T_i_b is not None else homogeneous(np.eye(3), np.zeros(3)),
             **_noise_keys(meta), "model": "calibrated", "rostopic": rostopic,
             "time_offset": float(time_offset_s), "update_rate": float(rate_hz)}
    if intrinsics is not None:
        entry["model"] = "scale-misalignment"
        entry["accelerometers"] = {"M": _matrix(intrinsics.M_acc)}
        entry["gyroscopes"] = {"M": _matrix(intrinsics.M_gyr), "A": _matrix(intrinsics.A),
                               "C_gyro_i": _matrix(intrinsics.C_gyro_i)}
    return entry


def openvins_imu_entry(meta: dict, rostopic: str, rate_hz: float, intrinsics: KalibrIntrinsics) -> dict:
    """``imu0`` of OpenVINS's ``kalibr_imu_chain.yaml`` (model ``kalibr``; module notes)."""
    return {"T_i_b": homogeneous(intrinsics.C_i_S, np.zeros(3)), **_noise_keys(meta), "rostopic": rostopic,
            "time_offset": 0.0, "update_rate": float(rate_hz), "model": "kalibr",
            "Tw": _matrix(intrinsics.M_gyr), "R_IMUtoGYRO": _matrix(intrinsics.C_gyro_i),
            "Ta": _matrix(intrinsics.M_acc), "R_IMUtoACC": _matrix(np.eye(3)),
            "Tg": _matrix(intrinsics.A @ intrinsics.C_gyro_i)}


def kalibr_pair_T_i_b(R_imu0_imu1, lever_arm_m) -> list:
    """imu1's ``T_i_b`` as Kalibr writes it (IccImu.updateImuConfig): rotation ``C_i_b`` (imu0 -> imu1 vectors,
    ``R_imu0_imu1^T``), translation ``r_b``, imu1's position in the imu0 frame (our lever arm) as is."""
    lever = np.zeros(3) if lever_arm_m is None else np.asarray(lever_arm_m, dtype=float)
    return homogeneous(np.asarray(R_imu0_imu1, dtype=float).T, lever)


@dataclass
class NoiseValue:
    """One key of Kalibr's imu.yaml: its value and a comment saying where it comes from."""

    value: float
    comment: str


def kalibr_imu_yaml_text(rostopic: str, rate_hz: float, noise: dict[str, NoiseValue], header: str = "") -> str:
    """Kalibr's ``imu.yaml`` (keys and layout of Kalibr's example file), one comment per value."""
    lines = [f"# {line}" for line in header.splitlines()]
    for key in KALIBR_NOISE_KEYS:
        v = noise[key]
        lines.append(f"{key}: {v.value:.6e}  # {v.comment}")
    lines += [f"rostopic: {yaml.safe_dump(rostopic, default_style=None).splitlines()[0]}",
              f"update_rate: {float(rate_hz):.6g}  # Hz"]
    return "\n".join(lines) + "\n"


def yaml_text(data: dict, header: str = "") -> str:
    """YAML of ``data`` in Kalibr's flow style for matrices, after ``header`` as comment lines."""
    comments = "".join(f"# {line}\n" for line in header.splitlines())
    return comments + yaml.safe_dump(data, sort_keys=False, default_flow_style=None)
