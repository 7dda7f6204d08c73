"""IMU measurement model: specific force and angular rate as a MEMS/FOG triad reports them.

Frames: ``S`` is the sensor (body) frame of one IMU, ``W`` a local-level world frame with z up.
Units: specific force in m s^-2, angular rate in rad s^-1, temperature in degC, time in s.

Measurement equations (raw means "as the sensor reports, in nominal SI units")::

    a_raw = inv(M_a) f_S + b_a + k_a (T - T_ref) + n_a
    w_raw = inv(M_g) w_S + b_g + A f_S + k_g (T - T_ref) + n_g

and the calibration inverts them (the YAML contract of ``selfcal calibrate imu``)::

    f_S = M_a (a_raw - b_a(T))            w_S = M_g (w_raw - b_g(T) - A f_S)

``M = T K``: ``K`` holds the per-axis gains, ``T`` the non-orthogonality.  For the accelerometer the body
frame is *defined* by the triad (x along the accelerometer x axis, y in its xy plane), so ``M_a`` is upper
triangular (6 parameters); the gyro ``M_g`` is a full 3x3 (scale, misalignment and its rotation relative to
the accelerometer frame, 9 parameters).  ``A`` is the gyro g-sensitivity (rad s^-1 per m s^-2).

Two rigidly mounted IMUs (``imu0``, ``imu1``): ``v_imu0 = R_imu0_imu1 v_imu1``; ``imu1`` sits at ``r_m``
(imu0 frame) from ``imu0``; clocks obey ``t_imu0 = t_imu1 + dt_s``.  Rigid-body kinematics give the
specific force at imu1, expressed in the imu0 frame::

    f_1 = f_0 + dw/dt x r + w x (w x r)                 (w, dw/dt of the body, imu0 frame)

References
----------
D. Tedaldi, A. Pretto, E. Menegatti, "A robust and easy to implement method for IMU calibration without
external equipments", ICRA 2014 (the M = T K model and the multi-position protocol).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from selfcal.core import so3

def upper_triangular(m6: np.ndarray) -> np.ndarray:
    """3x3 upper-triangular matrix from its 6 entries (m00, m01, m02, m11, m12, m22)."""
    m = np.asarray(m6, dtype=float)
    return np.array([[m[0], m[1], m[2]], [0.0, m[3], m[4]], [0.0, 0.0, m[5]]])


UPPER_TRIANGULAR_INDEX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def upper_triangular_entries(M: np.ndarray) -> np.ndarray:
    """Inverse of :func:`upper_triangular`."""
    return np.array([M[i, j] for i, j in UPPER_TRIANGULAR_INDEX])


def scale_and_misalignment(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split ``M = T K`` (K diagonal, T unit upper-triangular part) into per-axis scale error and angles.

    Returns ``scale`` with ``a_raw_i = (1 + scale_i) f_i`` along each sensing axis (0 = nominal gain) and
    the three non-orthogonality ``angles`` (rad) of Tedaldi's T = [[1, -a_yz, a_zy], [0, 1, -a_zx], [0, 0, 1]],
    read from the columns of ``M diag(M)^-1``.  Below-diagonal terms of a full gyro M are not angles of this
    parametrisation and are ignored here (they remain in M).
    """
    K = np.diag(M).copy()
    T = M / K[None, :]
    return 1.0 / K - 1.0, np.array([-T[0, 1], T[0, 2], -T[1, 2]])


class _TemperatureBias:
    """``bias(T) = bias + temperature_slope (T - T_ref)``, shared by both triads."""

    def bias_at(self, temperature_degC=None) -> np.ndarray:
        """Bias (3,) without a temperature, else (N, 3) for temperatures (N,) in degC."""
        if temperature_degC is None:
            return self.bias
        dT = np.asarray(temperature_degC, dtype=float) - self.temperature_ref_degC
        return self.bias + np.multiply.outer(dT, self.temperature_slope)


@dataclass
class AccelIntrinsics(_TemperatureBias):
    """Accelerometer triad intrinsics: ``f_S = M (a_raw - bias - temperature_slope (T - T_ref))``."""

    M: np.ndarray = field(default_factory=lambda: np.eye(3))
    bias: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m s^-2
    temperature_slope: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m s^-2 per degC
    temperature_ref_degC: float = 25.0

    def raw_from_specific_force(self, f_S: np.ndarray, temperature_degC=None) -> np.ndarray:
        """Noise-free raw accelerometer output (N, 3) for true specific force f_S (N, 3)."""
        return np.asarray(f_S) @ np.linalg.inv(self.M).T + self.bias_at(temperature_degC)

    def specific_force(self, a_raw: np.ndarray, temperature_degC=None) -> np.ndarray:
        """Calibrated specific force f_S (N, 3) from raw output."""
        return (np.asarray(a_raw) - self.bias_at(temperature_degC)) @ self.M.T


@dataclass
class GyroIntrinsics(_TemperatureBias):
    """Gyro triad intrinsics: ``w_S = M (w_raw - bias - A f_S - temperature_slope (T - T_ref))``."""

    M: np.ndarray = field(default_factory=lambda: np.eye(3))
    bias: np.ndarray = field(default_factory=lambda: np.zeros(3))  # rad s^-1
    A: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # rad s^-1 per m s^-2
    temperature_slope: np.ndarray = field(default_factory=lambda: np.zeros(3))  # rad s^-1 per degC
    temperature_ref_degC: float = 25.0

    def raw_from_rate(self, w_S: np.ndarray, f_S: np.ndarray, temperature_degC=None) -> np.ndarray:
        """Noise-free raw gyro output (N, 3) for true rate w_S and true specific force f_S (N, 3)."""
        return (np.asarray(w_S) @ np.linalg.inv(self.M).T + np.asarray(f_S) @ self.A.T
                + self.bias_at(temperature_degC))

    def rate(self, w_raw: np.ndarray, f_S: np.ndarray, temperature_degC=None) -> np.ndarray:
        """Calibrated angular rate w_S (N, 3) from raw output and the (calibrated) specific force."""
        return (np.asarray(w_raw) - self.bias_at(temperature_degC) - np.asarray(f_S) @ self.A.T) @ self.M.T


def gyro_rates_and_jacobians(w_raw, f_S, gyro: GyroIntrinsics, bias_offset=None):
    """Calibrated rates (N, 3) and their derivatives w.r.t. bias (3), M (9 row-major) and A (9 row-major).

    ``w = M u``, ``u = w_raw - b - db - A f``:  dw/db = -M, dw/dM_jk = e_j u_k, dw/dA_jk = -M e_j f_k.
    ``bias_offset`` (N, 3) is an extra, per-sample bias (e.g. slope x channel deviation).
    """
    u = np.asarray(w_raw) - gyro.bias - np.asarray(f_S) @ gyro.A.T
    if bias_offset is not None:
        u = u - bias_offset
    w = u @ gyro.M.T
    n = len(u)
    d_bias = np.broadcast_to(-gyro.M, (n, 3, 3))
    d_M = np.einsum("aj,nk->najk", np.eye(3), u).reshape(n, 3, 9)
    d_A = -np.einsum("aj,nk->najk", gyro.M, np.asarray(f_S)).reshape(n, 3, 9)
    return w, d_bias, d_M, d_A


def relative_rotation_and_jacobians(w_raw, f_S, dt_s, gyro: GyroIntrinsics, channels=None):
    """Rotation body(start) <- body(end) integrated from raw gyro samples, with right-Jacobians.

    ``channels`` maps a name to ``(slope (3,), deviation (N,))``: the gyro bias is ``b + slope * deviation``
    sample by sample.  Returns ``delta_R`` and a dict of Jacobians ``J`` (3 x block size) for the blocks
    ``bias``, ``M``, ``A`` and each channel name, with ``delta_R(theta + d) = delta_R Exp(J d)``.
    """
    channels = channels or {}
    offset = sum((np.outer(dev, slope) for slope, dev in channels.values()), np.zeros((len(w_raw), 3)))
    w, d_bias, d_M, d_A = gyro_rates_and_jacobians(w_raw, f_S, gyro, offset)
    delta_R, J = so3.integrate_rates(w, dt_s, with_jacobians=True)
    J_flat = J.transpose(1, 0, 2).reshape(3, -1)  # sum_i J_i D_i as one matmul: [J_1 ... J_n] [D_1; ...; D_n]
    out = {name: J_flat @ np.ascontiguousarray(D).reshape(-1, D.shape[-1])
           for name, D in (("bias", d_bias), ("M", d_M), ("A", d_A))}
    for name, (_, dev) in channels.items():  # per-sample bias slope x deviation: sum_i J_i (-M) dev_i
        out[name] = np.tensordot(dev, J, axes=(0, 0)) @ (-gyro.M)
    return delta_R, out


def white_noise_sigma_of_mean(noise_density: float, rate_hz: float, n_samples: int) -> float:
    """1-sigma of the mean of n samples of white noise with density ``noise_density`` (unit/sqrt(Hz)).

    One sample has sigma = density * sqrt(rate); the mean of n independent samples divides by sqrt(n).
    """
    return noise_density * np.sqrt(rate_hz) / np.sqrt(n_samples)
