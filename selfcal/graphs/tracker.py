"""The laser-tracker target as a factor graph, online (iSAM2 / fixed-lag) and offline (batch), with fault gating.

One engine, :class:`TrackerEstimator`, consumes samples in timestamp order.  IMU samples are preintegrated;
every ``keyframe_s`` a keyframe ``(X_k, V_k, B_k)`` enters with a ``CombinedImuFactor`` and the factors of
the measurements that arrived since the previous keyframe (:mod:`selfcal.factors.tracker`).

Time alignment.  A measurement taken at ``t_m`` is moved to the keyframe time ``t_k`` (0 to ``keyframe_s``
later) with the IMU-propagated motion between the two instants: the prism position and velocity by the
predicted displacement, the inclinometer's up direction and the camera bearing by the gyro's relative rotation
``dR = R(t_m)^T R(t_k)``.  Over 0.1 s these deltas are known to micrometres and microradians.

Fault gating (every decision is returned with its statistic):

1. *Chi-square gate* (hard faults: spikes, outliers, tracker jumps).  Before a factor enters, its whitened
   residual ``b`` and Jacobian ``A`` at the propagated state give the predicted residual covariance
   ``S = I + A P A^T`` (``P``: marginal covariance of the previous keyframe grown by the preintegration noise);
   ``b^T S^-1 b`` is tested against ``chi2(dim).ppf(1 - gate_alpha)``; a failing factor never enters.
2. *Eigenvalue detector* (soft faults: bias ramps, a stuck output).  The normalised residuals
   ``nu = L^-1 b`` (``S = L L^T``) of each sensor's accepted factors fill a sliding window of ``n``; every
   ``stride`` samples the largest eigenvalue of ``W = sum nu nu^T`` (m x m) is compared with the threshold
   for which a fault-free sensor (``W ~ Wishart_m(n, I)``) raises ``false_alarms_per_hour`` at most (union
   bound over the tests per hour; the quantile comes from a seeded Monte Carlo of the Bartlett decomposition,
   :func:`wishart_lambda_max_quantile`).  On detection all the sensor's factors still inside the smoother
   are removed again (``factorsToRemove``) and its new factors are held out; it is readmitted when a full
   window of its (monitored, not added) residuals passes the same test.
   Rejected inclinometer samples go to the detector too, winsorised onto the gate's boundary (unless the
   accelerometer shows vibration starting), so a ramp the gate keeps catching is declared within seconds.
   A stuck inclinometer (its output repeated exactly, ``GatingOptions.frozen_samples`` times) is held out at
   once, its recent factors removed the same way, and readmitted with its first moving sample: a working sensor's
   noise never repeats both axes, and the detector's window would take seconds to see it.
3. Vibration is modelled, not alarmed: the inclinometer factor's covariance grows with the vibration the
   accelerometer shows over a window centred on the sample (:meth:`TrackerEstimator._vibration_covariance`;
   the sample enters provisionally at once and is re-decided when the window is complete) and with the
   high-frequency energy of its own residuals (:meth:`TrackerEstimator._own_vibration`); the detector's
   residual is normalised with the energy of the samples after it too (a burst's onset).

Solvers: ``'isam2'`` (gtsam.ISAM2, the whole history), ``'fixed-lag'`` (gtsam.IncrementalFixedLagSmoother over
``lag_s``: bounded memory over hours), and :func:`batch_smooth` (the same accepted factors over all keyframes,
Gauss-Newton from the online estimates, Levenberg-Marquardt if a step fails).
"""
from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field, replace
from functools import lru_cache

import gtsam
import numpy as np
from scipy import stats

from selfcal.core import inertial
from selfcal.factors import tracker as ft
from selfcal.core.solve import DegenerateDataError, optimize
from selfcal.core import so3
from selfcal.models import tracker as mt
from selfcal.core.stats import wishart_lambda_max_quantile, wishart_lambda_min_quantile

log = logging.getLogger(__name__)

X, V, B = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B
_UP_BASIS = ft.UP_W.basis()  # (3, 2): the inclinometer factor's error is expressed on this tangent basis
SENSORS = ("tracker0", "incl0", "cam0")


@lru_cache(maxsize=64)
def _variance_ratio(dof: int, alpha: float) -> float:
    """chi2(dof).ppf(1 - alpha) / dof: a sample variance above ``white`` times this is significant at ``alpha``."""
    return float(stats.chi2.ppf(1.0 - alpha, dof) / dof)


@dataclass
class SensorNoise:
    """Per-sample sigmas and geometry of the target (from sensor.yaml; defaults = the simulator's)."""

    tracker_sigma_m: float = 0.5e-3
    tracker_velocity_sigma_m_s: float = 2e-3
    incl_sigma_rad: float = 8.7e-5
    incl_average_s: float = 0.02  # the inclinometer's own averaging of the specific force before each sample
    cam_sigma_px: float = 0.2
    r_P_B: np.ndarray = field(default_factory=lambda: np.array([0.12, -0.05, 0.25]))
    r_C_B: np.ndarray = field(default_factory=lambda: np.array([0.10, 0.03, 0.20]))
    R_B_C: np.ndarray = field(default_factory=lambda: np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]))
    camera_matrix: np.ndarray = field(default_factory=lambda: np.array([[1200.0, 0, 320.0], [0, 1200.0, 240.0],
                                                                        [0, 0, 1.0]]))
    dist_coeffs: np.ndarray = field(default_factory=lambda: np.zeros(5))
    tracker_W: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_noise_density: float = 1.7e-4
    accel_noise_density: float = 2e-3
    gyro_random_walk: float = 1.6e-5
    accel_random_walk: float = 1.6e-4
    imu_rate_hz: float = 200.0
    gravity_m_s2: float = 9.80665

    @property
    def cam_sigma_rad(self) -> float:
        return self.cam_sigma_px / float(self.camera_matrix[0, 0])


@dataclass(frozen=True)
class GatingOptions:
    chi2: bool = True  # hard-fault gate
    eigen: bool = True  # soft-fault detector
    gate_alpha: float = 1e-4  # per-factor probability of rejecting a good measurement
    window: int = 30  # eigen detector window n (inclinometer samples)
    stride_s: float = 1.0  # time between eigen tests of one sensor
    false_alarms_per_hour: float = 1.0  # stated rate, per sensor (union bound)
    vibration_inflation: bool = True  # inclinometer covariance grown by the vibration the accelerometer shows
    vibration_window_s: float = 0.5  # accelerometer history the vibration is measured over
    vibration_alpha: float = 0.01  # significance of the excess accelerometer energy before it inflates anything
    # a rejected inclinometer sample is kept from the soft-fault detector when the accelerometer shows energy
    # above its white noise at this loose level: a burst's onset (the first ~0.5 s, before the vibration is
    # significant at vibration_alpha) rejects a few samples, which must not add up to a soft fault
    vibration_hint_alpha: float = 0.2
    diff_window: int = 10  # inclinometer residual differences whose median measures its own vibration
    diff_ratio: float = 2.5  # their median over its null value before it inflates (P = 0.7 % without vibration)
    # the soft-fault detector's residuals are normalised with the larger of that and the vibration the next
    # ``onset_window`` differences show (a burst's onset, which the accelerometer cannot see yet and the previous
    # differences see a second late), median over its null value above ``onset_ratio`` (P = 1 %: median of 3
    # exponentials, binomial tail); the factor's own noise stays causal.  3 samples: the decision (and the
    # soft-fault test) waits 0.35 s for them
    onset_window: int = 3
    onset_ratio: float = 4.09
    max_consecutive_rejects: int = 20  # then the sensor is readmitted (the state, not it, is judged wrong)
    # a held-out inclinometer whose residuals keep their noise (not stuck) is readmitted after this long: a slow
    # ramp the state followed (tilt and accelerometer bias are one combination for everything but the
    # inclinometer) leaves the state off when the ramp ends, and the good sensor then disagrees with it for ever
    max_holdout_s: float = 60.0
    max_grace_s: float = 20.0  # longest ungated, unaccusable spell after such a readmission
    # a slow inclinometer ramp can be followed by the state without residuals: the smoother tilts and lets the
    # accelerometer bias absorb g x tilt, straining the bias's random walk instead.  The bias increments of the
    # last ``bias_drift_window`` keyframes, normalised by the random walk, summed / sqrt(n) on the horizontal
    # body axes: above ``bias_drift_z`` (fault-free runs with vibration: max ~4 over 600 s; a 0.01 deg/s ramp:
    # 8-19) the inclinometer is declared faulty
    bias_drift_window: int = 30
    bias_drift_z: float = 6.0
    bias_drift_settle_s: float = 30.0  # the bias converges first
    # after a hold-out ends the readmitted inclinometer pulls tilt and accelerometer bias back together: seconds of
    # legitimate bias motion (measured: a bias-drift alarm 5 s after a recovery, on a good sensor)
    bias_drift_resettle_s: float = 10.0
    # the patent's state recursor for the inclinometer (off: with a MEMS gyro, 1.7e-4 rad/sqrt(s), the
    # gyro-only attitude over a 3 s window wanders ~3 inclinometer sigmas, its pseudo-innovations are strongly
    # correlated and the Wishart threshold does not hold: measured false alarms every few seconds)
    recursor: bool = False
    # a stuck inclinometer repeats its last output exactly; a working one cannot, its noise (0.005 deg) being larger
    # than its resolution: with noise sigma >= the step q, both axes repeat with P <= (q / (2 sqrt(pi) sigma))^2
    # = 0.08 per sample, so 10 in a row (1 s at 10 Hz) is a false alarm every 10^6 h.  0 switches the test off
    # (a sensor quantised coarser than its noise repeats honestly)
    frozen_samples: int = 10


UNGATED = GatingOptions(chi2=False, eigen=False, frozen_samples=0)  # every sample enters (the vibration model stays)


@dataclass(frozen=True)
class TrackerOptions:
    keyframe_s: float = 0.1
    lag_s: float = 5.0  # longer than the detection window, so a detected soft fault's factors can be removed
    mode: str = "fixed-lag"  # 'fixed-lag' | 'isam2'
    gating: GatingOptions = GatingOptions()
    keep_graph: bool = False  # keep every factor and keyframe for batch_smooth (memory grows with the run)
    covariance: bool = True  # marginal covariance per output (needed by the gate's P as well)
    initial_gyro_bias_sigma: float = 5e-3
    initial_accel_bias_sigma: float = 0.05


class EigenDetector:
    """Extreme eigenvalues of the windowed sum of outer products of normalised residuals (m-dimensional)."""

    last_min = np.inf

    def __init__(self, m: int, options: GatingOptions, rate_hz: float):
        self.m, self.n, self.stride = m, options.window, max(1, int(round(options.stride_s * rate_hz)))
        tests_per_hour = 3600.0 * rate_hz / self.stride
        self.alpha = min(0.5, options.false_alarms_per_hour / tests_per_hour)
        # two-sided spectral test, alpha split evenly: too much residual energy in one direction (bias, ramp,
        # outliers) or too little (a stuck output has no noise and drags the state along with it)
        self.threshold = wishart_lambda_max_quantile(m, self.n, round(self.alpha / 2, 12))
        self.lower = wishart_lambda_min_quantile(m, self.n, round(self.alpha / 2, 12))
        self.window: deque = deque(maxlen=self.n)
        self.inflated: deque = deque(maxlen=self.n)  # was the sample's noise grown by measured vibration?
        self.count = 0

    def push(self, nu: np.ndarray, inflated: bool = False) -> float | None:
        """Add one normalised residual; the statistic when a test is due (full window, every stride), else None."""
        self.window.append(np.asarray(nu, dtype=float))
        self.inflated.append(bool(inflated))
        self.count += 1
        if len(self.window) < self.n or self.count % self.stride:
            return None
        Y = np.array(self.window)
        eig = np.linalg.eigvalsh(Y.T @ Y)
        self.last_min = float(eig[0])
        return float(eig[-1])

    def healthy(self, lam_max: float) -> bool:
        """The last test passed.  The lower side (no noise left: a stuck output) is tested only on windows
        whose noise was not grown by measured vibration: an estimated vibration variance (+-30 % from 0.5 s of
        accelerometer) makes ``lambda_min`` meaningless."""
        return lam_max <= self.threshold and (self.last_min >= self.lower or any(self.inflated))

    def certifies_recovery(self, lam_max: float) -> bool:
        """Readmission needs a window passing both sides (an over-estimated vibration makes the lower side
        harder to pass, never easier) in which at most a third of the residuals had their noise grown by
        vibration: residuals drowned in vibration cannot show that an offset has gone."""
        return lam_max <= self.threshold and self.last_min >= self.lower and sum(self.inflated) <= self.n // 3

    def reset(self) -> None:
        self.window.clear()
        self.inflated.clear()
        self.count = 0


@dataclass
class _Pending:
    sensor: str
    t_ns: int
    z: np.ndarray
    nav: gtsam.NavState  # propagated state at the measurement
    extra: np.ndarray | None = None  # velocity for the tracker, body rate for the velocity factor


def _inverse_cholesky(S: np.ndarray) -> np.ndarray:
    """``L^-1`` with ``S = L L^T`` (Cholesky), closed form for 3x3 (numpy's cholesky + inv cost ~30 us)."""
    if S.shape != (3, 3):
        return np.linalg.inv(np.linalg.cholesky(S))
    (s00, s01, s02), (_, s11, s12), (_, _, s22) = S.tolist()
    l00 = math.sqrt(s00)
    l10, l20 = s01 / l00, s02 / l00
    l11 = math.sqrt(s11 - l10 * l10)
    l21 = (s12 - l20 * l10) / l11
    l22 = math.sqrt(s22 - l20 * l20 - l21 * l21)
    # forward substitution on the columns of I
    i10 = -l10 / (l00 * l11)
    i21 = -l21 / (l11 * l22)
    i20 = -(l20 / l00 + l21 * i10) / l22
    return np.array([[1.0 / l00, 0.0, 0.0], [i10, 1.0 / l11, 0.0], [i20, i21, 1.0 / l22]])


def _whiten(S: np.ndarray, r: np.ndarray) -> np.ndarray:
    """``L^-1 r`` with ``S = L L^T`` (Cholesky): the normalised residual.  Closed form for 2x2 and 3x3 (the
    online gate's sizes; numpy's cholesky + solve cost ~15 us on such matrices, ten times the arithmetic)."""
    if len(r) == 2:
        (s00, s01), (_, s11) = S.tolist()
        r0, r1 = r.tolist()
        l00 = math.sqrt(s00)
        l10 = s01 / l00
        x0 = r0 / l00
        return np.array([x0, (r1 - l10 * x0) / math.sqrt(s11 - l10 * l10)])
    if len(r) == 3:
        (s00, s01, s02), (_, s11, s12), (_, _, s22) = S.tolist()
        r0, r1, r2 = r.tolist()
        l00 = math.sqrt(s00)
        l10, l20 = s01 / l00, s02 / l00
        l11 = math.sqrt(s11 - l10 * l10)
        l21 = (s12 - l20 * l10) / l11
        l22 = math.sqrt(s22 - l20 * l20 - l21 * l21)
        x0 = r0 / l00
        x1 = (r1 - l10 * x0) / l11
        return np.array([x0, x1, (r2 - l20 * x0 - l21 * x1) / l22])
    return np.linalg.solve(np.linalg.cholesky(S), r)


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b`` (Rodrigues; a and b nearly equal)."""
    axis = mt.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-15:
        return np.eye(3)
    K = so3.hat(axis / s)
    return np.eye(3) + s * K + (1.0 - c) * K @ K


def _navstate_values(nav: gtsam.NavState, k: int) -> gtsam.Values:
    # by keyword: pybind11 then skips the ~50 overloads of Values.insert it would otherwise try to convert to
    # (20 us for a Pose3, 110 us for a ConstantBias, per insert)
    values = gtsam.Values()
    values.insert(j=X(k), pose3=nav.pose())
    values.insert(j=V(k), vector=nav.velocity())
    return values


class TrackerEstimator:
    """Online estimator: feed samples in timestamp order, get one output per keyframe.

    ``imu(t_ns, gyro, accel)``, ``tracker(t_ns, position, velocity=None)``, ``incl(t_ns, roll, pitch)``,
    ``cam(t_ns, u, v)`` each return a (possibly empty) list of outputs: ``{"t_ns", "position" (3, m),
    "quaternion" (qx, qy, qz, qw of R_W_B), "covariance" (6x6, [rotation rad, position m], world frame),
    "faults" {sensor: bool}, "decisions" [...]}``.
    """

    def __init__(self, noise: SensorNoise = SensorNoise(), options: TrackerOptions = TrackerOptions()):
        self.noise, self.options = noise, options
        g = options.gating
        params = gtsam.PreintegrationCombinedParams.MakeSharedU(noise.gravity_m_s2)
        params.setGyroscopeCovariance(noise.gyro_noise_density**2 * np.eye(3))
        params.setAccelerometerCovariance(noise.accel_noise_density**2 * np.eye(3))
        params.setIntegrationCovariance(1e-10 * np.eye(3))
        params.setBiasOmegaCovariance(noise.gyro_random_walk**2 * np.eye(3))
        params.setBiasAccCovariance(noise.accel_random_walk**2 * np.eye(3))
        self.params = params
        self._noise_models = {
            "tracker0": gtsam.noiseModel.Isotropic.Sigma(3, noise.tracker_sigma_m),
            "tracker0/velocity": gtsam.noiseModel.Isotropic.Sigma(3, noise.tracker_velocity_sigma_m_s),
            "cam0": gtsam.noiseModel.Isotropic.Sigma(2, noise.cam_sigma_rad),
            "incl0": gtsam.noiseModel.Isotropic.Sigma(2, noise.incl_sigma_rad)}
        self._chi2_threshold = {d: float(stats.chi2.ppf(1.0 - g.gate_alpha, d)) for d in (2, 3)}
        rates = {"tracker0": 50.0, "incl0": 10.0, "cam0": 10.0}
        # soft-fault detection watches the inclinometer, the sensor vibration and drift corrupt (the patent's
        # suspect): holding it out costs little (tilt then rests on the accelerometer bias, which wanders
        # slowly).  The tracker and the camera are the only sources of position and azimuth: nothing could
        # isolate a soft fault in them, and holding them out would let the state drift away from their own
        # recovery test; they are protected by the chi-square gate.
        half = replace(g, false_alarms_per_hour=g.false_alarms_per_hour / 2)  # two detectors share the rate
        self.detectors = {"incl0": EigenDetector(2, half, rates["incl0"])}
        # the recursor tests once per window (not every stride): its per-test alpha follows from that
        self.recursor = EigenDetector(2, replace(half, stride_s=g.window / rates["incl0"]), rates["incl0"])
        self._restart_recursor = False
        self.faulty = {s: False for s in SENSORS}
        self._consecutive: dict[str, int] = {}
        # (keyframe, factor index) of each sensor's factors still in the smoother: on a soft-fault alarm all of them
        # are removed, back to the lag -- a ramp the state followed for seconds before the alarm (the detection
        # delay exceeds the detector's window) would otherwise stay in the state through the whole hold-out
        self._recent = {s: deque(maxlen=3 * int(np.ceil(options.lag_s / options.keyframe_s)) + 8) for s in SENSORS}
        self.k = -1
        self.t0_ns = None
        self._last_imu = None  # (t_ns, gyro, accel)
        self._latest = {}  # sensor -> last raw sample, for initialisation
        self._pending: list[_Pending] = []
        self._decisions: list[dict] = []
        # (t_ns, prediction error (2,) rad) of every inclinometer sample at its arrival, in order: the own-vibration
        # estimates of a sample need diff_window samples before it and onset_window after it
        self._incl_residuals: deque = deque(maxlen=2 * (g.diff_window + g.onset_window) + 24)
        self._incl_up_last, self._incl_t_last, self._incl_dt_s = None, None, None
        self._vibration_hint = False
        self._fault_t_ns: dict[str, int] = {}
        self._incl_previous_up, self._frozen_count, self._frozen_fault = None, 0, False
        self._stuck_until_ns = 0  # the first moving sample after a stuck spell (samples before it are decided later)
        self._grace_until_ns: dict[str, int] = {}
        self._bias_increments: deque = deque(maxlen=g.bias_drift_window)
        self._carried_removals: list[int] = []  # factor indices to remove at the next update
        self._bias_drift_resume_ns = 0  # no bias-drift test before (re-convergence after a hold-out)
        self._bias_increment_sum = np.zeros(2)  # of _bias_increments
        # accelerometer history with stamps: the vibration window centred on an inclinometer sample decided up to
        # ~1.3 s later (its own samples after it, at >= 5 Hz), and the window after it, plus margin
        n_buf = int(round((g.vibration_window_s + 1.5 + 2 * options.keyframe_s) * noise.imu_rate_hz)) + 8
        self._acc_t = np.zeros(2 * n_buf, dtype=np.int64)  # ring kept contiguous: written twice, read as a slice
        self._acc = np.zeros((2 * n_buf, 3))
        self._acc_n, self._acc_len = 0, n_buf
        # a keyframe is due half an IMU interval before keyframe_s has passed (stamps jitter by nanoseconds)
        self._keyframe_due_ns = 1e9 * (options.keyframe_s - 0.5 / noise.imu_rate_hz)
        self._hat_r_P_B = -so3.hat(noise.r_P_B)
        self._deferred: list = []
        self._removed_indices: set = set()  # bounded: duplicates only arise within the deferral (< 1 s)
        self._removed_order: deque = deque(maxlen=4096)  # inclinometer factors waiting for the accelerometer after them
        self.counts = {"accepted": 0, "rejected": 0, "held_out": 0, "removed": 0}
        # [factor, tag, keyframe, removed, meta]: meta holds what the audit needs to rebuild the factor with
        # calibration effects (selfcal.audit.tracker)
        self.graph_log: list | None = [] if options.keep_graph else None
        self._meta: dict[int, dict] = {}  # id(factor object) -> meta, until the factor enters the graph
        self._log_position: dict[int, int] = {}  # smoother factor index -> position in graph_log
        self.keyframe_t_ns: list[int] = [] if options.keep_graph else None
        self.initial_values = gtsam.Values() if options.keep_graph else None
        self._smoother = None

    # --- input -------------------------------------------------------------------------------------------------

    def imu(self, t_ns: int, gyro, accel) -> list[dict]:
        gyro, accel = np.asarray(gyro, dtype=float), np.asarray(accel, dtype=float)
        out = []
        if self.k < 0:
            self._last_imu = (t_ns, gyro, accel)
            if self._ready():
                self._initialise(t_ns)
            return out
        t_prev, g_prev, a_prev = self._last_imu
        dt = (t_ns - t_prev) * 1e-9
        if dt <= 0:
            log.warning("imu0: sample at %d ns not after the previous one: skipped", t_ns)
            return out
        self.pim.integrateMeasurement(a_prev, g_prev, dt)
        self._last_imu = (t_ns, gyro, accel)
        i = self._acc_n % self._acc_len
        self._acc_t[i] = self._acc_t[i + self._acc_len] = t_ns
        self._acc[i] = self._acc[i + self._acc_len] = accel
        self._acc_n += 1
        if t_ns - self.kf_t_ns >= self._keyframe_due_ns:
            out.append(self._keyframe(t_ns))
        return out

    def tracker(self, t_ns: int, position, velocity=None) -> list[dict]:
        self._latest["tracker0"] = (t_ns, np.asarray(position, dtype=float),
                                    None if velocity is None else np.asarray(velocity, dtype=float))
        if self.k >= 0:
            w = self._last_imu[1] - self.bias.gyroscope()
            self._pending.append(_Pending("tracker0", t_ns, np.asarray(position, dtype=float), self._predict(),
                                          None if velocity is None else np.concatenate([velocity, w])))
        return []

    def incl(self, t_ns: int, roll: float, pitch: float) -> list[dict]:
        up = mt.up_direction_B(roll, pitch)
        self._latest["incl0"] = (t_ns, up)
        if self.k >= 0:
            self._pending.append(_Pending("incl0", t_ns, up, self._predict()))
        return []

    def cam(self, t_ns: int, u: float, v: float) -> list[dict]:
        bearing = mt.bearing_from_pixel(np.array([u, v]), self.noise.camera_matrix, self.noise.dist_coeffs)[0]
        self._latest["cam0"] = (t_ns, bearing)
        if self.k >= 0:
            self._pending.append(_Pending("cam0", t_ns, bearing, self._predict()))
        return []

    # --- internals ---------------------------------------------------------------------------------------------

    def _ready(self) -> bool:
        return "tracker0" in self._latest and "incl0" in self._latest and "cam0" in self._latest

    def _predict(self) -> gtsam.NavState:
        return self.pim.predict(self.nav, self.bias)

    def _initialise(self, t_ns: int) -> None:
        """First keyframe from the latest samples: tilt (inclinometer), azimuth (beam), position (tracker)."""
        n = self.noise
        _, p_P, v_P = self._latest["tracker0"]
        _, up_B = self._latest["incl0"]
        _, bearing_C = self._latest["cam0"]
        roll, pitch = inertial.tilt_from_specific_force(up_B)
        beam_W = n.tracker_W - p_P
        R = mt.attitude_from_tilt_and_beam(float(roll), float(pitch), n.R_B_C @ bearing_C, beam_W / np.linalg.norm(beam_W))
        p = p_P - R @ n.r_P_B
        v = v_P if v_P is not None else np.zeros(3)
        self.t0_ns = t_ns
        self.kf_t_ns = t_ns
        self.k = 0
        self.nav = gtsam.NavState(gtsam.Rot3(R), p, v)
        self.bias = gtsam.imuBias.ConstantBias()
        self.pim = gtsam.PreintegratedCombinedMeasurements(self.params, self.bias)
        graph = gtsam.NonlinearFactorGraph()
        o = self.options
        graph.add(gtsam.PriorFactorPose3(X(0), self.nav.pose(), gtsam.noiseModel.Diagonal.Sigmas(
            np.array([2e-3, 2e-3, 5e-3, 0.01, 0.01, 0.01]))))
        graph.add(gtsam.PriorFactorVector(V(0), v, gtsam.noiseModel.Isotropic.Sigma(3, 0.02)))
        graph.add(gtsam.PriorFactorConstantBias(B(0), self.bias, gtsam.noiseModel.Diagonal.Sigmas(
            np.array([o.initial_accel_bias_sigma] * 3 + [o.initial_gyro_bias_sigma] * 3))))
        values = _navstate_values(self.nav, 0)
        values.insert(B(0), self.bias)
        if o.mode == "fixed-lag":
            params = gtsam.ISAM2Params()
            params.setRelinearizeThreshold(0.01)
            self._smoother = gtsam.IncrementalFixedLagSmoother(o.lag_s, params)
        elif o.mode == "isam2":
            params = gtsam.ISAM2Params()
            params.setRelinearizeThreshold(0.01)
            self._smoother = gtsam.ISAM2(params)
        else:
            raise ValueError(f"unknown mode {o.mode!r}: 'fixed-lag' or 'isam2'")
        self._update(graph, values, [None] * graph.size(), 0)
        self._P_pose = np.diag(np.array([2e-3, 2e-3, 5e-3, 0.01, 0.01, 0.01]) ** 2)
        self._P_vel = 0.02**2 * np.eye(3)
        self._recursor_reset(self.nav.attitude().matrix(), self._P_pose[:3, :3])
        if self.keyframe_t_ns is not None:
            self.keyframe_t_ns.append(t_ns)
            self.initial_values.insert(values)

    def _remember(self, factor, **meta):
        """Keep the measurement behind a factor for the audit (only when the graph is kept)."""
        if self.graph_log is not None:
            self._meta[id(factor)] = meta
        return factor

    def _update(self, graph, values, tags, k, to_remove=(), metas=None):
        """One smoother update (new keyframe, its factors, factors to remove); remembers the new indices."""
        to_remove = [i for i in dict.fromkeys(to_remove) if i not in self._removed_indices]
        for i in to_remove:  # a factor may be named twice (fault window, provisional replaced): removed once
            if len(self._removed_order) == self._removed_order.maxlen:
                self._removed_indices.discard(self._removed_order[0])
            self._removed_order.append(i)
            self._removed_indices.add(i)
        if to_remove:
            self.counts["removed"] += len(to_remove)
            if self.graph_log is not None:
                for idx in to_remove:
                    self.graph_log[self._log_position[idx]][3] = True
        if self.options.mode == "fixed-lag":
            stamps = {key: (self.kf_t_ns - self.t0_ns) * 1e-9 for key in (X(k), V(k), B(k))}
            self._smoother.update(graph, values, stamps, to_remove)
            indices = self._smoother.getISAM2Result().getNewFactorsIndices()
        else:
            indices = self._smoother.update(graph, values, to_remove).getNewFactorsIndices()
        for i, (idx, tag) in enumerate(zip(indices, tags)):
            if tag is not None and tag.split("/")[0] in self._recent:
                self._recent[tag.split("/")[0]].append((k, int(idx)))
            if self.graph_log is not None:
                self._log_position[int(idx)] = len(self.graph_log)
                self.graph_log.append([graph.at(i), tag, k, False, metas[i] if metas else None])
        return indices

    def _estimate(self, k):
        s = self._smoother  # per key: calculateEstimate() would build every variable of the lag
        return s.calculateEstimatePose3(X(k)), s.calculateEstimateVector(V(k)), s.calculateEstimateConstantBias(B(k))

    def _vibration_covariance(self, R_W_B: np.ndarray, t_ns: int) -> np.ndarray | None:
        """Extra covariance (2x2, rad^2, in the inclinometer factor's error coordinates) of the inclinometer from
        the vibration the accelerometer itself shows, or None when it shows none.

        The inclinometer reads the direction of the specific force averaged over ``incl_average_s``; its error is
        the horizontal part of that average over g.  The accelerometer sees the same force: its last
        ``vibration_window_s`` of samples centred on the inclinometer's sample time ``t_ns`` (its factor waits
        half a window for them: the accelerometer sees a burst's onset only as it happens), averaged in blocks
        of the inclinometer's own length (the same low-pass),
        give m block means whose horizontal components (perpendicular to the predicted up, body frame) have the
        sample covariance ``C``; without vibration ``C ~ sigma_w^2 Wishart_2(m - 1) / (m - 1)`` with
        ``sigma_w^2 = accel_noise_density^2 rate / n_avg``.  When ``trace C`` exceeds its white-noise level at
        ``vibration_alpha``, the excess ``C - sigma_w^2 I`` (eigenvalues clipped at 0) over g^2 is the tilt
        disturbance's covariance, anisotropic as the vibration is, rotated into the factor's error coordinates
        (the tangent basis of the world's up: ``e = basis^T R_W_B d_B``).  ``| |f| - g |`` (the ship system's
        disturbance measure) is not used: it is mostly the vertical part, which does not tilt the reading.
        """
        g, n = self.options.gating, self.noise
        self._vibration_hint = False
        if not g.vibration_inflation:
            return None
        n_avg = max(1, int(round(n.incl_average_s * n.imu_rate_hz)))
        half_ns = 0.5e9 * g.vibration_window_s
        start = self._acc_n % self._acc_len if self._acc_n >= self._acc_len else 0
        count = min(self._acc_n, self._acc_len)
        stamps = self._acc_t[start:start + count]  # oldest first
        lo, hi = np.searchsorted(stamps, [t_ns - half_ns, t_ns + half_ns], side="left")
        acc = self._acc[start + lo:start + hi]
        m = len(acc) // n_avg
        if m < 3:
            return None
        acc = acc[:m * n_avg].reshape(m, n_avg, 3).sum(axis=1)  # n_avg times the block means
        ux, uy, uz = R_W_B[2].tolist()  # up in the body, R_W_B^T e_z
        # horizontal orthonormal basis of the body frame: body x made horizontal (tilts are small), up x that
        h1 = np.array([1.0 - ux * ux, -ux * uy, -ux * uz])
        h1 /= math.sqrt(h1 @ h1)
        H = np.column_stack([h1, mt.cross(np.array([ux, uy, uz]), h1)]) / n_avg
        h = acc @ H
        h -= h.sum(axis=0) / m
        C = h.T @ h / (m - 1)
        white = n.accel_noise_density**2 * n.imu_rate_hz / n_avg
        (c00, c01), (_, c11) = C.tolist()
        ratio = (c00 + c11) / (2 * white)
        self._vibration_hint = ratio > _variance_ratio(2 * (m - 1), g.vibration_hint_alpha)
        if ratio <= _variance_ratio(2 * (m - 1), g.vibration_alpha):
            return None
        # the excess over the white noise along C's principal axes (2x2 eigen-decomposition in closed form)
        mean, dev = 0.5 * (c00 + c11), math.hypot(0.5 * (c00 - c11), c01)
        lam1, lam2 = max(mean + dev - white, 0.0), max(mean - dev - white, 0.0)
        angle = 0.5 * math.atan2(2 * c01, c00 - c11)
        u = np.array([math.cos(angle), math.sin(angle)])
        v = np.array([-u[1], u[0]])
        C_B = (lam1 * np.outer(u, u) + lam2 * np.outer(v, v)) / n.gravity_m_s2**2
        M = _UP_BASIS.T @ R_W_B @ H * n_avg
        return M @ C_B @ M.T

    def _own_vibration(self, t_ns: int, ahead: bool = False) -> float:
        """Vibration variance per axis (rad^2) the inclinometer's own residuals show at its sample ``t_ns``: from
        the ``diff_window`` differences up to the sample, or (``ahead``) the ``onset_window`` after it; 0 when
        not significant.

        Below ~1e-3 rad the accelerometer (white noise ~16 inclinometer sigmas per averaged block) cannot see
        vibration the inclinometer feels.  The inclinometer's own prediction errors, differenced between
        consecutive samples, show it: vibration at 3-25 Hz sampled at 10 Hz is nearly white there, while a soft
        fault (offset, ramp, stuck output) is slow and cancels in the difference.  Without vibration
        ``|d|^2 ~ v0 chi2(2)``, ``v0 = 2 sigma^2 + gyro noise over the sample interval`` per axis, median
        ``2 ln 2 v0``; the median of the window (a spike moves it little) above ``diff_ratio`` (``onset_ratio``)
        times that gives the excess ``(median / ln 4 - v0) / 2`` per axis.  The differences after the sample
        matter at a burst's onset: its envelope rises within a second (``u^4 (1-u)^4``), so the first samples it
        tilts have only the differences after them in the burst -- normalised by the previous ones alone, their
        rejects and 5-sigma residuals added up to false soft-fault alarms (5 of the 6 per hour with bursts).
        """
        g, n = self.options.gating, self.noise
        buf = self._incl_residuals
        w, ratio = (g.onset_window, g.onset_ratio) if ahead else (g.diff_window, g.diff_ratio)
        stamps = [t for t, _ in buf]
        if t_ns not in stamps:
            return 0.0
        i = stamps.index(t_ns)
        lo, hi = (i, i + w) if ahead else (i - w, i)
        if lo < 0 or hi >= len(buf):
            return 0.0
        d = np.diff(np.array([buf[j][1] for j in range(lo, hi + 1)]), axis=0)
        rate = 10.0 if self._incl_dt_s is None else 1.0 / self._incl_dt_s
        v0 = 2 * n.incl_sigma_rad**2 + n.gyro_noise_density**2 / rate
        d2 = sorted(np.einsum("ij,ij->i", d, d).tolist())  # a few values: np.median costs ~40 us
        med = 0.5 * (d2[(w - 1) // 2] + d2[w // 2])
        if med <= ratio * v0 * 2 * np.log(2):
            return 0.0
        return 0.5 * (med / (2 * np.log(2)) - v0)

    def _with_own_vibration(self, factor, excess: float, incl_cov: np.ndarray | None, up_B: np.ndarray):
        """The inclinometer factor with its covariance grown by the vibration variance ``excess`` (rad^2 per axis,
        :meth:`_own_vibration`, isotropic), unless the accelerometer's estimate is already larger."""
        n = self.noise
        if not self.options.gating.vibration_inflation or excess <= 0.0:
            return factor
        base = np.zeros((2, 2)) if incl_cov is None else incl_cov
        if excess <= 0.5 * np.trace(base):
            return factor
        cov = n.incl_sigma_rad**2 * np.eye(2) + base + (excess - 0.5 * np.trace(base)) * np.eye(2)
        return ft.inclinometer_factor(gtsam.noiseModel.Gaussian.Covariance(cov), factor.keys()[0], up_B)

    def _provisional_inclinometer(self, t_m: int, k: int, values: gtsam.Values, P_blocks: dict, t_ns: int) -> list:
        """An inclinometer sample enters at once, provisionally, with the vibration of the last window (causal),
        when it passes the chi-square gate: the online pose then has it without delay.  Its decision proper waits
        for the centred window (:meth:`_deferred_inclinometer`), which keeps it, re-weights it or removes it."""
        entry = {"t": t_m, "k": k, "up": self._incl_up_last, "index": None, "values": values, "P": P_blocks}
        self._deferred.append(entry)
        nominal = ft.inclinometer_factor(self._noise_models["incl0"], X(k), entry["up"])
        self._incl_residuals.append((t_m, np.asarray(nominal.unwhitenedError(values))))
        if self.faulty["incl0"] or not self.options.gating.vibration_inflation:
            return []
        R = values.atPose3(X(k)).rotation().matrix()
        cov = self._vibration_covariance(R, t_ns - int(0.5e9 * self.options.gating.vibration_window_s))
        factor = nominal if cov is None else self._incl_factor(k, entry["up"], cov)
        stat, _ = self._innovation(factor, values, P_blocks)
        if self.options.gating.chi2 and stat > self._chi2_threshold[2]:
            return []
        entry["index"], entry["cov"] = -1, cov  # -1: index known after the smoother update
        if self.graph_log is not None:  # the audit's record (batch runs only)
            self._remember(factor, t_ns=t_m, up_B=entry["up"], cov=self._incl_cov(cov),
                           f_B=self._mean_specific_force(t_m))
        return [(factor, "incl0/provisional")]

    def _incl_cov(self, cov: np.ndarray | None, factor=None) -> np.ndarray:
        """The inclinometer factor's whole covariance (2x2, rad^2, world up's tangent basis)."""
        if factor is not None:
            R = factor.noiseModel().R()
            return np.linalg.inv(R.T @ R)
        return self.noise.incl_sigma_rad**2 * np.eye(2) + (0.0 if cov is None else cov)

    def _mean_specific_force(self, t_ns: int) -> np.ndarray:
        """Accelerometer mean over the inclinometer's averaging window before ``t_ns`` (bias not removed)."""
        n_avg = max(1, int(round(self.noise.incl_average_s * self.noise.imu_rate_hz)))
        start = self._acc_n % self._acc_len if self._acc_n >= self._acc_len else 0
        stamps = self._acc_t[start:start + min(self._acc_n, self._acc_len)]
        hi = int(np.searchsorted(stamps, t_ns, side="left"))
        return self._acc[start + max(hi - n_avg, 0):start + max(hi, 1)].mean(axis=0)

    def _incl_factor(self, k: int, up_B: np.ndarray, cov: np.ndarray | None):
        noise = self._noise_models["incl0"] if cov is None else gtsam.noiseModel.Gaussian.Covariance(
            self.noise.incl_sigma_rad**2 * np.eye(2) + cov)
        return ft.inclinometer_factor(noise, X(k), up_B)

    def _incl_deferral_s(self) -> float:
        """How long an inclinometer sample's decision waits: for the accelerometer window centred on it and for
        ``onset_window`` of its own samples after it (0 without the vibration model)."""
        g = self.options.gating
        if not g.vibration_inflation:
            return 0.0
        return max(0.5 * g.vibration_window_s, (g.onset_window + 0.5) * (self._incl_dt_s or 0.1))

    def _deferred_inclinometer(self, t_ns: int, k: int, values: gtsam.Values, P_blocks: dict) -> list:
        """Gate the inclinometer samples whose centred vibration window is complete (see
        :meth:`_vibration_covariance`); each factor stays on the keyframe it arrived at, its innovation is the
        one predicted at its arrival."""
        half_ns = 1e9 * self._incl_deferral_s()
        ready = [d for d in self._deferred if d["t"] + half_ns <= t_ns]
        self._deferred = [d for d in self._deferred if d["t"] + half_ns > t_ns]
        out = []
        if not ready:
            return out
        for d in ready:
            # the innovation against the prediction at its arrival (before the sample, provisional or not,
            # entered), with the noise of the centred window
            t_m, km, up, vals, P = d["t"], d["k"], d["up"], d.pop("values"), d.pop("P")
            R = vals.atPose3(X(km)).rotation().matrix()
            cov = self._vibration_covariance(R, t_m)
            base = self._incl_factor(km, up, cov)
            causal = self._own_vibration(t_m)
            factor = self._with_own_vibration(base, causal, cov, up)
            stat, nu = self._innovation(factor, vals, P)
            if self.options.gating.eigen and self.options.gating.recursor:
                self._recursor_test(factor, km, t_m)
            nominal = cov is None and factor is base
            # the soft-fault detector's residual: normalised with the vibration the samples after it show too, when
            # the accelerometer after it (up to 0.5 s, as far as it has arrived) corroborates (energy above its
            # white noise at the loose hint level): a fault's own transients (the state lurching after a ramp) must
            # not excuse it
            monitor = None
            onset = self._own_vibration(t_m, ahead=True) if self.options.gating.eigen else 0.0
            if onset > causal:
                hint = self._vibration_hint
                self._vibration_covariance(R, t_m + int(0.5e9 * self.options.gating.vibration_window_s))
                ahead, self._vibration_hint = self._vibration_hint, hint
                grown = self._with_own_vibration(base, onset, cov, up) if ahead else factor
                if grown is not factor:
                    monitor = self._innovation(grown, vals, P) + (True,)
            keep = self._gate("incl0", t_m, stat, nu, k, inflated=not nominal, excused=self._vibration_hint,
                              monitor=monitor)
            if d["index"] is not None:
                unchanged = nominal and d["cov"] is None
                if keep and unchanged:
                    continue  # the provisional factor stands as it is
                self._to_remove.append(d["index"])
            if keep:
                if self.graph_log is not None:  # the audit's record (batch runs only)
                    self._remember(factor, t_ns=t_m, up_B=up, cov=self._incl_cov(cov, factor),
                                   f_B=self._mean_specific_force(t_m))
                out.append((factor, "incl0"))
        return out

    def _factor_for(self, m: _Pending, k: int, nav_k: gtsam.NavState):
        """The measurement moved to keyframe k (see module docstring), as GTSAM factors (and their tags)."""
        n = self.noise
        R_m, R_k = m.nav.attitude().matrix(), nav_k.attitude().matrix()
        if m.sensor == "tracker0":
            shift = (nav_k.position() + R_k @ n.r_P_B) - (m.nav.position() + R_m @ n.r_P_B)
            factors = [(ft.prism_position_factor(self._noise_models["tracker0"], X(k), m.z + shift, n.r_P_B),
                        "tracker0")]
            if m.extra is not None:
                v_meas, w = m.extra[:3] + (nav_k.velocity() - m.nav.velocity()), m.extra[3:]
                factors.append((ft.prism_velocity_factor(self._noise_models["tracker0/velocity"], X(k), V(k),
                                                         v_meas, w, n.r_P_B), "tracker0/velocity"))
            return factors
        dR = R_m.T @ R_k
        if m.sensor == "incl0":
            noise = self._noise_models["incl0"]
            self._incl_up_last = dR.T @ m.z
            if self._incl_t_last is not None:
                self._incl_dt_s = (m.t_ns - self._incl_t_last) * 1e-9
            self._incl_t_last = m.t_ns
            return [(ft.inclinometer_factor(noise, X(k), self._incl_up_last), "incl0")]
        # the beam's bearing changes with the rotation AND the translation between the two instants (a target
        # moving 0.1 m/s at 30 m turns the beam by 3e-4 rad in 0.1 s): the measured bearing is turned by the
        # rotation that takes the bearing predicted at the measurement to the one predicted at the keyframe
        b_m = mt.beam_direction_C(R_m, m.nav.position(), n.r_C_B, n.R_B_C, n.tracker_W)
        b_k = mt.beam_direction_C(R_k, nav_k.position(), n.r_C_B, n.R_B_C, n.tracker_W)
        bearing = _rotation_between(b_m / np.linalg.norm(b_m), b_k / np.linalg.norm(b_k)) @ m.z
        return [(ft.beam_bearing_factor(self._noise_models["cam0"], X(k), bearing, n.r_C_B, n.R_B_C, n.tracker_W),
                 "cam0")]

    def _innovation(self, factor, values, P_blocks):
        """(statistic, normalised residual) of a factor at the propagated state with covariance P."""
        A, b = factor.linearize(values).jacobian()
        keys = factor.keys()
        if len(keys) == 1:  # a pose factor (inclinometer, camera)
            P = P_blocks["x"]
        else:
            P = np.zeros((A.shape[1], A.shape[1]))
            col = 0
            for key in keys:
                Pk = P_blocks[chr(gtsam.Symbol(key).chr())]
                d = Pk.shape[0]
                P[col:col + d, col:col + d] = Pk
                col += d
        S = A @ P @ A.T
        S.flat[::len(b) + 1] += 1.0  # + I: whitened measurement noise
        nu = _whiten(S, -b)
        return float(nu @ nu), nu

    def _gate(self, tag: str, t_ns: int, stat: float, nu: np.ndarray, k: int, inflated: bool = False,
              excused: bool = False, monitor: tuple | None = None) -> bool:
        """Chi-square gate and eigenvalue detector for one measurement; logs the decision; True = add it.

        ``monitor`` = (statistic, normalised residual, inflated) for the soft-fault detector when it differs
        from the factor's (see ``GatingOptions.onset_window``)."""
        gating = self.options.gating
        m_stat, m_nu, m_inflated = monitor if monitor is not None else (stat, nu, inflated)
        sensor = tag.split("/")[0]
        dof = len(nu)
        threshold = self._chi2_threshold[dof]
        decision = {"t_ns": int(t_ns), "sensor": tag, "test": "chi2", "statistic": stat, "dof": dof,
                    "threshold": threshold}
        detector = self.detectors.get(tag)
        self._decisions_now.append(decision)
        # a stuck inclinometer is readmitted by the stuck-output test alone, from its first moving sample on
        stuck = sensor == "incl0" and (self._frozen_fault or t_ns < self._stuck_until_ns)
        if self.faulty[sensor] or stuck:
            decision["decision"] = "held_out"
            self.counts["held_out"] += 1
            if detector is not None and not stuck:  # monitored while held out: readmitted when a window looks healthy
                lam = detector.push(m_nu, m_inflated)
                held_s = (t_ns - self._fault_t_ns.get(sensor, t_ns)) * 1e-9
                healthy = lam is not None and detector.certifies_recovery(lam)
                if healthy or (lam is not None and held_s > gating.max_holdout_s
                               and detector.last_min >= detector.lower):
                    self.faulty[sensor] = False
                    detector.reset()
                    outcome = "recovered" if healthy else "readmitted_after_holdout"
                    self._bias_drift_resume_ns = int(t_ns + 1e9 * gating.bias_drift_resettle_s)
                    if not healthy:  # the state is off: the sensor's samples enter ungated until it has come back
                        self._grace_until_ns[sensor] = int(t_ns + 1e9 * gating.max_grace_s)
                    self._decisions_now.append({"t_ns": int(t_ns), "sensor": tag, "test": "eigen", "statistic": lam,
                                                "threshold": detector.threshold, "lambda_min": detector.last_min,
                                                "lower_threshold": detector.lower, "decision": outcome,
                                                "held_out_s": held_s})
                    log.info("%s %s after %.0f s (lambda_max %.1f vs %.1f)", tag, outcome, held_s, lam,
                             detector.threshold)
            return False
        monitored = gating.eigen and detector is not None
        if t_ns < self._grace_until_ns.get(sensor, 0):
            # readmitted after a long hold-out: it has to pull the state back (tilt and accelerometer bias
            # together, against the bias's random walk: seconds), so it is not gated and cannot be accused until a
            # window of its residuals looks healthy again (or max_grace_s has passed)
            decision["decision"] = "accept_grace"
            self.counts["accepted"] += 1
            if detector is not None:
                lam = detector.push(m_nu, m_inflated)
                if lam is not None and detector.healthy(lam):
                    del self._grace_until_ns[sensor]
            return True
        if gating.chi2 and stat > threshold:
            self._consecutive[tag] = self._consecutive.get(tag, 0) + 1
            if monitored:
                # a rejected sample still goes to the soft-fault detector, shrunk onto the gate's boundary
                # (winsorised: a lone spike adds at most the threshold to the window, while a run of rejects -- a
                # ramp or an offset the gate keeps catching -- fills the window and raises the alarm within
                # seconds); hiding rejects from it would leave a soft fault to the gate alone
                decision["decision"] = "reject"
                self.counts["rejected"] += 1
                if excused:  # the accelerometer shows vibration starting: the reject is not evidence of a fault
                    decision["vibration"] = True
                else:
                    if monitor is not None and m_stat <= threshold:
                        decision["vibration"] = True  # the samples after it show a burst starting
                    self._monitor(tag, detector, m_nu * np.sqrt(min(1.0, threshold / m_stat)), t_ns, k, m_inflated)
                return False
            if self._consecutive[tag] <= gating.max_consecutive_rejects:
                decision["decision"] = "reject"
                self.counts["rejected"] += 1
                return False
            # an unmonitored sensor (tracker, camera: sole sources of position and azimuth) rejected for so long
            # is more likely right than the state: the state has drifted away and only this sensor can bring it
            # back
            decision["decision"] = "accept_after_rejects"
            self._consecutive[tag] = 0
        else:
            self._consecutive[tag] = 0
            decision["decision"] = "accept"
        self.counts["accepted"] += 1
        if monitored:
            self._monitor(tag, detector, m_nu, t_ns, k, m_inflated)
        return True

    def _monitor(self, tag: str, detector: EigenDetector, nu: np.ndarray, t_ns: int, k: int,
                 inflated: bool = False) -> None:
        """Feed the soft-fault detector; on an alarm hold the sensor out and remove its recent factors."""
        sensor = tag.split("/")[0]
        lam = detector.push(nu, inflated)
        if lam is not None and not detector.healthy(lam) and not any(self.faulty.values()):
            self._declare_fault(tag, t_ns, k, {"test": "eigen", "statistic": lam, "threshold": detector.threshold,
                                               "lambda_min": detector.last_min, "lower_threshold": detector.lower})
            log.info("%s soft fault (lambda_max %.1f vs %.1f, lambda_min %.2f vs %.2f)", tag, lam,
                     detector.threshold, detector.last_min, detector.lower)

    def _declare_fault(self, tag: str, t_ns: int, k: int, test: dict) -> None:
        """Hold ``tag``'s sensor out and remove its factors still in the smoother; log ``test`` as the decision."""
        # single-fault assumption: while one sensor is held out the others' residuals carry its pull on the
        # state, so their windows restart instead of accusing them in cascade
        sensor = tag.split("/")[0]
        self.faulty[sensor] = True
        self._fault_t_ns[sensor] = int(t_ns)
        for d in self.detectors.values():
            d.reset()
        self._decisions_now.append({"t_ns": int(t_ns), "sensor": tag, **test, "decision": "fault"})
        self._to_remove.extend(self._removable(sensor, k))

    def _frozen_check(self, t_ns: int, up_B: np.ndarray, k: int) -> None:
        """The inclinometer's stuck-output test (``GatingOptions.frozen_samples``): held out when its output
        repeats exactly that many times, readmitted (to the chi-square gate) as soon as it moves again."""
        n = self.options.gating.frozen_samples
        if not n:
            return
        same = self._incl_previous_up is not None and np.array_equal(up_B, self._incl_previous_up)
        self._incl_previous_up = up_B
        self._frozen_count = self._frozen_count + 1 if same else 0
        if self._frozen_count == n and not any(self.faulty.values()):
            self._declare_fault("incl0", t_ns, k, {"test": "frozen", "statistic": n, "threshold": n})
            self._frozen_fault = True
            log.info("incl0 stuck: %d identical outputs", n + 1)
        elif not same and self._frozen_fault:
            self._frozen_fault = False
            self._stuck_until_ns = int(t_ns)
            self.faulty["incl0"] = False
            for d in self.detectors.values():
                d.reset()
            held_s = (t_ns - self._fault_t_ns["incl0"]) * 1e-9
            self._bias_drift_resume_ns = int(t_ns + 1e9 * self.options.gating.bias_drift_resettle_s)
            self._decisions_now.append({"t_ns": int(t_ns), "sensor": "incl0", "test": "frozen", "statistic": 0,
                                        "threshold": n, "decision": "recovered", "held_out_s": held_s})
            log.info("incl0 moves again after %.0f s stuck", held_s)

    def _recursor_reset(self, R: np.ndarray, cov_rot: np.ndarray) -> None:
        self._rec_R, self._rec_cov = R.copy(), cov_rot.copy()
        self.recursor.reset()

    def _recursor_test(self, factor, k: int, t_ns: int) -> None:
        """The patent's state recursor for the inclinometer: its pseudo-innovation against the attitude of the
        last reset carried forward by the gyro only (so a slow ramp the smoother follows still accumulates);
        every ``window`` samples the spectral test, then a restart from the smoother's attitude."""
        values = gtsam.Values()
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(self._rec_R), np.zeros(3)))
        A, b = factor.linearize(values).jacobian()
        A = A[:, :3]
        L = np.linalg.cholesky(np.eye(len(b)) + A @ self._rec_cov @ A.T)
        self.recursor.window.append(np.linalg.solve(L, -b))
        if len(self.recursor.window) < self.recursor.n:
            return
        Y = np.array(self.recursor.window)
        eig = np.linalg.eigvalsh(Y.T @ Y)
        self.recursor.last_min = float(eig[0])
        healthy = self.recursor.healthy(float(eig[-1]))
        decision = {"t_ns": int(t_ns), "sensor": "incl0", "test": "eigen_recursor", "statistic": float(eig[-1]),
                    "threshold": self.recursor.threshold, "lambda_min": float(eig[0]),
                    "lower_threshold": self.recursor.lower, "decision": "normal" if healthy else "fault"}
        self._decisions_now.append(decision)
        if not healthy and not any(self.faulty.values()):
            self.faulty["incl0"] = True
            for d in self.detectors.values():
                d.reset()
            self._to_remove.extend(self._removable("incl0", k))
            log.info("incl0 soft fault from the state recursor (lambda_max %.1f, lambda_min %.2f)", eig[-1], eig[0])
        self.recursor.window.clear()
        self._restart_recursor = True

    def _tracker_factors(self, pending: list, k: int, nav_k: gtsam.NavState, P_blocks: dict) -> list:
        """Tracker samples moved to keyframe k, gated one by one (vectorised), averaged into one position
        (and one velocity) factor with sigma / sqrt(accepted samples)."""
        n = self.noise
        R_k, p_k, v_k = nav_k.attitude().matrix(), nav_k.position(), nav_k.velocity()
        r = n.r_P_B
        pred = p_k + R_k @ r
        Z = np.array([m.z + pred - (m.nav.position() + m.nav.attitude().matrix() @ r) for m in pending])
        H = np.hstack([R_k @ self._hat_r_P_B, R_k])  # d(p + R r)/d[w, t] = [-R [r]x, R]
        S = H @ P_blocks["x"] @ H.T
        S.flat[::4] += n.tracker_sigma_m**2
        # L^-1 of a 3x3 once, then one small product: scipy's solve_triangular (LAPACK trtrs) costs ~7 ms a call
        # on a loaded machine with OpenBLAS threads, more than the whole keyframe update
        nu = (Z - pred) @ _inverse_cholesky(S).T
        stat = np.einsum("ij,ij->i", nu, nu)
        keep = np.array([self._gate("tracker0", m.t_ns, float(s), v, k) for m, s, v in zip(pending, stat, nu)])
        out = []
        if keep.any():
            noise = gtsam.noiseModel.Isotropic.Sigma(3, n.tracker_sigma_m / np.sqrt(keep.sum()))
            factor = ft.prism_position_factor(noise, X(k), Z[keep].sum(axis=0) / keep.sum(), r)
            if self.graph_log is not None:  # the audit's record (batch runs only)
                kept = [m for m, kk in zip(pending, keep) if kk]
                velocities = np.array([m.extra[:3] for m in kept]) if all(m.extra is not None for m in kept) else None
                self._remember(factor, Z=Z[keep], sigma=n.tracker_sigma_m, t_ns=[m.t_ns for m in kept],
                               v_start=self.nav.velocity(),  # the filtered velocity the samples were moved with
                               V=velocities)
            out.append((factor, "tracker0"))
        with_velocity = [i for i, m in enumerate(pending) if keep[i] and m.extra is not None]
        if with_velocity:
            vel = np.array([pending[i].extra[:3] + v_k - pending[i].nav.velocity() for i in with_velocity])
            w = np.array([pending[i].extra[3:] for i in with_velocity]).sum(axis=0) / len(with_velocity)
            # H = [-R [w x r]x (rotation), 0 (position), I (velocity)]: S = H_rot P_rot H_rot^T + P_v + noise;
            # the mean of n samples: state uncertainty unchanged, measurement noise / n
            H_rot = -R_k @ so3.hat(mt.cross(w, r))
            Sv = H_rot @ P_blocks["x"][:3, :3] @ H_rot.T + P_blocks["v"]
            Sv.flat[::4] += n.tracker_velocity_sigma_m_s**2 / len(with_velocity)
            vel_mean = vel.sum(axis=0) / len(with_velocity)
            e = vel_mean - mt.prism_velocity_W(R_k, v_k, w, r)
            nu_v = _whiten(Sv, e)
            if self._gate("tracker0/velocity", pending[with_velocity[-1]].t_ns, float(nu_v @ nu_v), nu_v, k):
                noise = gtsam.noiseModel.Isotropic.Sigma(3, n.tracker_velocity_sigma_m_s / np.sqrt(len(with_velocity)))
                factor = ft.prism_velocity_factor(noise, X(k), V(k), vel_mean, w, r)
                if self.graph_log is not None:  # the audit's record (batch runs only)
                    self._remember(factor, z=vel_mean, w_B=w, sigma=n.tracker_velocity_sigma_m_s / np.sqrt(
                        len(with_velocity)), a_W=(v_k - self.nav.velocity()) / max(self.pim.deltaTij(), 1e-3))
                out.append((factor, "tracker0/velocity"))
        return out

    def _keyframe(self, t_ns: int) -> dict:
        k = self.k + 1
        nav_k = self._predict()
        graph, values, tags = gtsam.NonlinearFactorGraph(), _navstate_values(nav_k, k), []
        values.insert(j=B(k), constant_bias=self.bias)
        graph.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), self.pim))
        tags.append(None)
        metas = [None]
        cov = self.pim.preintMeasCov()
        dt = self.pim.deltaTij()
        P_pose = self._P_pose + cov[:6, :6]
        P_pose[3:, 3:] += dt**2 * self._P_vel
        P_blocks = {"x": P_pose, "v": self._P_vel + cov[6:9, 6:9]}
        self._decisions_now, self._to_remove, accepted = [], self._carried_removals, []
        self._carried_removals = []
        if self.options.gating.recursor:
            # the state recursor rides on the gyro alone: attitude of the last reset times the gyro's rotation
            self._rec_R = self._rec_R @ self.pim.deltaRij().matrix()
            self._rec_cov = self._rec_cov + self.noise.gyro_noise_density**2 * dt * np.eye(3)
        tracker = [m for m in self._pending if m.sensor == "tracker0"]
        if tracker:
            accepted.extend(self._tracker_factors(tracker, k, nav_k, P_blocks))
        for m in self._pending:
            if m.sensor == "tracker0":
                continue
            for factor, tag in self._factor_for(m, k, nav_k):
                if tag == "incl0":
                    self._frozen_check(m.t_ns, m.z, k)
                    accepted.extend(self._provisional_inclinometer(m.t_ns, k, values, P_blocks, t_ns))
                    continue
                stat, nu = self._innovation(factor, values, P_blocks)
                if self._gate(tag, m.t_ns, stat, nu, k):
                    accepted.append((factor, tag))
        self._pending = []
        accepted.extend(self._deferred_inclinometer(t_ns, k, values, P_blocks))
        provisional = [d for d in self._deferred if d["index"] == -1]
        decisions, to_remove = self._decisions_now, self._to_remove
        for factor, tag in accepted:  # a sensor found faulty in this keyframe keeps none of its new factors
            if self.faulty[tag.split("/")[0]]:
                self.counts["removed"] += 1
                continue
            graph.add(factor)
            tags.append(tag)
            metas.append(self._meta.pop(id(factor), None))
        self.kf_t_ns = t_ns
        self.k = k
        self._meta.clear()
        indices = self._update(graph, values, tags, k, to_remove, metas)
        waiting = iter(provisional)
        for idx, tag in zip(indices, tags):
            if tag == "incl0/provisional":
                next(waiting)["index"] = int(idx)
        for d in provisional:
            if d["index"] == -1:
                d["index"] = None  # not added after all (its sensor was found faulty in this keyframe)
        if self.keyframe_t_ns is not None:
            self.keyframe_t_ns.append(t_ns)
            self.initial_values.insert(values)
        pose, vel, bias = self._estimate(k)
        self.nav = gtsam.NavState(pose.rotation(), pose.translation(), vel)
        self._bias_drift_check(bias, t_ns, k, dt)
        self.bias = bias
        self.pim.resetIntegrationAndSetBias(bias)
        if self._restart_recursor:
            self._restart_recursor = False
            P_rot = self._P_pose[:3, :3] if self.options.covariance else P_pose[:3, :3]
            self._recursor_reset(pose.rotation().matrix(), P_rot)
        covariance = None
        if self.options.covariance:
            self._P_pose = self._smoother.marginalCovariance(X(k))
            self._P_vel = self._smoother.marginalCovariance(V(k))
            Rw = pose.rotation().matrix()
            J = np.zeros((6, 6))
            J[:3, :3], J[3:, 3:] = Rw, Rw
            covariance = J @ self._P_pose @ J.T
        else:
            self._P_pose = P_pose
            self._P_vel = P_blocks["v"]
        q = pose.rotation().toQuaternion()
        self._decisions = decisions
        return {"t_ns": int(t_ns), "position": pose.translation().tolist(),
                "quaternion": [q.x(), q.y(), q.z(), q.w()],
                "covariance": covariance, "faults": dict(self.faulty), "decisions": decisions}

    def _bias_drift_check(self, bias, t_ns: int, k: int, dt: float) -> None:
        """The accelerometer-bias drift test (see ``GatingOptions.bias_drift_z``); on an alarm the inclinometer
        is held out and its recent factors are removed at the next update."""
        g = self.options.gating
        if not (g.eigen and "incl0" in self.detectors) or dt <= 0:
            return
        if self.faulty["incl0"] or t_ns < self._grace_until_ns.get("incl0", 0):
            self._bias_increments.clear()  # held out or pulling the state back: the bias moves legitimately
            self._bias_drift_prev = None
            return
        a = np.asarray(bias.accelerometer())
        previous = getattr(self, "_bias_drift_prev", None)
        self._bias_drift_prev = a
        if previous is None:
            return
        increments = self._bias_increments
        if len(increments) == increments.maxlen:
            self._bias_increment_sum = self._bias_increment_sum - increments[0]  # running sum of the window
        step = (a[:2] - previous[:2]) / (self.noise.accel_random_walk * math.sqrt(dt))
        increments.append(step)
        self._bias_increment_sum = step if len(increments) == 1 else self._bias_increment_sum + step
        if (len(increments) < g.bias_drift_window or (t_ns - self.t0_ns) * 1e-9 < g.bias_drift_settle_s
                or t_ns < self._bias_drift_resume_ns):
            return
        z = max(abs(x) for x in self._bias_increment_sum.tolist()) / math.sqrt(g.bias_drift_window)
        if z <= g.bias_drift_z or any(self.faulty.values()):
            return
        self.faulty["incl0"] = True
        self._fault_t_ns["incl0"] = int(t_ns)
        for d in self.detectors.values():
            d.reset()
        self._bias_increments.clear()
        self._decisions_now.append({"t_ns": int(t_ns), "sensor": "incl0", "test": "bias_drift", "statistic": z,
                                    "threshold": g.bias_drift_z, "decision": "fault"})
        log.info("incl0 soft fault from the accelerometer bias drift (z %.1f > %.1f)", z, g.bias_drift_z)
        self._carried_removals.extend(self._removable("incl0", k))

    def _removable(self, tag: str, k: int) -> list[int]:
        """Factor indices of all ``tag``'s recent factors still inside the smoother (not marginalised)."""
        # factors are logged with the keyframe they entered at; a deferred inclinometer factor sits on a keyframe
        # up to the deferral older
        defer = int(np.ceil(self._incl_deferral_s() / self.options.keyframe_s)) + 1
        margin = int(np.ceil(self.options.lag_s / self.options.keyframe_s)) - 2 - defer
        out = [idx for kf, idx in self._recent[tag] if self.options.mode == "isam2" or k - kf < margin]
        self._recent[tag].clear()
        return out


def gauss_newton(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int = 5,
                 tol: float = 1e-7) -> gtsam.Values:
    """Gauss-Newton from a close start (the online pass's estimates), Levenberg-Marquardt if a step fails.

    From there the problem is nearly linear: 2-3 steps converge (largest tangent step below ``tol``).  GTSAM's
    LM re-evaluates the Python factors for every damping trial, ~5x slower here.
    """
    error = graph.error(values)
    for _ in range(max_iterations):
        delta = graph.linearize(values).optimize()
        new = values.retract(delta)
        new_error = graph.error(new)
        if new_error > error * (1 + 1e-9):
            log.info("Gauss-Newton step raised the error (%.6g -> %.6g): Levenberg-Marquardt", error, new_error)
            return optimize(graph, values, max_iterations=30)
        values, error = new, new_error
        if np.max(np.abs(delta.vector())) < tol:
            break
    return values


def batch_smooth(estimator: TrackerEstimator, covariance: bool = False):
    """Gauss-Newton (LM fallback) over every keyframe with the factors the online pass accepted (not removed).

    Returns (t_ns (K,), poses list[Pose3], covariances list or None).
    """
    if estimator.graph_log is None:
        raise ValueError("the estimator must run with TrackerOptions(keep_graph=True)")
    graph = gtsam.NonlinearFactorGraph()
    for factor, _, _, removed, _ in estimator.graph_log:
        if not removed:
            graph.add(factor)
    if graph.size() == 0:
        raise DegenerateDataError("no keyframe: the recording never had tracker, inclinometer and camera samples")
    t0 = time.perf_counter()
    result = gauss_newton(graph, estimator.initial_values)
    log.info("batch smoother over %d keyframes: %.1f s", len(estimator.keyframe_t_ns), time.perf_counter() - t0)
    K = len(estimator.keyframe_t_ns)
    poses = [result.atPose3(X(k)) for k in range(K)]
    covs = None
    if covariance:
        marginals = gtsam.Marginals(graph, result)
        covs = []
        for k, pose in enumerate(poses):
            Rw = pose.rotation().matrix()
            J = np.zeros((6, 6))
            J[:3, :3], J[3:, 3:] = Rw, Rw
            covs.append(J @ marginals.marginalCovariance(X(k)) @ J.T)
    return np.array(estimator.keyframe_t_ns, dtype=np.int64), poses, covs
