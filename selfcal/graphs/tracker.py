"""The laser-tracker target as a factor graph, online (iSAM2 / fixed-lag) and offline (batch LM), with fault gating.

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
   :func:`wishart_lambda_max_quantile`).  On detection the sensor's factors of the window still inside the
   smoother are removed again (``factorsToRemove``) and its new factors are held out; it is readmitted when a
   full window of its (monitored, not added) residuals passes the same test.
3. The inclinometer factor's sigma grows with the vibration the accelerometer itself shows (excess variance
   of the keyframe interval's specific force over its white noise, when significant at 0.1 %).

Solvers: ``'isam2'`` (gtsam.ISAM2, the whole history), ``'fixed-lag'`` (gtsam.IncrementalFixedLagSmoother over
``lag_s``: bounded memory over hours), and :func:`batch_smooth` (the same accepted factors, Levenberg-Marquardt
over all keyframes).
"""
from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field, replace
from functools import lru_cache

import gtsam
import numpy as np
from scipy import stats
from scipy.linalg import solve_triangular

from selfcal.factors import tracker as ft
from selfcal.graphs.solve import DegenerateDataError, optimize
from selfcal.models import so3
from selfcal.models import tracker as mt
from selfcal.models.tracker import wishart_lambda_max_quantile, wishart_lambda_min_quantile

log = logging.getLogger(__name__)

X, V, B = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B
SENSORS = ("tracker0", "incl0", "cam0")


@lru_cache(maxsize=64)
def _variance_ratio_999(dof: int) -> float:
    """chi2(dof).ppf(0.999) / dof: a sample variance above ``white`` times this is significant at 0.1 %."""
    return float(stats.chi2.ppf(0.999, dof) / dof)


@dataclass
class SensorNoise:
    """Per-sample sigmas and geometry of the target (from sensor.yaml; defaults = the simulator's)."""

    tracker_sigma_m: float = 0.5e-3
    tracker_velocity_sigma_m_s: float = 2e-3
    incl_sigma_rad: float = 8.7e-5
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
    vibration_inflation: bool = True
    max_consecutive_rejects: int = 20  # then the sensor is readmitted (the state, not it, is judged wrong)
    # the patent's state recursor for the inclinometer (off: with a MEMS gyro, 1.7e-4 rad/sqrt(s), the
    # gyro-only attitude over a 3 s window wanders ~3 inclinometer sigmas, its pseudo-innovations are strongly
    # correlated and the Wishart threshold does not hold: measured false alarms every few seconds)
    recursor: bool = False


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
        self.count = 0

    def push(self, nu: np.ndarray) -> float | None:
        """Add one normalised residual; the statistic when a test is due (full window, every stride), else None."""
        self.window.append(np.asarray(nu, dtype=float))
        self.count += 1
        if len(self.window) < self.n or self.count % self.stride:
            return None
        Y = np.array(self.window)
        eig = np.linalg.eigvalsh(Y.T @ Y)
        self.last_min = float(eig[0])
        return float(eig[-1])

    def healthy(self, lam_max: float) -> bool:
        """The last test passed on both sides."""
        return lam_max <= self.threshold and self.last_min >= self.lower

    def reset(self) -> None:
        self.window.clear()
        self.count = 0


@dataclass
class _Pending:
    sensor: str
    t_ns: int
    z: np.ndarray
    nav: gtsam.NavState  # propagated state at the measurement
    extra: np.ndarray | None = None  # velocity for the tracker, body rate for the velocity factor


def _navstate_values(nav: gtsam.NavState, k: int) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(X(k), nav.pose())
    values.insert(V(k), nav.velocity())
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
            "cam0": gtsam.noiseModel.Isotropic.Sigma(2, noise.cam_sigma_rad)}
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
        self._recent = {s: deque(maxlen=g.window) for s in SENSORS}  # (keyframe, factor index) in the smoother
        self.k = -1
        self.t0_ns = None
        self._last_imu = None  # (t_ns, gyro, accel)
        self._latest = {}  # sensor -> last raw sample, for initialisation
        self._pending: list[_Pending] = []
        self._decisions: list[dict] = []
        self._acc_sum = np.zeros(3)
        self._acc_sq = np.zeros(3)
        self._acc_n = 0
        self.counts = {"accepted": 0, "rejected": 0, "held_out": 0, "removed": 0}
        self.graph_log: list | None = [] if options.keep_graph else None  # [factor, tag, keyframe, removed]
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
        self._acc_sum += accel
        self._acc_sq += accel**2
        self._acc_n += 1
        if (t_ns - self.kf_t_ns) * 1e-9 >= self.options.keyframe_s - 0.5 / self.noise.imu_rate_hz:
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
        roll, pitch = mt.tilt_from_specific_force(up_B)
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

    def _update(self, graph, values, tags, k, to_remove=()):
        """One smoother update (new keyframe, its factors, factors to remove); remembers the new indices."""
        to_remove = list(to_remove)
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
                self.graph_log.append([graph.at(i), tag, k, False])
        return indices

    def _estimate(self, k):
        s = self._smoother
        est = s.calculateEstimate()
        return est.atPose3(X(k)), est.atVector(V(k)), est.atConstantBias(B(k))

    def _vibration_sigma(self) -> float:
        """Extra inclinometer sigma (rad) from the accelerometer's excess variance over the keyframe interval."""
        n = self._acc_n
        if n < 3 or not self.options.gating.vibration_inflation:
            return 0.0
        var = (self._acc_sq - self._acc_sum**2 / n).sum() / (n - 1)
        white = 3.0 * self.noise.accel_noise_density**2 * self.noise.imu_rate_hz
        if var <= white * _variance_ratio_999(3 * (n - 1)):
            return 0.0
        return float(np.sqrt(var - white) / self.noise.gravity_m_s2)

    def _factor_for(self, m: _Pending, k: int, nav_k: gtsam.NavState, incl_sigma: float):
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
            noise = gtsam.noiseModel.Isotropic.Sigma(2, float(np.hypot(n.incl_sigma_rad, incl_sigma)))
            return [(ft.inclinometer_factor(noise, X(k), dR.T @ m.z), "incl0")]
        bearing = n.R_B_C.T @ dR.T @ n.R_B_C @ m.z
        return [(ft.beam_bearing_factor(self._noise_models["cam0"], X(k), bearing, n.r_C_B, n.R_B_C, n.tracker_W),
                 "cam0")]

    def _innovation(self, factor, values, P_blocks):
        """(statistic, normalised residual) of a factor at the propagated state with covariance P."""
        A, b = factor.linearize(values).jacobian()
        P = np.zeros((A.shape[1], A.shape[1]))
        col = 0
        for key in factor.keys():
            Pk = P_blocks[chr(gtsam.Symbol(key).chr())]
            d = Pk.shape[0]
            P[col:col + d, col:col + d] = Pk
            col += d
        S = np.eye(len(b)) + A @ P @ A.T
        L = np.linalg.cholesky(S)
        nu = np.linalg.solve(L, -b)
        return float(nu @ nu), nu

    def _gate(self, tag: str, t_ns: int, stat: float, nu: np.ndarray, k: int) -> bool:
        """Chi-square gate and eigenvalue detector for one measurement; logs the decision; True = add it."""
        gating = self.options.gating
        sensor = tag.split("/")[0]
        dof = len(nu)
        threshold = self._chi2_threshold[dof]
        decision = {"t_ns": int(t_ns), "sensor": tag, "test": "chi2", "statistic": stat, "dof": dof,
                    "threshold": threshold}
        detector = self.detectors.get(tag)
        self._decisions_now.append(decision)
        if self.faulty[sensor]:
            decision["decision"] = "held_out"
            self.counts["held_out"] += 1
            if detector is not None:  # monitored while held out: readmitted when a full window looks healthy
                lam = detector.push(nu)
                if lam is not None and detector.healthy(lam):
                    self.faulty[sensor] = False
                    detector.reset()
                    self._decisions_now.append({"t_ns": int(t_ns), "sensor": tag, "test": "eigen", "statistic": lam,
                                                "threshold": detector.threshold, "lambda_min": detector.last_min,
                                                "lower_threshold": detector.lower, "decision": "recovered"})
                    log.info("%s recovered (lambda_max %.1f <= %.1f)", tag, lam, detector.threshold)
            return False
        if gating.chi2 and stat > threshold:
            self._consecutive[tag] = self._consecutive.get(tag, 0) + 1
            if self._consecutive[tag] <= gating.max_consecutive_rejects:
                decision["decision"] = "reject"
                self.counts["rejected"] += 1
                return False
            # a sensor rejected for so long is more likely right than the state: the state has drifted away
            # (e.g. pulled by another sensor's undetected fault) and only this sensor can bring it back
            decision["decision"] = "accept_after_rejects"
            self._consecutive[tag] = 0
        else:
            self._consecutive[tag] = 0
            decision["decision"] = "accept"
        self.counts["accepted"] += 1
        if gating.eigen and detector is not None:
            lam = detector.push(nu)
            if lam is not None and not detector.healthy(lam) and not any(self.faulty.values()):
                # single-fault assumption: while one sensor is held out the others' residuals carry its
                # pull on the state, so their windows restart instead of accusing them in cascade
                self.faulty[sensor] = True
                for d in self.detectors.values():
                    d.reset()
                self._decisions_now.append({"t_ns": int(t_ns), "sensor": tag, "test": "eigen", "statistic": lam,
                                            "threshold": detector.threshold, "lambda_min": detector.last_min,
                                            "lower_threshold": detector.lower, "decision": "fault"})
                log.info("%s soft fault (lambda_max %.1f vs %.1f, lambda_min %.2f vs %.2f)", tag, lam,
                         detector.threshold, detector.last_min, detector.lower)
                self._to_remove.extend(self._removable(sensor, k))
        return True

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
        H = np.hstack([-R_k @ so3.hat(r), R_k])
        S = H @ P_blocks["x"] @ H.T + n.tracker_sigma_m**2 * np.eye(3)
        L = np.linalg.cholesky(S)
        nu = solve_triangular(L, (Z - pred).T, lower=True).T
        stat = np.einsum("ij,ij->i", nu, nu)
        keep = np.array([self._gate("tracker0", m.t_ns, float(s), v, k) for m, s, v in zip(pending, stat, nu)])
        out = []
        if keep.any():
            noise = gtsam.noiseModel.Isotropic.Sigma(3, n.tracker_sigma_m / np.sqrt(keep.sum()))
            out.append((ft.prism_position_factor(noise, X(k), Z[keep].mean(axis=0), r), "tracker0"))
        with_velocity = [i for i, m in enumerate(pending) if keep[i] and m.extra is not None]
        if with_velocity:
            vel = np.array([pending[i].extra[:3] + v_k - pending[i].nav.velocity() for i in with_velocity])
            w = np.array([pending[i].extra[3:] for i in with_velocity]).mean(axis=0)
            Hv = np.hstack([-R_k @ so3.hat(mt.cross(w, r)), np.zeros((3, 3)), np.eye(3)])
            P = np.zeros((9, 9))
            P[:6, :6], P[6:, 6:] = P_blocks["x"], P_blocks["v"]
            # the mean of n samples: state uncertainty unchanged, measurement noise / n
            Sv = Hv @ P @ Hv.T + n.tracker_velocity_sigma_m_s**2 / len(with_velocity) * np.eye(3)
            e = vel.mean(axis=0) - mt.prism_velocity_W(R_k, v_k, w, r)
            nu_v = solve_triangular(np.linalg.cholesky(Sv), e, lower=True)
            if self._gate("tracker0/velocity", pending[with_velocity[-1]].t_ns, float(nu_v @ nu_v), nu_v, k):
                noise = gtsam.noiseModel.Isotropic.Sigma(3, n.tracker_velocity_sigma_m_s / np.sqrt(len(with_velocity)))
                out.append((ft.prism_velocity_factor(noise, X(k), V(k), vel.mean(axis=0), w, r), "tracker0/velocity"))
        return out

    def _keyframe(self, t_ns: int) -> dict:
        k = self.k + 1
        nav_k = self._predict()
        graph, values, tags = gtsam.NonlinearFactorGraph(), _navstate_values(nav_k, k), []
        values.insert(B(k), self.bias)
        graph.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), self.pim))
        tags.append(None)
        cov = self.pim.preintMeasCov()
        dt = self.pim.deltaTij()
        P_pose = self._P_pose + cov[:6, :6]
        P_pose[3:, 3:] += dt**2 * self._P_vel
        P_blocks = {"x": P_pose, "v": self._P_vel + cov[6:9, 6:9]}
        incl_sigma = self._vibration_sigma()
        self._decisions_now, self._to_remove, accepted = [], [], []
        # the state recursor rides on the gyro alone: attitude of the last reset times the gyro's rotation
        self._rec_R = self._rec_R @ self.pim.deltaRij().matrix()
        self._rec_cov = self._rec_cov + self.noise.gyro_noise_density**2 * dt * np.eye(3)
        tracker = [m for m in self._pending if m.sensor == "tracker0"]
        if tracker:
            accepted.extend(self._tracker_factors(tracker, k, nav_k, P_blocks))
        for m in self._pending:
            if m.sensor == "tracker0":
                continue
            for factor, tag in self._factor_for(m, k, nav_k, incl_sigma):
                stat, nu = self._innovation(factor, values, P_blocks)
                if tag == "incl0" and self.options.gating.eigen and self.options.gating.recursor:
                    self._recursor_test(factor, k, m.t_ns)
                if self._gate(tag, m.t_ns, stat, nu, k):
                    accepted.append((factor, tag))
        self._pending = []
        decisions, to_remove = self._decisions_now, self._to_remove
        for factor, tag in accepted:  # a sensor found faulty in this keyframe keeps none of its new factors
            if self.faulty[tag.split("/")[0]]:
                self.counts["removed"] += 1
                continue
            graph.add(factor)
            tags.append(tag)
        self.kf_t_ns = t_ns
        self.k = k
        self._update(graph, values, tags, k, to_remove)
        if self.keyframe_t_ns is not None:
            self.keyframe_t_ns.append(t_ns)
            self.initial_values.insert(values)
        pose, vel, bias = self._estimate(k)
        self.nav = gtsam.NavState(pose.rotation(), pose.translation(), vel)
        self.bias = bias
        self.pim.resetIntegrationAndSetBias(bias)
        if self._restart_recursor:
            self._restart_recursor = False
            P_rot = self._P_pose[:3, :3] if self.options.covariance else P_pose[:3, :3]
            self._recursor_reset(pose.rotation().matrix(), P_rot)
        self._acc_sum[:] = 0.0
        self._acc_sq[:] = 0.0
        self._acc_n = 0
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

    def _removable(self, tag: str, k: int) -> list[int]:
        """Factor indices of ``tag`` from the detection window still inside the smoother (not marginalised)."""
        margin = int(np.ceil(self.options.lag_s / self.options.keyframe_s)) - 2
        out = [idx for kf, idx in self._recent[tag] if self.options.mode == "isam2" or k - kf < margin]
        self._recent[tag].clear()
        return out


def batch_smooth(estimator: TrackerEstimator, covariance: bool = False):
    """Levenberg-Marquardt over every keyframe with the factors the online pass accepted (and did not remove).

    Returns (t_ns (K,), poses list[Pose3], covariances list or None).
    """
    if estimator.graph_log is None:
        raise ValueError("the estimator must run with TrackerOptions(keep_graph=True)")
    graph = gtsam.NonlinearFactorGraph()
    for factor, _, _, removed in estimator.graph_log:
        if not removed:
            graph.add(factor)
    if graph.size() == 0:
        raise DegenerateDataError("no keyframe: the recording never had tracker, inclinometer and camera samples")
    t0 = time.perf_counter()
    result = optimize(graph, estimator.initial_values, max_iterations=30)
    log.info("batch LM over %d keyframes: %.1f s", len(estimator.keyframe_t_ns), time.perf_counter() - t0)
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
