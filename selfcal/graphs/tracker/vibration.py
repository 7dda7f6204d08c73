"""Vibration is modelled, not alarmed: the inclinometer factor's covariance grows with the vibration measured
around its sample.

Two measures: the accelerometer's energy above its white noise over a window centred on the sample
(:func:`accel_tilt_covariance`), and the high-frequency energy of the inclinometer's own residuals
(:func:`own_vibration_excess`), which sees vibration below what the accelerometer can (~1e-3 rad).
"""
from __future__ import annotations

import math
from collections import deque
from functools import lru_cache

import gtsam
import numpy as np

from selfcal.core.stats import chi2_upper_quantile  # scipy.special would cost ~0.4 s of start-up
from selfcal.factors import tracker as ft
from selfcal.graphs.tracker.options import GatingOptions, SensorNoise
from selfcal.models import tracker as mt

X = gtsam.symbol_shorthand.X
UP_BASIS = ft.UP_W.basis()  # (3, 2): the inclinometer factor's error is expressed on this tangent basis


@lru_cache(maxsize=64)
def variance_ratio(dof: int, alpha: float) -> float:
    """chi2(dof).ppf(1 - alpha) / dof: a sample variance above ``white`` times this is significant at ``alpha``."""
    return chi2_upper_quantile(dof, alpha) / dof


class ImuHistory:
    """The last ``capacity`` IMU samples, rows (specific force m/s^2, angular rate rad/s), body frame, with their
    stamps, oldest first."""

    FLUSH = 64  # samples held in a list before they enter the ring together (well under any capacity)

    def __init__(self, capacity: int):
        # a ring kept contiguous: each sample is written twice, any span is read as one slice.  Samples arrive at
        # 200 Hz and are read about twice a keyframe: they wait in a list and enter the ring together (one numpy
        # write of 20 rows costs what one row does)
        capacity = max(capacity, self.FLUSH)
        self._t_ns = np.zeros(2 * capacity, dtype=np.int64)
        self._imu = np.zeros((2 * capacity, 6))
        self._n, self._capacity = 0, capacity
        self._new_t_ns: list[int] = []
        self._new_imu: list = []

    def append(self, t_ns: int, accel: np.ndarray, gyro: np.ndarray) -> None:
        self._new_t_ns.append(t_ns)
        self._new_imu.append(np.concatenate([accel, gyro]))
        if len(self._new_t_ns) >= self.FLUSH:
            self._flush()

    def _flush(self) -> None:
        if not self._new_t_ns:
            return
        i = (self._n + np.arange(len(self._new_t_ns))) % self._capacity
        t_ns, imu = np.array(self._new_t_ns, dtype=np.int64), np.array(self._new_imu, dtype=float)
        self._t_ns[i] = self._t_ns[i + self._capacity] = t_ns
        self._imu[i] = self._imu[i + self._capacity] = imu
        self._n += len(self._new_t_ns)
        self._new_t_ns, self._new_imu = [], []

    def _stamps(self) -> tuple[int, np.ndarray]:
        """(start of the stored samples in the ring, their stamps)."""
        self._flush()
        start = self._n % self._capacity if self._n >= self._capacity else 0
        return start, self._t_ns[start:start + min(self._n, self._capacity)]

    def between(self, t_from_ns: float, t_to_ns: float) -> np.ndarray:
        """(n, 6) samples (specific force, angular rate) stamped in ``[t_from_ns, t_to_ns)``."""
        start, stamps = self._stamps()
        lo, hi = np.searchsorted(stamps, [t_from_ns, t_to_ns], side="left")
        return self._imu[start + lo:start + hi]

    def mean_before(self, t_ns: int, n: int) -> np.ndarray:
        """Mean specific force of the ``n`` samples before ``t_ns`` (the latest one if none is earlier)."""
        start, stamps = self._stamps()
        hi = int(np.searchsorted(stamps, t_ns, side="left"))
        return self._imu[start + max(hi - n, 0):start + max(hi, 1), :3].mean(axis=0)


def horizontal_basis_B(R_W_B: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the body frame's horizontal plane: body x made horizontal (tilts are small),
    then up x that."""
    ux, uy, uz = R_W_B[2].tolist()  # up in the body, R_W_B^T e_z
    h1 = np.array([1.0 - ux * ux, -ux * uy, -ux * uz])
    h1 /= math.sqrt(h1 @ h1)
    return np.column_stack([h1, mt.cross(np.array([ux, uy, uz]), h1)])


def excess_over_white(c00: float, c01: float, c11: float, white: float) -> np.ndarray:
    """The 2x2 covariance ``C - white I`` with its eigenvalues clipped at 0 (eigen-decomposition in closed form)."""
    mean, dev = 0.5 * (c00 + c11), math.hypot(0.5 * (c00 - c11), c01)
    lam1, lam2 = max(mean + dev - white, 0.0), max(mean - dev - white, 0.0)
    angle = 0.5 * math.atan2(2 * c01, c00 - c11)  # C's principal axes
    u = np.array([math.cos(angle), math.sin(angle)])
    v = np.array([-u[1], u[0]])
    return lam1 * np.outer(u, u) + lam2 * np.outer(v, v)


def in_centre_frame(imu_B: np.ndarray, dt_s: float) -> np.ndarray:
    """The specific forces of the samples ``imu_B`` ((n, 6): force, rate; body) turned into the body frame at the
    window's centre by the gyro's rotation, ``f_c = R_c^T R_j f_j ~ f_j + theta_j x f_j`` with ``theta_j`` the
    rate integrated from the centre to sample j (small angles: 0.03 rad/s over 0.25 s is 8 mrad, the neglected
    second order 3e-5 of g).  Gravity is then one vector across the window: what is left is acceleration and noise.
    """
    theta = np.cumsum(imu_B[:, 3:], axis=0) * dt_s
    theta -= theta[len(theta) // 2]
    f = imu_B[:, :3]
    return f + np.cross(theta, f)


def accel_tilt_covariance(imu_B: np.ndarray, R_W_B: np.ndarray, n_avg: int, noise: SensorNoise,
                          gating: GatingOptions, turned: bool = False) -> tuple[np.ndarray | None, bool]:
    """Extra covariance (2x2, rad^2, in the inclinometer factor's error coordinates) of the inclinometer from the
    vibration the IMU samples ``imu_B`` ((n, 6): specific force, angular rate; the window around the sample) show,
    or None when they show none; and whether they show energy above the white noise at the loose
    ``vibration_hint_alpha``.

    The inclinometer reads the direction of the specific force averaged over ``incl_average_s``; its error is the
    horizontal part of that average over g.  The accelerometer sees the same force: its samples averaged in blocks
    of the inclinometer's own length ``n_avg`` (the same low-pass) give m block means whose horizontal components
    (perpendicular to the predicted up, body frame) have the sample covariance ``C``; without vibration
    ``C ~ sigma_w^2 Wishart_2(m - 1) / (m - 1)`` with ``sigma_w^2 = accel_noise_density^2 rate / n_avg``.  When
    ``trace C`` exceeds its white-noise level at ``vibration_alpha``, the excess ``C - sigma_w^2 I`` (eigenvalues
    clipped at 0) over g^2 is the tilt disturbance's covariance, anisotropic as the vibration is, rotated into
    the factor's error coordinates (the tangent basis of the world's up: ``e = basis^T R_W_B d_B``).
    ``| |f| - g |`` (the ship system's disturbance measure) is not used: it is mostly the vertical part, which
    does not tilt the reading.

    ``turned``: the samples are first turned into the body frame at the window's centre (:func:`in_centre_frame`),
    so the target's own rotation over the window, motion the attitude states carry, is not counted: steered at
    0.03 rad/s it moves the block means by 0.04 m/s^2 across the window, three times their white noise.  The online
    pass counts it (its inclinometer noise grows while the target turns, a conservative gate measured against the
    patent's filter); the audit's Wiener prediction of the reading from the accelerometer needs the vibration
    alone (with the rotation counted, weights of ~0.9 sat on the accelerometer's noise in steered runs without
    any vibration, and a null run read an acceleration sensitivity of -0.98 +- 0.15).
    """
    m = len(imu_B) // n_avg
    if m < 3:
        return None, False
    accel_B = in_centre_frame(imu_B[:m * n_avg], 1.0 / noise.imu_rate_hz) if turned else imu_B[:m * n_avg, :3]
    sums = accel_B.reshape(m, n_avg, 3).sum(axis=1)  # n_avg times the block means
    H = horizontal_basis_B(R_W_B) / n_avg
    h = sums @ H  # the block means' horizontal components
    h -= h.sum(axis=0) / m
    C = h.T @ h / (m - 1)  # C = sum (h - mean)(h - mean)^T / (m - 1)
    white = noise.accel_noise_density**2 * noise.imu_rate_hz / n_avg  # sigma_w^2 of a block mean, per axis
    (c00, c01), (_, c11) = C.tolist()
    ratio = (c00 + c11) / (2 * white)  # trace C / (2 sigma_w^2) ~ chi2(2 (m - 1)) / (2 (m - 1)) without vibration
    hint = ratio > variance_ratio(2 * (m - 1), gating.vibration_hint_alpha)
    if ratio <= variance_ratio(2 * (m - 1), gating.vibration_alpha):
        return None, hint
    C_B = excess_over_white(c00, c01, c11, white) / noise.gravity_m_s2**2  # tilt = horizontal force / g
    M = UP_BASIS.T @ R_W_B @ H * n_avg  # e = basis^T R_W_B d_B
    return M @ C_B @ M.T, hint


def own_vibration_excess(residuals_rad: np.ndarray, v0_rad2: float, ratio: float) -> float:
    """Vibration variance per axis (rad^2) shown by consecutive inclinometer prediction errors (``(w + 1, 2)``),
    0 when not significant.

    Vibration at 3-25 Hz sampled at 10 Hz is nearly white there, while a soft fault (offset, ramp, stuck output)
    is slow and cancels in the difference.  Without vibration ``|d|^2 ~ v0 chi2(2)``, median ``2 ln 2 v0``; the
    median of the window (a spike moves it little) above ``ratio`` times that gives the excess
    ``(median / ln 4 - v0) / 2`` per axis.
    """
    d = np.diff(residuals_rad, axis=0)
    d2 = sorted(np.einsum("ij,ij->i", d, d).tolist())  # a few values: np.median costs ~40 us
    w = len(d2)
    med = 0.5 * (d2[(w - 1) // 2] + d2[w // 2])
    if med <= ratio * v0_rad2 * 2 * np.log(2):
        return 0.0
    return 0.5 * (med / (2 * np.log(2)) - v0_rad2)


def noise_covariance(factor) -> np.ndarray:
    """The covariance of a factor's Gaussian noise model, ``(R^T R)^-1`` (``R``: its square-root information)."""
    R = factor.noiseModel().R()
    return np.linalg.inv(R.T @ R)


class InclinometerVibration:
    """The inclinometer's noise model under vibration: the accelerometer history and the inclinometer's own
    prediction errors it is measured from, and the inclinometer factors it gives."""

    def __init__(self, noise: SensorNoise, gating: GatingOptions, keyframe_s: float):
        self.noise, self.gating = noise, gating
        self.n_avg = max(1, int(round(noise.incl_average_s * noise.imu_rate_hz)))  # IMU samples per reading
        # the window centred on an inclinometer sample decided up to ~1.3 s later (its own samples after it, at
        # >= 5 Hz), and the window after it, plus margin
        self.imu = ImuHistory(int(round((gating.vibration_window_s + 1.5 + 2 * keyframe_s)
                                        * noise.imu_rate_hz)) + 8)
        # (t_ns, prediction error (2,) rad) of every inclinometer sample at its arrival, in order: the own-vibration
        # estimates of a sample need diff_window samples before it and onset_window after it
        self._residuals: deque = deque(maxlen=2 * (gating.diff_window + gating.onset_window) + 24)
        self._t_last_ns, self._interval_s = None, None  # the inclinometer's sample interval
        self._nominal_noise = gtsam.noiseModel.Isotropic.Sigma(2, noise.incl_sigma_rad)

    def note_sample(self, t_ns: int) -> None:
        """An inclinometer sample's stamp (its sample interval sets the null level and the decision's delay)."""
        if self._t_last_ns is not None:
            self._interval_s = (t_ns - self._t_last_ns) * 1e-9
        self._t_last_ns = t_ns

    def add_residual(self, t_ns: int, residual_rad: np.ndarray) -> None:
        self._residuals.append((t_ns, residual_rad))

    def deferral_s(self) -> float:
        """How long an inclinometer sample's decision waits: for the accelerometer window centred on it and for
        ``onset_window`` of its own samples after it (0 without the vibration model)."""
        g = self.gating
        if not g.vibration_inflation:
            return 0.0
        return max(0.5 * g.vibration_window_s, (g.onset_window + 0.5) * (self._interval_s or 0.1))

    def accelerometer(self, R_W_B: np.ndarray, t_ns: int, turned: bool = False) -> tuple[np.ndarray | None, bool]:
        """:func:`accel_tilt_covariance` over the ``vibration_window_s`` of accelerometer centred on ``t_ns``."""
        if not self.gating.vibration_inflation:
            return None, False
        half_ns = 0.5e9 * self.gating.vibration_window_s
        imu_B = self.imu.between(t_ns - half_ns, t_ns + half_ns)
        return accel_tilt_covariance(imu_B, R_W_B, self.n_avg, self.noise, self.gating, turned)

    def own(self, t_ns: int, ahead: bool = False) -> float:
        """Vibration variance per axis (rad^2) the inclinometer's own residuals show at its sample ``t_ns``: from
        the ``diff_window`` differences up to the sample, or (``ahead``) the ``onset_window`` after it; 0 when
        not significant (:func:`own_vibration_excess`).

        The differences after the sample matter at a burst's onset: its envelope rises within a second
        (``u^4 (1-u)^4``), so the first samples it tilts have only the differences after them in the burst;
        normalised by the previous ones alone, their rejects and 5-sigma residuals add up to false soft-fault
        alarms (measured: 5 of the 6 per hour with bursts).
        """
        g, buf = self.gating, self._residuals
        w, ratio = (g.onset_window, g.onset_ratio) if ahead else (g.diff_window, g.diff_ratio)
        stamps = [t for t, _ in buf]
        if t_ns not in stamps:
            return 0.0
        i = stamps.index(t_ns)
        lo, hi = (i, i + w) if ahead else (i - w, i)
        if lo < 0 or hi >= len(buf):
            return 0.0
        rate_hz = 10.0 if self._interval_s is None else 1.0 / self._interval_s
        # v0 = 2 sigma^2 + gyro noise over the sample interval  (per axis, of a difference)
        v0 = 2 * self.noise.incl_sigma_rad**2 + self.noise.gyro_noise_density**2 / rate_hz
        return own_vibration_excess(np.array([buf[j][1] for j in range(lo, hi + 1)]), v0, ratio)

    def factor(self, k: int, up_B: np.ndarray, accel_cov: np.ndarray | None):
        """The inclinometer factor with covariance ``sigma^2 I + accel_cov`` (nominal when None)."""
        noise = self._nominal_noise if accel_cov is None else gtsam.noiseModel.Gaussian.Covariance(
            self.noise.incl_sigma_rad**2 * np.eye(2) + accel_cov)
        return ft.inclinometer_factor(noise, X(k), up_B)

    def grown(self, factor, excess_rad2: float, accel_cov: np.ndarray | None, up_B: np.ndarray):
        """The inclinometer factor with its covariance grown by the own-vibration variance ``excess_rad2``
        (isotropic), unless the accelerometer's estimate is already larger."""
        if not self.gating.vibration_inflation or excess_rad2 <= 0.0:
            return factor
        base = np.zeros((2, 2)) if accel_cov is None else accel_cov
        if excess_rad2 <= 0.5 * np.trace(base):
            return factor
        cov = self.noise.incl_sigma_rad**2 * np.eye(2) + base + (excess_rad2 - 0.5 * np.trace(base)) * np.eye(2)
        return ft.inclinometer_factor(gtsam.noiseModel.Gaussian.Covariance(cov), factor.keys()[0], up_B)

    def covariance(self, accel_cov: np.ndarray | None) -> np.ndarray:
        """The whole covariance (2x2, rad^2, world up's tangent basis) of :meth:`factor`: ``sigma^2 I + accel_cov``."""
        return self.noise.incl_sigma_rad**2 * np.eye(2) + (0.0 if accel_cov is None else accel_cov)

    def mean_specific_force(self, t_ns: int) -> np.ndarray:
        """Accelerometer mean over the inclinometer's averaging window before ``t_ns`` (bias not removed)."""
        return self.imu.mean_before(t_ns, self.n_avg)
