"""Baseline: rotation between two co-mounted motion sensors from static measurements, as patent seed 002 writes it.

The method (CN1737580A, Philips, "一種校準的方法和裝置", Liu Fang and Tu Jiawen, filed 2004-08-17):

1. a minimum number of measurements follows from the dimensions of the two sensors' coordinate systems
   (1-D: 1, 2-D: 1, 3-D: 3; if the dimensions differ, the smaller dimension decides);
2. both sensors are measured in that many (or more) static poses, a different attitude each time;
3. the residual of measurement i in the first sensor's frame is ``a0_i - R a1_i``;
4. ``R`` minimises ``sum_i ||a0_i - R a1_i||^2``:

   * 1-D: ``R`` is a scale ratio, ``R = A1^T A0 / (A1^T A1)``;
   * 2-D: one angle, ``R = [[cos t, sin t], [-sin t, cos t]]``;
   * 3-D: Euler angles (phi, theta, psi), ``R = B C D`` with ``D = Rz'(phi)``, ``C = Rx'(theta)``,
     ``B = Rz'(psi)`` where ``Rz'(a) = [[cos a, sin a, 0], [-sin a, cos a, 0], [0, 0, 1]]`` and
     ``Rx'(a) = [[1, 0, 0], [0, cos a, sin a], [0, -sin a, cos a]]`` (passive, "x-convention" ZXZ),
     "found by search".

5. with more than two sensors, each is calibrated against one reference sensor.

Convention throughout: ``v0 = R v1`` (``R`` maps vectors from the second sensor's frame into the first's), i.e.
``R`` is ``R_imu0_imu1``.  Pure numpy/scipy, so it stays an independent reference for the factor-graph solution.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

# Minimum measurements per coordinate-system dimension, as the patent states them.  (Mathematically two
# non-parallel 3-D measurements already fix R; the patent asks for three.)
MIN_MEASUREMENTS = {1: 1, 2: 1, 3: 3}

# Coarse search grid (phi, theta, psi): 30 deg steps; theta at cell centres keeps the start off the gimbal lock.
_GRID_STEPS = (12, 6, 12)


@dataclass
class PatentRotationResult:
    """3-D result of the patent's method.

    Attributes
    ----------
    R_imu0_imu1 : (3, 3) rotation with ``v0 = R v1``.
    euler_rad : (phi, theta, psi) with ``R = Rz'(psi) Rx'(theta) Rz'(phi)``; phi, psi in [-pi, pi),
        theta in [0, pi].  At theta = 0 or pi (gimbal lock) only phi + psi (resp. phi - psi) is determined.
    residual_rms : ``sqrt(sum_i ||a0_i - R a1_i||^2 / N)``, in the input units.
    n_measurements : N.
    """

    R_imu0_imu1: np.ndarray
    euler_rad: np.ndarray
    residual_rms: float
    n_measurements: int


def minimum_measurements(dim0: int, dim1: int) -> int:
    """Fewest static measurements the patent requires for sensors of dimensions ``dim0`` and ``dim1``.

    1-D: 1, 2-D: 1, 3-D: 3; when the dimensions differ, the smaller one decides (patent seed 002).
    """
    for dim in (dim0, dim1):
        if dim not in MIN_MEASUREMENTS:
            raise ValueError(f"sensor coordinate systems must be 1-, 2- or 3-dimensional, got {dim}")
    return MIN_MEASUREMENTS[min(dim0, dim1)]


def scale_ratio_1d(a0, a1) -> float:
    """Scale ratio R with ``a0 = R a1`` in least squares: ``R = A1^T A0 / (A1^T A1)`` (patent seed 002, 1-D)."""
    A0, A1 = (a[:, 0] for a in _as_measurements(a0, a1, 1))
    denominator = A1 @ A1
    if denominator == 0.0:
        raise ValueError("1-D calibration: the second sensor measured zero in every pose; the ratio is undefined")
    return float(A1 @ A0 / denominator)


def patent_rotation_2d(angle_rad: float) -> np.ndarray:
    """``R = [[cos t, sin t], [-sin t, cos t]]`` (patent seed 002, 2-D)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, s], [-s, c]])


def rotation_2d(a0, a1) -> tuple[float, np.ndarray]:
    """Angle t and ``R(t)`` minimising ``sum_i ||a0_i - R(t) a1_i||^2`` (patent seed 002, 2-D).

    With the patent's matrix ``a0_i . R a1_i = cos t * sum(a0 . a1) + sin t * sum(a0 x a1)`` (a0 x a1 the
    scalar cross product x0 y1 - y0 x1), so the one-angle least squares has the closed form
    ``t = atan2(sum(a0 x a1), sum(a0 . a1))``.

    Parameters
    ----------
    a0, a1 : (N, 2) measurements of the first and second sensor.

    Returns
    -------
    angle_rad : t in (-pi, pi].
    R : (2, 2) with ``a0 = R a1``.
    """
    a0, a1 = _as_measurements(a0, a1, 2)
    dot = np.sum(a0 * a1)
    cross = np.sum(a0[:, 0] * a1[:, 1] - a0[:, 1] * a1[:, 0])
    if dot == 0.0 and cross == 0.0:
        raise ValueError("2-D calibration: the measurements are zero; the angle is undefined")
    angle = float(np.arctan2(cross, dot))
    return angle, patent_rotation_2d(angle)


def _rz(a: np.ndarray) -> np.ndarray:
    """Patent's ``[[cos a, sin a, 0], [-sin a, cos a, 0], [0, 0, 1]]`` for an array of angles: (..., 3, 3)."""
    c, s = np.cos(a), np.sin(a)
    out = np.zeros(np.shape(a) + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1], out[..., 2, 2] = c, s, -s, c, 1.0
    return out


def _rx(a: np.ndarray) -> np.ndarray:
    """Patent's ``[[1, 0, 0], [0, cos a, sin a], [0, -sin a, cos a]]`` for an array of angles: (..., 3, 3)."""
    c, s = np.cos(a), np.sin(a)
    out = np.zeros(np.shape(a) + (3, 3))
    out[..., 0, 0], out[..., 1, 1], out[..., 1, 2], out[..., 2, 1], out[..., 2, 2] = 1.0, c, s, -s, c
    return out


def _drz(a: float) -> np.ndarray:
    """d/da of the patent's Rz'(a)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[-s, c, 0.0], [-c, -s, 0.0], [0.0, 0.0, 0.0]])


def _drx(a: float) -> np.ndarray:
    """d/da of the patent's Rx'(a)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[0.0, 0.0, 0.0], [0.0, -s, c], [0.0, -c, -s]])


def patent_rotation_3d(phi_rad, theta_rad, psi_rad) -> np.ndarray:
    """``R = B C D`` with ``D = Rz'(phi)``, ``C = Rx'(theta)``, ``B = Rz'(psi)`` (patent seed 002, 3-D).

    Broadcasts over arrays of angles, returning (..., 3, 3).
    """
    return _rz(np.asarray(psi_rad, dtype=float)) @ _rx(np.asarray(theta_rad, dtype=float)) \
        @ _rz(np.asarray(phi_rad, dtype=float))


def _canonical_euler(angles: np.ndarray) -> np.ndarray:
    """Same rotation with phi, psi in [-pi, pi) and theta in [0, pi].

    Uses ``Rx'(-theta) = Rz'(pi) Rx'(theta) Rz'(pi)``, so ``(phi, -theta, psi) ~ (phi + pi, theta, psi + pi)``.
    """
    phi, theta, psi = angles
    theta = _wrap_pi(theta)
    if theta < 0:
        phi, theta, psi = phi + np.pi, -theta, psi + np.pi
    return np.array([_wrap_pi(phi), theta, _wrap_pi(psi)])


def _wrap_pi(a: float) -> float:
    """Angle in [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def rotation_3d(a0, a1) -> PatentRotationResult:
    """Euler angles minimising ``sum_i ||a0_i - B C D a1_i||^2`` by search (patent seed 002, 3-D).

    The "search" is a coarse grid over (phi, theta, psi) in 30 deg steps (vectorised cost), then
    Levenberg-Marquardt (``scipy.optimize.least_squares``, analytic Jacobian) on the three angles from the best
    three grid cells, then three Gauss-Newton steps on the best fit so the gradient, not only the cost change,
    reaches round-off.

    The ZXZ angles are singular at theta = 0 and pi, and theta = 0 is exactly the common case of co-aligned
    sensors (R near identity, or a PCB rotation about a shared z axis): there only phi + psi is observable and
    the angle Jacobian loses rank.  The cost stays smooth in the angles and attains its minimum along the whole
    degenerate line, so LM (damped) and the minimum-norm Gauss-Newton steps still converge to the right R.  R,
    not the angles, is the calibration; the angles are returned in a canonical range.

    Parameters
    ----------
    a0, a1 : (N, 3) static measurements of the first and second sensor, N >= 3 (the patent's minimum).

    Returns
    -------
    PatentRotationResult with ``a0 ~ R_imu0_imu1 a1``.
    """
    a0, a1 = _as_measurements(a0, a1, 3)
    directions = a1 / np.linalg.norm(a1, axis=1, keepdims=True).clip(min=np.finfo(float).tiny)
    s = np.linalg.svd(directions, compute_uv=False)
    if s[1] <= 1e-9 * s[0]:
        raise ValueError("3-D calibration: all measurements point in one direction, so the rotation about it is "
                         "undetermined; measure in static poses with different gravity directions")

    def residuals(angles: np.ndarray) -> np.ndarray:
        return (a0 - a1 @ patent_rotation_3d(*angles).T).ravel()

    def jacobian(angles: np.ndarray) -> np.ndarray:
        # d r_i / d angle = -(dR / d angle) a1_i; analytic, because a finite-difference Jacobian would move the
        # fixed point J^T r = 0 of this non-zero-residual problem by ~sqrt(eps), i.e. ~1e-8 rad.
        phi, theta, psi = angles
        B, C, D = _rz(psi), _rx(theta), _rz(phi)
        dR = (B @ C @ _drz(phi), B @ _drx(theta) @ D, _drz(psi) @ C @ D)
        return np.stack([-(a1 @ d.T).ravel() for d in dR], axis=1)

    n_phi, n_theta, n_psi = _GRID_STEPS
    phi = np.arange(n_phi) * 2 * np.pi / n_phi - np.pi
    theta = (np.arange(n_theta) + 0.5) * np.pi / n_theta
    psi = np.arange(n_psi) * 2 * np.pi / n_psi - np.pi
    grid = np.stack(np.meshgrid(phi, theta, psi, indexing="ij"), axis=-1).reshape(-1, 3)
    Rs = patent_rotation_3d(grid[:, 0], grid[:, 1], grid[:, 2])
    # sum_i ||a0_i - R a1_i||^2 = const - 2 trace(R^T sum_i a0_i a1_i^T): one contraction per grid point
    costs = -np.einsum("gij,ij->g", Rs, a0.T @ a1)
    best = None
    for start in grid[np.argsort(costs)[:3]]:
        fit = least_squares(residuals, start, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        if best is None or fit.cost < best.cost:
            best = fit
    angles = best.x
    # LM stops once the relative cost change is below eps, which resolves the angles only to
    # ~sqrt(eps cost / Hessian) (1e-10..1e-9 rad); Gauss-Newton steps drive the gradient J^T r to zero instead.
    # lstsq takes the minimum-norm step where the Jacobian is rank deficient (gimbal lock).
    for _ in range(3):
        angles = angles + np.linalg.lstsq(jacobian(angles), -residuals(angles), rcond=1e-12)[0]
    angles = _canonical_euler(angles)
    R = patent_rotation_3d(*angles)
    rms = float(np.sqrt(np.sum((a0 - a1 @ R.T) ** 2) / len(a0)))
    return PatentRotationResult(R, angles, rms, len(a0))


def _as_measurements(a0, a1, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, dim) float arrays of equal shape with at least the patent's minimum N, or a one-line ValueError."""
    a0 = np.asarray(a0, dtype=float)
    a1 = np.asarray(a1, dtype=float)
    if dim == 1:  # (N,) is accepted as (N, 1)
        a0, a1 = (a[:, None] if a.ndim == 1 else a for a in (a0, a1))
    if a0.ndim != 2 or a0.shape[1] != dim or a0.shape != a1.shape:
        raise ValueError(f"{dim}-D calibration needs two (N, {dim}) measurement arrays of equal shape, "
                         f"got {a0.shape} and {a1.shape}")
    needed = MIN_MEASUREMENTS[dim]
    if len(a0) < needed:
        raise ValueError(f"{dim}-D sensors need at least {needed} static measurement(s) (patent seed 002), "
                         f"got {len(a0)}")
    if not (np.all(np.isfinite(a0)) and np.all(np.isfinite(a1))):
        raise ValueError(f"{dim}-D calibration: measurements contain NaN or inf")
    return a0, a1


def calibrate(a0, a1):
    """Rotation relation between two sensors, dispatched on the dimension of the measurements.

    Parameters
    ----------
    a0, a1 : (N,) or (N, 1) for 1-D, (N, 2) for 2-D, (N, 3) for 3-D sensors; equal shapes.

    Returns
    -------
    1-D: the scale ratio (float), as :func:`scale_ratio_1d`; 2-D: ``(angle_rad, R)``, as :func:`rotation_2d`;
    3-D: :class:`PatentRotationResult`, as :func:`rotation_3d`.  Always ``a0 ~ R a1``.
    """
    a0_arr, a1_arr = np.asarray(a0, dtype=float), np.asarray(a1, dtype=float)
    if a0_arr.shape != a1_arr.shape or a0_arr.ndim not in (1, 2):
        raise ValueError(f"the two sensors' measurements must be (N, d) arrays of equal shape, "
                         f"got {a0_arr.shape} and {a1_arr.shape}")
    dim = 1 if a0_arr.ndim == 1 else a0_arr.shape[1]
    if dim not in MIN_MEASUREMENTS:
        raise ValueError(f"sensor coordinate systems must be 1-, 2- or 3-dimensional, got {dim}")
    if dim == 1:
        return scale_ratio_1d(a0_arr, a1_arr)
    if dim == 2:
        return rotation_2d(a0_arr, a1_arr)
    return rotation_3d(a0_arr, a1_arr)


def calibrate_to_reference(measurements: dict, reference: str) -> dict:
    """More than two sensors: calibrate every other sensor against one reference sensor (patent seed 002).

    Parameters
    ----------
    measurements : sensor name -> (N, d) static measurements, row i taken in the same pose for every sensor.
    reference : name of the reference sensor (the "first sensor" of every pair).

    Returns
    -------
    dict: every non-reference name -> :func:`calibrate` ``(measurements[reference], measurements[name])``,
    so each result maps that sensor's frame into the reference frame (``v_reference = R v_name``).
    """
    if reference not in measurements:
        raise ValueError(f"reference sensor {reference!r} not among the measured sensors {sorted(measurements)}")
    return {name: calibrate(measurements[reference], a) for name, a in measurements.items() if name != reference}
