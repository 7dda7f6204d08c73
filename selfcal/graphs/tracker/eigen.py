"""Soft-fault detection by the extreme eigenvalues of a window of normalised residuals (Wishart test).

A fault-free sensor's normalised residuals ``nu = L^-1 b`` (``S = L L^T``) are N(0, I): over a window of ``n`` of
them ``W = sum nu nu^T ~ Wishart_m(n, I)``.  A bias, a ramp or outliers put too much energy in one direction
(``lambda_max`` too large); a stuck output has no noise left (``lambda_min`` too small).
"""
from __future__ import annotations

from collections import deque

import gtsam
import numpy as np

from selfcal.core.stats import wishart_lambda_max_quantile, wishart_lambda_min_quantile
from selfcal.graphs.tracker.options import GatingOptions

X = gtsam.symbol_shorthand.X


class EigenDetector:
    """Extreme eigenvalues of the windowed sum of outer products of normalised residuals (m-dimensional).

    The lower side (too little noise) accuses a sensor only once it has shown the noise its model states, on a
    window without vibration-grown noise: a stuck output is noise that has *gone*.  A sensor quieter than its
    model from the start -- noise-free (exact) data, or a sensor.yaml sigma overstated -- has lost nothing
    (measured: the exact 30 s recording's residuals spread 0.03-0.1 of their predicted 1 in the first window,
    the same run with the simulator's noise 0.7-1.0; held out at 3 s for the rest of the run before).
    """

    last_min = np.inf

    def __init__(self, m: int, options: GatingOptions, rate_hz: float):
        self.m, self.n, self.stride = m, options.window, max(1, int(round(options.stride_s * rate_hz)))
        tests_per_hour = 3600.0 * rate_hz / self.stride
        # alpha = false alarms per hour / tests per hour  (union bound)
        self.alpha = min(0.5, options.false_alarms_per_hour / tests_per_hour)
        # two-sided spectral test, alpha split evenly: too much residual energy in one direction (bias, ramp,
        # outliers) or too little (a stuck output has no noise and drags the state along with it)
        self.threshold = wishart_lambda_max_quantile(m, self.n, round(self.alpha / 2, 12))
        self.lower = wishart_lambda_min_quantile(m, self.n, round(self.alpha / 2, 12))
        self.window: deque = deque(maxlen=self.n)
        self.inflated: deque = deque(maxlen=self.n)  # whether each sample's noise was grown by measured vibration
        self.count = 0
        # a window without vibration-grown noise has passed the lower side: the sensor has the noise its model
        # states, so losing it is a fault (kept across resets: a property of the sensor, not of the window)
        self.noise_seen = False

    def push(self, nu: np.ndarray, inflated: bool = False) -> float | None:
        """Add one normalised residual; the statistic when a test is due (full window, every stride), else None."""
        self.window.append(np.asarray(nu, dtype=float))
        self.inflated.append(bool(inflated))
        self.count += 1
        if len(self.window) < self.n or self.count % self.stride:
            return None
        # W = Y^T Y = sum nu nu^T  (m x m); its extreme eigenvalues are the test statistics
        Y = np.array(self.window)
        eig = np.linalg.eigvalsh(Y.T @ Y)
        self.last_min = float(eig[0])
        if self.last_min >= self.lower and not any(self.inflated):
            self.noise_seen = True
        return float(eig[-1])

    def keeps_its_noise(self) -> bool:
        """The last test's lower side passed, or cannot accuse: the sensor has never shown its modelled noise."""
        return self.last_min >= self.lower or not self.noise_seen

    def quieter_than_model(self) -> bool:
        """The last test's window (no vibration-grown noise) is below the lower side, and no window ever passed
        it: noise-free data or an overstated sigma, not a fault."""
        return not self.noise_seen and self.last_min < self.lower and not any(self.inflated)

    def healthy(self, lam_max: float) -> bool:
        """The last test passed.  The lower side (no noise left: a stuck output) is tested only on windows
        whose noise was not grown by measured vibration: an estimated vibration variance (+-30 % from 0.5 s of
        accelerometer) makes ``lambda_min`` meaningless."""
        return lam_max <= self.threshold and (self.keeps_its_noise() or any(self.inflated))

    def certifies_recovery(self, lam_max: float) -> bool:
        """Readmission needs a window passing both sides (an over-estimated vibration makes the lower side
        harder to pass, never easier) in which at most a third of the residuals had their noise grown by
        vibration: residuals drowned in vibration cannot show that an offset has gone."""
        return lam_max <= self.threshold and self.keeps_its_noise() and sum(self.inflated) <= self.n // 3

    def reset(self) -> None:
        self.window.clear()
        self.inflated.clear()
        self.count = 0


class StateRecursor:
    """The patent's state recursor for the inclinometer (``GatingOptions.recursor``).

    Its pseudo-innovation is taken against the attitude of the last reset carried forward by the gyro only, so a
    slow ramp the smoother follows still accumulates; every ``window`` samples the spectral test, then a restart
    from the smoother's attitude (``restart_due``).
    """

    def __init__(self, detector: EigenDetector):
        self.detector = detector  # its stride is one window: one test per window
        self.restart_due = False

    def reset(self, R_W_B: np.ndarray, cov_rotation_rad2: np.ndarray) -> None:
        self._R_W_B, self._cov_rad2 = R_W_B.copy(), cov_rotation_rad2.copy()
        self.detector.reset()

    def propagate(self, delta_R: np.ndarray, dt_s: float, gyro_noise_density: float) -> None:
        # R <- R dR  (the gyro's rotation over the keyframe),  P <- P + sigma_g^2 dt I  (its angle random walk)
        self._R_W_B = self._R_W_B @ delta_R
        self._cov_rad2 = self._cov_rad2 + gyro_noise_density**2 * dt_s * np.eye(3)

    def test(self, factor, k: int) -> tuple[float, bool] | None:
        """Add the inclinometer factor's pseudo-innovation; (lambda_max, healthy) when the window is full."""
        values = gtsam.Values()
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(self._R_W_B), np.zeros(3)))
        A, b = factor.linearize(values).jacobian()
        A = A[:, :3]
        # S = I + A P A^T = L L^T  (whitened noise + the gyro-only attitude's),  nu = L^-1 (-b)
        L = np.linalg.cholesky(np.eye(len(b)) + A @ self._cov_rad2 @ A.T)
        lam_max = self.detector.push(np.linalg.solve(L, -b))
        if lam_max is None:
            return None
        healthy = self.detector.healthy(lam_max)
        self.detector.reset()
        self.restart_due = True
        return lam_max, healthy
