"""GTSAM factors for IMU intrinsics and inter-IMU calibration: thin adapters around :mod:`selfcal.models.imu`.

Each factor reads its variables from ``Values``, calls the model, and fills right-perturbation Jacobians
(``x . Exp(xi)`` for Rot3, ``Unit3.retract`` for directions, plain addition for vectors).  Intrinsic blocks that
are not estimated are passed as fixed values, so one factor serves every model variant the audit tries.

Variable kinds (``gtsam.Values`` types):
  ``Unit3``   up-direction of a static pose in the sensor frame (specific force at rest is ``g u``)
  ``Rot3``    ``R_imu0_imu1`` (v_imu0 = R v_imu1)
  vectors     accel bias (3), accel M upper-triangular entries (6), gyro bias (3), gyro M (9), gyro A (9),
              time offset dt (1), lever arm r (3), relative biases (3)
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.interpolate import CubicSpline

from selfcal.core import inertial
from selfcal.models import imu
from selfcal.core import so3


ALL_ACCEL_M = tuple(range(6))
ALL_GYRO_M = tuple(range(9))


@dataclass(frozen=True)
class AccelKeys:
    """Keys of the estimated accelerometer blocks; ``None`` means held at the nominal value.

    ``M_free`` selects which of the 6 upper-triangular entries the ``M`` variable holds (diagonal = scale,
    off-diagonal = misalignment); ``channels`` are ``(channel name, key of a 3-vector slope)``: the bias is
    ``b + slope * (channel - channel reference)``.
    """

    bias: int | None = None
    M: int | None = None
    M_free: tuple[int, ...] = ALL_ACCEL_M
    channels: tuple[tuple[str, int], ...] = ()


@dataclass(frozen=True)
class GyroKeys:
    """As :class:`AccelKeys`; ``M_free`` indexes the 9 row-major entries of the full gyro M; ``A`` is 9 entries."""

    bias: int | None = None
    M: int | None = None
    M_free: tuple[int, ...] = ALL_GYRO_M
    A: int | None = None
    channels: tuple[tuple[str, int], ...] = ()


def accel_from_values(values, keys: AccelKeys, nominal: imu.AccelIntrinsics) -> imu.AccelIntrinsics:
    m6 = imu.upper_triangular_entries(nominal.M)
    if keys.M is not None:
        m6[list(keys.M_free)] = values.atVector(keys.M)
    return imu.AccelIntrinsics(M=imu.upper_triangular(m6),
                               bias=values.atVector(keys.bias) if keys.bias is not None else nominal.bias)


def gyro_from_values(values, keys: GyroKeys, nominal: imu.GyroIntrinsics) -> imu.GyroIntrinsics:
    m9 = nominal.M.ravel().copy()
    if keys.M is not None:
        m9[list(keys.M_free)] = values.atVector(keys.M)
    return imu.GyroIntrinsics(
        M=m9.reshape(3, 3), bias=values.atVector(keys.bias) if keys.bias is not None else nominal.bias,
        A=values.atVector(keys.A).reshape(3, 3) if keys.A is not None else nominal.A)


def free_entries(M: np.ndarray, keys) -> np.ndarray:
    """Initial value of the ``M`` variable: the free entries of ``M``."""
    entries = imu.upper_triangular_entries(M) if isinstance(keys, AccelKeys) else M.ravel()
    return entries[list(keys.M_free)].copy()


def _channel_bias(values, channels, deviations) -> np.ndarray:
    """sum over channels of slope * deviation; deviations: name -> scalar or (n,) array."""
    return sum((np.multiply.outer(deviations[name], values.atVector(key)) for name, key in channels), 0.0)


def _fill(H, blocks):
    for n, J in enumerate(J for k, J in blocks if k is not None):
        H[n] = J


def static_accel_factor(noise, a_raw_mean, gravity_m_s2, up_key, keys: AccelKeys, nominal: imu.AccelIntrinsics,
                        channel_deviation: dict | None = None) -> gtsam.CustomFactor:
    """Static pose: ``e = a_raw_mean - b_a - sum_c k_c dc - M_a^-1 g u``  (raw output units, sensor frame).

    In the raw domain so the noise model is the raw output's noise whatever the gain: the estimate in counts
    per unit is then exactly invariant to the nominal transfer function used at import.
    ``channel_deviation``: the mean deviation of each auxiliary channel from its reference over this pose.
    """
    a = np.asarray(a_raw_mean, dtype=float)
    dev = channel_deviation or {}
    ordered = [up_key] + [k for k in (keys.bias, keys.M) if k is not None] + [k for _, k in keys.channels]

    def error(this, values, H):
        cal = accel_from_values(values, keys, nominal)
        up = values.atUnit3(up_key)
        M_inv = np.linalg.inv(cal.M)
        v = M_inv @ (gravity_m_s2 * up.point3())  # the raw output a perfect-bias sensor would give
        e = a - cal.bias - _channel_bias(values, keys.channels, dev) - v
        if H is not None:
            # d(M^-1)/dM_ij = -M^-1 E_ij M^-1, so de/dM_ij = M^-1 e_i v_j
            dM = np.zeros((3, 6))
            for col, (i, j) in enumerate(imu.UPPER_TRIANGULAR_INDEX):
                dM[:, col] = M_inv[:, i] * v[j]
            _fill(H, [(up_key, -gravity_m_s2 * M_inv @ up.basis()), (keys.bias, -np.eye(3)),
                      (keys.M, dM[:, list(keys.M_free)])]
                  + [(k, -np.eye(3) * dev[name]) for name, k in keys.channels])
        return e

    return gtsam.CustomFactor(noise, ordered, error)


def linear_bias_factor(noise, mean, bias_key, slopes, deviation: dict) -> gtsam.CustomFactor:
    """A segment of a static log: ``e = mean - b - sum_c k_c dc``, with slopes ``(channel, key)`` and the
    segment's channel deviations ``dc``; the plain bias model of a sensor at rest, in its output units."""
    mean = np.asarray(mean, dtype=float)
    ordered = [bias_key] + [k for _, k in slopes]

    def error(this, values, H):
        e = mean - values.atVector(bias_key) - _channel_bias(values, slopes, deviation)
        if H is not None:
            _fill(H, [(bias_key, -np.eye(3))] + [(k, -np.eye(3) * deviation[name]) for name, k in slopes])
        return e

    return gtsam.CustomFactor(noise, ordered, error)


def static_gyro_factor(noise, w_raw_mean, gravity_m_s2, up_key, keys: GyroKeys, nominal: imu.GyroIntrinsics,
                       channel_deviation: dict | None = None) -> gtsam.CustomFactor:
    """Static pose, zero rotation: ``e = w_raw_mean - b_g - sum_c k_c dc - A g u``  (rad s^-1, raw frame).

    Earth rotation (7.3e-5 rad/s) is not modelled: it is below the bias stability of the MEMS gyros this
    targets; for a navigation-grade gyro it would appear in the audit as an orientation-dependent bias.
    """
    w = np.asarray(w_raw_mean, dtype=float)
    dev = channel_deviation or {}
    ordered = [up_key] + [k for k in (keys.bias, keys.A) if k is not None] + [k for _, k in keys.channels]

    def error(this, values, H):
        cal = gyro_from_values(values, keys, nominal)
        up = values.atUnit3(up_key)
        f = gravity_m_s2 * up.point3()
        e = w - cal.bias - _channel_bias(values, keys.channels, dev) - cal.A @ f
        if H is not None:
            _fill(H, [(up_key, -gravity_m_s2 * cal.A @ up.basis()), (keys.bias, -np.eye(3)),
                      (keys.A, -np.kron(np.eye(3), f[None, :]))]
                  + [(k, -np.eye(3) * dev[name]) for name, k in keys.channels])
        return e

    return gtsam.CustomFactor(noise, ordered, error)


def gyro_motion_factor(noise, w_raw, f_S, dt_s, up_key_start, up_key_end, keys: GyroKeys,
                       nominal: imu.GyroIntrinsics, channel_deviation: dict | None = None) -> gtsam.CustomFactor:
    """Move between two static poses: the integrated gyro must carry the start up-direction onto the end one.

    ``e = u_end - delta_R^T u_start`` with ``delta_R`` = body(start) <- body(end) integrated from the
    calibrated rates (dimensionless chord between unit vectors, ~ rad for small errors).
    ``f_S`` is the specific force during the move (from the accelerometer), used only by the A f term;
    ``channel_deviation`` maps channel names to per-sample deviations (n,).
    """
    w_raw, f_S, dt_s = (np.asarray(x, dtype=float) for x in (w_raw, f_S, dt_s))
    dev = channel_deviation or {}
    ordered = ([up_key_start, up_key_end] + [k for k in (keys.bias, keys.M, keys.A) if k is not None]
               + [k for _, k in keys.channels])

    def error(this, values, H):
        cal = gyro_from_values(values, keys, nominal)
        u0, u1 = values.atUnit3(up_key_start), values.atUnit3(up_key_end)
        channels = {name: (values.atVector(k), dev[name]) for name, k in keys.channels}
        delta_R, J = imu.relative_rotation_and_jacobians(w_raw, f_S, dt_s, cal, channels)
        v = delta_R.T @ u0.point3()
        if H is not None:
            # delta_R Exp(J d): v -> Exp(-J d) v = v + [v]x J d, so de/dd = -[v]x J
            minus_v_hat = -so3.hat(v)
            _fill(H, [(up_key_start, -delta_R.T @ u0.basis()), (up_key_end, u1.basis()),
                      (keys.bias, minus_v_hat @ J["bias"]), (keys.M, minus_v_hat @ J["M"][:, list(keys.M_free)]),
                      (keys.A, minus_v_hat @ J["A"])]
                  + [(k, minus_v_hat @ J[name]) for name, k in keys.channels])
        return u1.point3() - v

    return gtsam.CustomFactor(noise, ordered, error)


# --- two IMUs -----------------------------------------------------------------------------------------------

SYMMETRIC_INDEX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def symmetric_gain(s6) -> np.ndarray:
    """``I + S`` with S symmetric from its 6 entries (00, 01, 02, 11, 12, 22): the second sensor's scale and
    non-orthogonality relative to the first.  Symmetric, so no rotation hides in it (polar decomposition)."""
    G = np.eye(3)
    for value, (i, j) in zip(s6, SYMMETRIC_INDEX):
        G[i, j] += value
        if i != j:
            G[j, i] += value
    return G


def _gain_jacobian(R: np.ndarray, v1: np.ndarray) -> np.ndarray:
    """d(-R (I + S) v1)/ds for each sample of v1 (n, 3): (n, 3, 6)."""
    out = np.zeros((len(v1), 3, 6))
    for col, (i, j) in enumerate(SYMMETRIC_INDEX):
        dS_v = np.zeros((len(v1), 3))
        dS_v[:, i] += v1[:, j]
        if i != j:
            dS_v[:, j] += v1[:, i]
        out[:, :, col] = -dS_v @ R.T
    return out


def static_pair_factor(noise, v0, v1, rotation_key, offset_key=None, gain_key=None,
                       axis_rotation_key=None) -> gtsam.CustomFactor:
    """Same static vector seen by both IMUs (the patent's residual): ``e = v0 - R (I + S + [rho]x) v1 - d``.

    ``v0``, ``v1``: mean accelerometer outputs of one static pose (m s^-2); ``d`` an optional relative bias
    (imu0 frame); ``S`` an optional relative gain (see :func:`symmetric_gain`), ``rho`` an optional axis rotation
    (see :func:`dynamic_pair_factor`).  Right perturbation R Exp(xi): d(-R u)/dxi = R [u]x with u = G v1.
    """
    return dynamic_pair_factor(noise, np.zeros(1), np.asarray(v0, dtype=float)[None],
                               Signal(np.array([-1.0, 1.0]), np.tile(np.asarray(v1, dtype=float), (2, 1))),
                               rotation_key, offset_key=offset_key, gain_key=gain_key,
                               axis_rotation_key=axis_rotation_key)


@dataclass(frozen=True)
class Signal:
    """A sampled 3-axis signal on its own clock, interpolated by a cubic spline; ``at`` returns value and slope.

    Cubic, not linear: a linear interpolant's error (h^2/8 times the curvature) on a rotating gravity vector has
    the shape of the centripetal lever-arm term and biased the lever arm whenever the clocks were offset.
    """

    t_s: np.ndarray
    x: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "_spline", CubicSpline(self.t_s, self.x, axis=0))

    def at(self, t_s):
        return self._spline(t_s), self._spline(t_s, 1)


def dynamic_pair_factor(noise, t0_s, v0, signal1: Signal, rotation_key, time_offset_key=None,
                        offset_key=None, lever_arm_key=None, w0=None, w_dot0=None,
                        gain_key=None, offset_channels=(), axis_rotation_key=None) -> gtsam.CustomFactor:
    """A block of imu0 samples against imu1's signal at the same physical instants.

    ``e_i = v0_i + L_i r - R (I + S + [rho]x) v1(t0_i - dt) - d - sum_c k_c phi_c,i`` stacked over the block
    (3n), with ``t_imu0 = t_imu1 + dt``, the optional relative gain ``S`` of imu1 (:func:`symmetric_gain`), the
    optional small axis rotation ``rho`` (rad) of this sensor's triad relative to the triad that fixes ``R`` (for
    accelerometers: imu1's accelerometer triad relative to its gyro triad, relative to imu0's; the gyros fix
    ``R`` while the rig moves, so a rotation between the triads shows in the accelerometer residual only), for
    accelerometers the lever-arm term ``L_i = [w_dot]x + [w]x^2`` (imu0 frame, from imu0's gyro), and optional
    ``offset_channels`` ``(key, phi (n,))``: the relative offset varying as ``k_c phi_c`` (``k_c`` a 3-vector;
    the audit's generic terms).  For gyros there is no lever arm: angular rate is the same everywhere on a rigid
    body.
    """
    t0_s, v0 = np.asarray(t0_s, dtype=float), np.asarray(v0, dtype=float)
    L = inertial.lever_arm_jacobian(w0, w_dot0) if lever_arm_key is not None else None
    channels = [(key, np.asarray(phi, dtype=float)) for key, phi in offset_channels]
    ordered = [k for k in (rotation_key, time_offset_key, offset_key, lever_arm_key, gain_key, axis_rotation_key)
               if k is not None]
    ordered += [key for key, _ in channels]

    def error(this, values, H):
        R = values.atRot3(rotation_key).matrix()
        G = symmetric_gain(values.atVector(gain_key)) if gain_key is not None else np.eye(3)
        if axis_rotation_key is not None:
            G = G + so3.hat(values.atVector(axis_rotation_key))
        dt = values.atVector(time_offset_key)[0] if time_offset_key is not None else 0.0
        v1, slope1 = signal1.at(t0_s - dt)
        u1, u_slope = v1 @ G.T, slope1 @ G.T
        e = v0 - u1 @ R.T
        if offset_key is not None:
            e = e - values.atVector(offset_key)
        if lever_arm_key is not None:
            e = e + np.einsum("nij,j->ni", L, values.atVector(lever_arm_key))
        for key, phi in channels:
            e = e - np.outer(phi, values.atVector(key))
        if H is not None:
            _fill(H, [(rotation_key, (R @ so3.hat(u1)).reshape(-1, 3)),
                      (time_offset_key, (u_slope @ R.T).reshape(-1, 1)),
                      (offset_key, np.tile(-np.eye(3), (len(v0), 1))),
                      (lever_arm_key, L.reshape(-1, 3) if L is not None else None),
                      (gain_key, _gain_jacobian(R, v1).reshape(-1, 6) if gain_key is not None else None),
                      # d(-R [rho]x v1)/drho = R [v1]x
                      (axis_rotation_key, (R @ so3.hat(v1)).reshape(-1, 3) if axis_rotation_key is not None
                       else None)]
                  + [(key, -np.kron(phi[:, None], np.eye(3))) for key, phi in channels])
        return e.reshape(-1)

    return gtsam.CustomFactor(noise, ordered, error)
