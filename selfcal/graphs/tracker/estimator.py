"""The online estimator: samples in timestamp order in, one pose per keyframe out.

IMU samples are preintegrated; every ``keyframe_s`` a keyframe ``(X_k, V_k, B_k)`` enters with a
``CombinedImuFactor`` and the factors of the measurements that arrived since the previous keyframe, each moved to
the keyframe (:mod:`~selfcal.graphs.tracker.alignment`) and decided on (:mod:`~selfcal.graphs.tracker.gate`).
"""
from __future__ import annotations

import logging
from dataclasses import replace

import gtsam
import numpy as np

from selfcal.core import inertial
from selfcal.core.solve import lag_stamp_s
from selfcal.factors import tracker as ft
from selfcal.graphs.tracker.alignment import Pending, bearing_at_keyframe, navstate_values
from selfcal.graphs.tracker.bookkeeping import FactorBook
from selfcal.graphs.tracker.checks import BiasDrift, FrozenOutput, SensorHealth
from selfcal.graphs.tracker.eigen import EigenDetector, StateRecursor
from selfcal.graphs.tracker.gate import Gate, linear_innovation, predicted_covariance
from selfcal.graphs.tracker.inclinometer import DeferredInclinometer
from selfcal.graphs.tracker.options import SensorNoise, TrackerOptions
from selfcal.graphs.tracker.prism import PrismFactors
from selfcal.graphs.tracker.vibration import InclinometerVibration
from selfcal.models import tracker as mt

log = logging.getLogger(__name__)

X, V, B = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B
PRIOR_POSE_SIGMAS = np.array([2e-3, 2e-3, 5e-3, 0.01, 0.01, 0.01])  # first keyframe: rotation (rad), position (m)
PRIOR_VELOCITY_SIGMA_M_S = 0.02
INCL_RATE_HZ = 10.0  # the inclinometer's nominal sample rate: sets its detectors' tests per hour


def pose_covariance_W(R_W_B: np.ndarray, P_pose: np.ndarray) -> np.ndarray:
    """A pose covariance [rotation rad, position m] from GTSAM's body-frame tangent to the world frame:
    ``J P J^T``, ``J = diag(R_W_B, R_W_B)``."""
    J = np.zeros((6, 6))
    J[:3, :3], J[3:, 3:] = R_W_B, R_W_B
    return J @ P_pose @ J.T


def frozen_jacobian(factor: gtsam.CustomFactor, values: gtsam.Values) -> gtsam.LinearContainerFactor:
    """A custom factor linearised once, at the propagated state ``values``, for the online smoother.

    GTSAM hands a CustomFactor's Python error function a copy of the smoother's whole linearisation point (pybind
    copies the ``gtsam.Values`` at every call): in ``isam2`` mode that is the whole history, and its update grew
    from 0.7 to 5.8 ms over 1000 keyframes (measured; ``ISAM2Params`` settings changed nothing).  The smoother
    linearises a new factor once and again only when its variables move by more than the relinearisation threshold
    (0.01); frozen, the factor differs from the relinearised one by second-order terms in that move: the beam
    bearing by ~0.01^2 / distance (rad), the prism velocity by ~|w x r| 0.01^2 (m/s), both far below their
    noise.  (Measured: the online poses of the benchmark recordings agree to 1e-14 m.)  Batch runs keep the
    nonlinear factor (their graph is re-solved by Levenberg-Marquardt).
    """
    return gtsam.LinearContainerFactor(factor.linearize(values), values)


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
        self._cam_noise = gtsam.noiseModel.Isotropic.Sigma(2, noise.cam_sigma_rad)
        # soft-fault detection watches the inclinometer, the sensor vibration and drift corrupt (the patent's
        # suspect): holding it out costs little (tilt then rests on the accelerometer bias, which wanders
        # slowly).  The tracker and the camera are the only sources of position and azimuth: nothing could
        # isolate a soft fault in them, and holding them out would let the state drift away from their own
        # recovery test; they are protected by the chi-square gate.
        half = replace(g, false_alarms_per_hour=g.false_alarms_per_hour / 2)  # two detectors share the rate
        self._vibration = InclinometerVibration(noise, g, options.keyframe_s)
        self._book = FactorBook(options, self._vibration.deferral_s)
        self._health = SensorHealth({"incl0": EigenDetector(2, half, INCL_RATE_HZ)}, g, self._book)
        # the recursor tests once per window (not every stride): its per-test alpha follows from that
        self._recursor = StateRecursor(EigenDetector(2, replace(half, stride_s=g.window / INCL_RATE_HZ),
                                                     INCL_RATE_HZ))
        self._frozen = FrozenOutput(g.frozen_samples, self._health)
        self._bias_drift = BiasDrift(g, noise.accel_random_walk, self._health)
        self._gate = Gate(g, self._health, self._frozen)
        self._prism = PrismFactors(noise, self._gate, self._book)
        self._inclinometer = DeferredInclinometer(g, self._vibration, self._gate, self._health, self._frozen,
                                                  self._recursor, self._book)
        self.k = -1
        self.t0_ns = None
        self._last_imu = None  # (t_ns, gyro, accel)
        self._latest = {}  # sensor -> last raw sample, for initialisation
        self._pending: list[Pending] = []
        # a keyframe is due half an IMU interval before keyframe_s has passed (stamps jitter by nanoseconds)
        self._keyframe_due_ns = 1e9 * (options.keyframe_s - 0.5 / noise.imu_rate_hz)
        self._smoother = None

    @property
    def counts(self) -> dict[str, int]:
        return {**self._gate.counts, "removed": self._book.removed, "replaced": self._book.replaced}

    @property
    def faulty(self) -> dict[str, bool]:
        return self._health.faulty

    @property
    def graph_log(self) -> list | None:
        """[factor, tag, keyframe, removed, meta] of every factor (``keep_graph``), else None."""
        return self._book.graph_log

    @property
    def keyframe_t_ns(self) -> list[int] | None:
        return self._book.keyframe_t_ns

    @property
    def initial_values(self) -> gtsam.Values | None:
        return self._book.initial_values

    # --- input -------------------------------------------------------------------------------------------------

    def imu(self, t_ns: int, gyro, accel) -> list[dict]:
        gyro, accel = np.asarray(gyro, dtype=float), np.asarray(accel, dtype=float)
        if self.k < 0:
            self._last_imu = (t_ns, gyro, accel)
            if all(s in self._latest for s in ("tracker0", "incl0", "cam0")):
                self._initialise(t_ns)
            return []
        t_prev, g_prev, a_prev = self._last_imu
        dt = (t_ns - t_prev) * 1e-9
        if dt <= 0:
            log.warning("imu0: sample at %d ns not after the previous one: skipped", t_ns)
            return []
        self.pim.integrateMeasurement(a_prev, g_prev, dt)
        self._last_imu = (t_ns, gyro, accel)
        self._vibration.imu.append(t_ns, accel, gyro)
        if t_ns - self.kf_t_ns >= self._keyframe_due_ns:
            return [self._keyframe(t_ns)]
        return []

    def tracker(self, t_ns: int, position, velocity=None) -> list[dict]:
        position = np.asarray(position, dtype=float)
        velocity = None if velocity is None else np.asarray(velocity, dtype=float)
        self._latest["tracker0"] = (t_ns, position, velocity)
        if self.k >= 0:
            w_B = self._last_imu[1] - self.bias.gyroscope()
            self._pending.append(Pending("tracker0", t_ns, position, self._predict(), velocity, w_B))
        return []

    def incl(self, t_ns: int, roll: float, pitch: float) -> list[dict]:
        up = mt.up_direction_B(roll, pitch)
        self._latest["incl0"] = (t_ns, up)
        if self.k >= 0:
            self._pending.append(Pending("incl0", t_ns, up, self._predict()))
        return []

    def cam(self, t_ns: int, u: float, v: float) -> list[dict]:
        bearing = mt.bearing_from_pixel(np.array([u, v]), self.noise.camera_matrix, self.noise.dist_coeffs)[0]
        self._latest["cam0"] = (t_ns, bearing)
        if self.k >= 0:
            self._pending.append(Pending("cam0", t_ns, bearing, self._predict()))
        return []

    # --- state and smoother ------------------------------------------------------------------------------------

    def _predict(self) -> gtsam.NavState:
        return self.pim.predict(self.nav, self.bias)

    def _initialise(self, t_ns: int) -> None:
        """First keyframe from the latest samples: tilt (inclinometer), azimuth (beam), position (tracker)."""
        n, o = self.noise, self.options
        _, p_P, v_P = self._latest["tracker0"]
        _, up_B = self._latest["incl0"]
        _, bearing_C = self._latest["cam0"]
        roll, pitch = inertial.tilt_from_specific_force(up_B)
        beam_W = n.tracker_W - p_P
        R = mt.attitude_from_tilt_and_beam(float(roll), float(pitch), n.R_B_C @ bearing_C,
                                           beam_W / np.linalg.norm(beam_W))
        v = v_P if v_P is not None else np.zeros(3)
        self.t0_ns = self.kf_t_ns = t_ns
        self.k = 0
        self.nav = gtsam.NavState(gtsam.Rot3(R), p_P - R @ n.r_P_B, v)
        self.bias = gtsam.imuBias.ConstantBias()
        self.pim = gtsam.PreintegratedCombinedMeasurements(self.params, self.bias)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(X(0), self.nav.pose(), gtsam.noiseModel.Diagonal.Sigmas(PRIOR_POSE_SIGMAS)))
        graph.add(gtsam.PriorFactorVector(V(0), v, gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_VELOCITY_SIGMA_M_S)))
        graph.add(gtsam.PriorFactorConstantBias(B(0), self.bias, gtsam.noiseModel.Diagonal.Sigmas(
            np.array([o.initial_accel_bias_sigma] * 3 + [o.initial_gyro_bias_sigma] * 3))))
        values = navstate_values(self.nav, 0)
        values.insert(B(0), self.bias)
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(0.01)
        if o.mode == "fixed-lag":
            self._smoother = gtsam.IncrementalFixedLagSmoother(o.lag_s, params)
        elif o.mode == "isam2":
            self._smoother = gtsam.ISAM2(params)
        else:
            raise ValueError(f"unknown mode {o.mode!r}: 'fixed-lag' or 'isam2'")
        self._update(graph, values, [None] * graph.size(), 0)
        self._P_pose = np.diag(PRIOR_POSE_SIGMAS**2)
        self._P_vel = PRIOR_VELOCITY_SIGMA_M_S**2 * np.eye(3)
        self._P_bias = np.diag([o.initial_accel_bias_sigma**2] * 3 + [o.initial_gyro_bias_sigma**2] * 3)
        self._recursor.reset(self.nav.attitude().matrix(), self._P_pose[:3, :3])
        self._book.add_keyframe(t_ns, values)

    def _update(self, graph, values, tags, k, metas=None):
        """One smoother update (new keyframe, its factors, the factors to remove); remembers the new indices."""
        to_remove = self._book.removals()
        if self.options.mode == "fixed-lag":
            stamp = lag_stamp_s((self.kf_t_ns - self.t0_ns) * 1e-9, self.options.lag_step_s)
            stamps = {key: stamp for key in (X(k), V(k), B(k))}
            self._smoother.update(graph, values, stamps, to_remove)
            indices = self._smoother.getISAM2Result().getNewFactorsIndices()
        else:
            indices = self._smoother.update(graph, values, to_remove).getNewFactorsIndices()
        self._book.added(graph, indices, tags, k, metas)
        return indices

    def _estimate(self, k):
        s = self._smoother  # per key: calculateEstimate() would build every variable of the lag
        return s.calculateEstimatePose3(X(k)), s.calculateEstimateVector(V(k)), s.calculateEstimateConstantBias(B(k))

    # --- one keyframe ------------------------------------------------------------------------------------------

    def _keyframe(self, t_ns: int) -> dict:
        k = self.k + 1
        nav_k = self._predict()
        values = navstate_values(nav_k, k)
        values.insert(j=B(k), constant_bias=self.bias)
        P_pose, P_vel = predicted_covariance(self._P_pose, self._P_vel, self.pim, self._P_bias,
                                             self.nav.attitude().matrix())
        dt = self.pim.deltaTij()
        self._health.decisions = decisions = []
        if self.options.gating.recursor:
            # the state recursor rides on the gyro alone: attitude of the last reset times the gyro's rotation
            self._recursor.propagate(self.pim.deltaRij().matrix(), dt, self.noise.gyro_noise_density)
        accepted = self._pending_factors(k, nav_k, values, P_pose, P_vel, t_ns)
        accepted.extend(self._inclinometer.decide_ready(t_ns, k))
        self._add_keyframe(k, t_ns, values, accepted)
        pose, vel, bias = self._estimate(k)
        self.nav = gtsam.NavState(pose.rotation(), pose.translation(), vel)
        self._bias_drift.check(np.asarray(bias.accelerometer()), t_ns, k, dt, (t_ns - self.t0_ns) * 1e-9)
        self.bias = bias
        self.pim.resetIntegrationAndSetBias(bias)
        if self._recursor.restart_due:
            self._recursor.restart_due = False
            P_rot = self._P_pose[:3, :3] if self.options.covariance else P_pose[:3, :3]
            self._recursor.reset(pose.rotation().matrix(), P_rot)
        covariance = None
        if self.options.covariance:
            self._P_pose = self._smoother.marginalCovariance(X(k))
            self._P_vel = self._smoother.marginalCovariance(V(k))
            self._P_bias = self._smoother.marginalCovariance(B(k))
            covariance = pose_covariance_W(pose.rotation().matrix(), self._P_pose)
        else:
            self._P_pose, self._P_vel = P_pose, P_vel
        q = pose.rotation().toQuaternion()
        return {"t_ns": int(t_ns), "position": pose.translation().tolist(), "quaternion": [q.x(), q.y(), q.z(), q.w()],
                "covariance": covariance, "faults": dict(self._health.faulty), "decisions": decisions}

    def _pending_factors(self, k: int, nav_k: gtsam.NavState, values: gtsam.Values, P_pose: np.ndarray,
                         P_vel: np.ndarray, t_ns: int) -> list:
        """The samples since the previous keyframe moved to keyframe k and gated: [(factor, tag)] to add."""
        n = self.noise
        tracker = [m for m in self._pending if m.sensor == "tracker0"]
        accepted = (self._prism.factors(tracker, k, nav_k, P_pose, P_vel, self.nav.velocity(), self.pim.deltaTij())
                    if tracker else [])
        for m in self._pending:
            if m.sensor == "incl0":
                accepted.extend(self._inclinometer.arrive(m, k, nav_k, values, P_pose, t_ns))
            elif m.sensor == "cam0":
                bearing = bearing_at_keyframe(m, nav_k, n.r_C_B, n.R_B_C, n.tracker_W)
                factor = ft.beam_bearing_factor(self._cam_noise, X(k), bearing, n.r_C_B, n.R_B_C, n.tracker_W)
                linear = factor.linearize(values)  # once: for the gate and, online, as the frozen factor itself
                stat, nu = linear_innovation(linear, P_pose)
                if self._gate.decide("cam0", m.t_ns, stat, nu, k):
                    if self._book.graph_log is None:  # see frozen_jacobian
                        factor = gtsam.LinearContainerFactor(linear, values)
                    accepted.append((factor, "cam0"))
        self._pending = []
        return accepted

    def _add_keyframe(self, k: int, t_ns: int, values: gtsam.Values, accepted: list) -> None:
        """The smoother update with the IMU factor and the accepted factors (a sensor found faulty in this
        keyframe keeps none of its new factors)."""
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), self.pim))
        tags, factors = [None], []
        for factor, tag in accepted:
            if self._health.faulty[tag.split("/")[0]]:
                self._book.removed += 1
                continue
            if self._book.graph_log is None and isinstance(factor, gtsam.CustomFactor):
                factor = frozen_jacobian(factor, values)
            graph.add(factor)
            tags.append(tag)
            factors.append(factor)
        metas = [None] + self._book.take_metas(factors)
        self.kf_t_ns = t_ns
        self.k = k
        indices = self._update(graph, values, tags, k, metas)
        self._inclinometer.added(indices, tags)
        self._book.add_keyframe(t_ns, values)
