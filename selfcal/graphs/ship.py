"""Vessel attitude and gyro bias as a factor graph (batch and iSAM2), corrected by the accelerometer's tilt.

Variables: ``R_k`` (Rot3, body -> local level) at keyframes every ``keyframe_s``, gyro bias ``b_j`` (Vector3)
per bias segment of ``bias_segment_s``.  Factors, all GTSAM's own:

* ``AHRSFactor(R_k, R_k+1, b_j)``: gyro preintegrated between keyframes (``PreintegratedAhrsMeasurements``);
  with ``estimate_gyro_scale`` instead :func:`selfcal.factors.ship.gyro_scale_rotation_factor`, the same error
  with the gyro's per-axis scale error ``s`` (Vector3, raw = (1 + s) true) as an unknown,
* tilt factor on ``R_k`` (:func:`selfcal.factors.ship.tilt_factor`): the up direction measured by the
  accelerometer (total force averaged over 0.2 s, known accelerations removed) against the
  world's up, with a sigma from the noise the accelerometer itself shows across the force (white noise,
  vibration: measured, then divided by the samples averaged), a floor of unmodelled slow accelerations and the
  known acceleration's relative error.  Heave changes only |f| and does not weigh the tilt down; optionally with the accelerometer's lever arm ``l`` (Vector3, m)
  as an unknown — an accelerometer high on a mast sees the roll's angular acceleration as a tilt, which a
  smoother averages out but a filter cannot — and the speed log's scale error ``k`` (Vector1),
* ``BetweenFactorVector(b_j, b_j+1)``: bias random walk, and priors fixing the first attitude (yaw is a gauge:
  without a compass the data cannot tell it) and the first bias.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from scipy.ndimage import uniform_filter1d
from scipy.signal import savgol_filter

from selfcal.core import inertial
from selfcal.factors.ship import gyro_scale_rotation_factor, tilt_factor
from selfcal.core.progress import quiet
from selfcal.core.solve import lag_stamp_s, optimize
from selfcal.models import ship

R_KEY, B_KEY, V_KEY = gtsam.symbol_shorthand.R, gtsam.symbol_shorthand.B, gtsam.symbol_shorthand.V
LEVER_ARM_KEY, SPEED_SCALE_KEY = gtsam.symbol("l", 0), gtsam.symbol("k", 0)
GYRO_SCALE_KEY = gtsam.symbol("g", 0)
RELATIVE_TOLERANCE = 1e-5  # LM converges in a few iterations, then crawls along the weakly determined lever arm
# components (horizontal ones, in a sea without turns) at a relative gain of ~1e-6 per iteration: attitudes then
# change by nanoradians, and an hour's graph would spend twenty minutes on it


@dataclass
class ShipInputs:
    """IMU samples with the speed (interpolated onto the IMU times, or None) of one voyage."""

    t_s: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray
    speed_m_s: np.ndarray | None
    gravity_m_s2: float = 9.80665
    gyro_noise_density: float = 1e-4  # rad s^-1 / sqrt(Hz)
    gyro_random_walk: float = 1e-5  # rad s^-2 / sqrt(Hz)
    speed_rate_m_s2: np.ndarray | None = None  # d speed / dt on the IMU times, when the source gives it
    speed_rate_sigma_m_s2: np.ndarray | None = None  # its 1-sigma (pipelines.ship.smoothed_speed)
    slow_speed_rate_m_s2: np.ndarray | None = None  # smoothed far more: the audit's surge driver (smoothed_speed)


@dataclass(frozen=True)
class ShipGraphOptions:
    keyframe_s: float = 0.2
    bias_segment_s: float = 10.0
    tilt_floor_rad: float = 0.002  # unmodelled slow horizontal accelerations (wave sway ~0.02 m/s^2) and
    # accelerometer bias instability, which no averaging removes
    known_acceleration_relative_sigma: float = 0.05  # the speed log's scale and rate are good to a few %
    unknown_acceleration_gain: float = 1.0  # without a speed source: sigma grows by this times ||f| - g| / g
    noise_window_s: float = 1.0  # the accelerometer's noise (and vibration) level is measured over this window
    tilt_average_s: float = 0.2  # the force is averaged over this centred window: the noise falls by its sample
    # count, and a roll of period T is attenuated by only (pi w / T)^2 / 6 (0.26 % at w = 0.2 s, T = 5 s)
    remove_known_acceleration: bool = True
    estimate_unknown_speed: bool = True  # without a speed source (none, or not removed), the speed through the
    # water is an unknown: the turns show it, the centrifugal v x yaw rate tilting the force across the hull
    speed_segment_s: float = 30.0  # the unknown speed is constant over segments this long, linked by a walk of
    speed_walk_m_s_sqrt_s: float = 0.1  # m/s per sqrt(s): a hull's surge of 0.05-0.25 m/s^2 over tens of seconds
    speed_prior_m_s: tuple = (0.0, 10.0)  # mean and sigma before the first turn (a ship's speeds, either way)
    initial_bias_sigma_rad_s: float = 0.1  # uncalibrated MEMS gyros start degrees per second off
    estimate_lever_arm: bool = True
    lever_arm_m: tuple = (0.0, 0.0, 0.0)  # known (or prior mean) accelerometer position from the centre of rotation
    lever_arm_prior_sigma_m: float = 20.0  # a ship's size: components the motion cannot show stay near the prior
    estimate_speed_scale: bool = False
    speed_scale: float = 0.0  # known speed-log scale error (used when not estimated)
    speed_scale_prior_sigma: float = 0.2
    speed_scale_regressor_s: float = 20.0  # the scale multiplies the hull acceleration smoothed over this centred
    # window (quartic Savitzky-Golay, SCALE_REGRESSOR_ORDER): the gyro's noise in v w, in the residual and in the same
    # keyframe's regressor, pulled the scale (errors in the variables: null turning voyages read +5.8 +- 1.6 %); a
    # plain 10 s mean bent the 5-10 s turn ramps (a 10 % scale read 7.2 +- 0.7 % beside two terms in centripetal
    # acceleration); a quadratic over 15 s still took enough of them that one voyage in 20 named a term instead
    angular_acceleration_window_s: float = 2.0  # Savitzky-Golay window for w_dot (centred: online, a 1 s delay)
    estimate_gyro_scale: bool = False  # the gyro's per-axis scale error s (raw = (1 + s) x true) as an unknown
    gyro_scale: tuple = (0.0, 0.0, 0.0)  # known gyro scale error (its prior mean when estimated)
    gyro_scale_prior_sigma: float = 0.1  # MEMS datasheets give +-3 % (MPU-6050); real boards show 7 %


@dataclass
class ShipEstimate:
    t_s: np.ndarray  # keyframe times
    roll: np.ndarray
    pitch: np.ndarray
    yaw: np.ndarray
    gyro_bias: np.ndarray  # (K, 3) at the keyframes
    seconds: float = 0.0
    lever_arm_m: np.ndarray | None = None  # estimated (final value), when in the graph
    speed_scale: float | None = None
    gyro_scale: np.ndarray | None = None
    speed_m_s: np.ndarray | None = None  # (K,) the unknown speed at the keyframes, when in the graph
    gyro_bias_covariance: np.ndarray | None = None  # (3, 3) marginal of the final bias segment, (rad/s)^2


def known_acceleration(inputs: ShipInputs, remove_known: bool) -> np.ndarray:
    """The hull acceleration the speed log and gyro explain (zero when not asked for or without a speed)."""
    if not remove_known or inputs.speed_m_s is None:
        return np.zeros_like(inputs.accel_m_s2)
    # a speed log's noise (cm/s per sample) differentiated sample by sample would be a surge "acceleration" of
    # tenths of a degree of tilt; a hull's surge changes over tens of seconds, so the rate is taken over 5 s
    speed_rate = (inputs.speed_rate_m_s2 if inputs.speed_rate_m_s2 is not None
                  else smooth_derivative(inputs.t_s, inputs.speed_m_s, SPEED_RATE_WINDOW_S))
    return ship.known_acceleration_S(inputs.speed_m_s, speed_rate, inputs.gyro_rad_s[:, 2])


SPEED_RATE_WINDOW_S = 5.0
SAVGOL_ORDER = 4  # quartic: a flat response up to the roll frequencies over a window long enough to quiet
# the gyro noise (a noisy w_dot would bias the lever arm low: errors in the variables)


SCALE_REGRESSOR_ORDER = 4  # the speed-log scale regressor's smoother: flat to the turns' ramps (its -3 dB at
# ~(order + 1) / (3.2 window): 13 s periods over 20 s, where a quadratic over 15 s passes 16 s)


def smooth_derivative(t_s: np.ndarray, x: np.ndarray, window_s: float) -> np.ndarray:
    """d x / dt along axis 0: Savitzky-Golay (quadratic over ``window_s``, centred), robust to sample noise."""
    rate = 1.0 / np.median(np.diff(t_s))
    n = max(5, int(round(window_s * rate)) | 1)
    if len(t_s) <= n:
        return np.gradient(x, t_s, axis=0)
    return savgol_filter(x, n, SAVGOL_ORDER, deriv=1, delta=1.0 / rate, axis=0)


def tilt_sigma_rad(noise_var_m2_s4: float, n_average: int, a_known_S: np.ndarray | None, f_S: np.ndarray, g: float,
                   options: ShipGraphOptions) -> float:
    """The sigma (rad, per axis) of one keyframe's tilt (the speed log rate's error, along the heading only, is
    apart: ``Keyframe.along_track_sigma_rad``).


    Terms: the measured noise across the force averaged over ``n_average`` samples; the floor of unmodelled
    slow accelerations; and the hull's acceleration.  With a speed source (``a_known_S`` given) the hull's
    horizontal acceleration is modelled and only its relative error enters: ``|f| - g`` is then heave, which
    does not tilt the force (the patent's point) and must not weigh it down.  Without one (``a_known_S`` None),
    ``|f| - g`` is the only evidence of unmodelled motion (turns, a hand moving a board), weak as it is (a
    horizontal ``a`` changes it by ``a^2 / 2g``), and the sigma grows with ``unknown_acceleration_gain`` times it.
    """
    if a_known_S is not None:
        hull = options.known_acceleration_relative_sigma * np.linalg.norm(a_known_S)
    else:
        hull = options.unknown_acceleration_gain * abs(np.linalg.norm(f_S) - g)
    return float(np.sqrt(noise_var_m2_s4 / max(n_average, 1) / g**2 + options.tilt_floor_rad**2 + (hull / g) ** 2))


def samples_per_keyframe(rate_hz: float, options: ShipGraphOptions) -> tuple[int, int]:
    """(samples averaged into one tilt, samples over which the noise is measured) at ``rate_hz``."""
    return max(1, int(round(options.tilt_average_s * rate_hz))), max(2, int(round(options.noise_window_s * rate_hz)))


@dataclass
class Keyframe:
    """What one keyframe brings: the gyro samples since the previous keyframe and the accelerometer at it."""

    t_s: float
    gyro_rad_s: np.ndarray  # (n, 3) samples from the previous keyframe up to this one (empty for the first)
    dt_s: np.ndarray  # (n,)
    accel_m_s2: np.ndarray  # (3,) specific force averaged over ``tilt_average_s``, centred on t_s
    A_S: np.ndarray  # (3, 3) lever-arm matrix [w_dot]x + [w]x^2 at t_s
    a_known_S: np.ndarray  # (3,) (dv/dt, v w_z, 0): the level-ship guide to the known hull acceleration (drivers,
    # sigma, start values); the tilt factor takes it exactly from a_known_S[0] and vw_S (models.ship.hull_acceleration_W)
    has_speed: bool = False
    tilt_sigma_rad: float = 0.01  # per axis (:func:`tilt_sigma_rad`)
    w_S: np.ndarray = field(default_factory=lambda: np.zeros(3))  # body rate averaged like the force, rad/s: the
    # centripetal term of an unknown speed
    vw_S: np.ndarray = field(default_factory=lambda: np.zeros(3))  # log speed times body rate, averaged likewise
    noise_tilt_sigma_rad: float = 0.0  # the part of tilt_sigma_rad the accelerometer's noise makes: white from one
    # keyframe to the next, unlike the floor and the hull terms (offline keyframes; the audit measures the floor by it)
    along_track_sigma_rad: float = 0.0  # the speed log rate's error / g: along the heading only (offline keyframes,
    # pipelines.ship.smoothed_speed; factors.ship.tilt_factor's along_track_ratio)
    scale_regressor: tuple | None = None  # (dv/dt, v w_S) smoothed over ``speed_scale_regressor_s``: what the
    # speed log's scale multiplies (offline keyframes; None: the keyframe's own)


def keyframes_from_inputs(inputs: ShipInputs, options: ShipGraphOptions) -> list[Keyframe]:
    """Keyframes every ``options.keyframe_s`` from a whole recording (derivatives centred: offline)."""
    t = inputs.t_s
    index = np.searchsorted(t, np.arange(t[0], t[-1], options.keyframe_s))
    a_known = known_acceleration(inputs, options.remove_known_acceleration)
    raw_surge = a_known[:, 0].copy()
    A = inertial.lever_arm_jacobian(inputs.gyro_rad_s, smooth_derivative(t, inputs.gyro_rad_s,
                                                                     options.angular_acceleration_window_s))
    dt = np.diff(t)
    n_average, n_noise = samples_per_keyframe(1.0 / np.median(dt), options)
    f_mean, noise_var = ship.averaged_specific_force(inputs.accel_m_s2, n_average, n_noise)
    # what is subtracted from the averaged force is averaged the same way (the residual is linear in them)
    A = uniform_filter1d(A, size=n_average, axis=0, mode="nearest")
    a_known = uniform_filter1d(a_known, size=n_average, axis=0, mode="nearest")
    w = uniform_filter1d(inputs.gyro_rad_s, size=n_average, axis=0, mode="nearest")
    raw_vw = (inputs.speed_m_s[:, None] * inputs.gyro_rad_s if inputs.speed_m_s is not None
              and options.remove_known_acceleration else np.zeros_like(w))
    vw = uniform_filter1d(raw_vw, size=n_average, axis=0, mode="nearest")
    surge_sigma = (inputs.speed_rate_sigma_m_s2 if inputs.speed_rate_sigma_m_s2 is not None
                   else np.zeros_like(t))
    # the scale's regressor: the same quantities smoothed (models.ship.level_residual's scale_regressor)
    n_regressor = max(SCALE_REGRESSOR_ORDER + 3, int(round(options.speed_scale_regressor_s / np.median(dt))) | 1)
    surge_regressor, vw_regressor = (savgol_filter(x, n_regressor, SCALE_REGRESSOR_ORDER, axis=0, mode="nearest")
                                     for x in (raw_surge, raw_vw))
    frames, previous = [], None
    for i in index:
        span = slice(previous, i) if previous is not None else slice(0, 0)
        has_speed = inputs.speed_m_s is not None and options.remove_known_acceleration
        sigma = tilt_sigma_rad(noise_var[i], n_average, a_known[i] if has_speed else None, f_mean[i],
                               inputs.gravity_m_s2, options)
        frames.append(Keyframe(float(t[i]), inputs.gyro_rad_s[span], dt[span], f_mean[i], A[i], a_known[i],
                               has_speed, sigma, w[i], vw[i], np.sqrt(noise_var[i] / n_average) / inputs.gravity_m_s2,
                               surge_sigma[i] / inputs.gravity_m_s2 if has_speed else 0.0,
                               (float(surge_regressor[i]), vw_regressor[i]) if has_speed else None))
        previous = i
    return frames


class ShipGraph:
    """The graph of one voyage, grown keyframe by keyframe (the same factors for batch, iSAM2 and live use)."""

    def __init__(self, options: ShipGraphOptions, gravity_m_s2: float, gyro_noise_density: float,
                 gyro_random_walk: float):
        self.options, self.gravity_m_s2, self.gyro_random_walk = options, gravity_m_s2, gyro_random_walk
        self.params = gtsam.PreintegratedRotationParams()
        self.params.setGyroscopeCovariance(gyro_noise_density**2 * np.eye(3))
        self.t0_s: float | None = None
        self.k = -1  # index of the last keyframe added
        self.last_speed_key: int | None = None  # the unknown speed's newest segment
        # the audit's generic terms: (key, phi over this graph's keyframes) tilt offsets, fitted (key in the
        # graph) or, for a held-out part, known (values given: subtracted); phi[k] a number or a function of the
        # attitude (factors.ship.tilt_factor)
        self.term_columns: list[tuple[int, object]] = []
        self.known_terms: list[tuple[np.ndarray, object]] = []  # (k (2,), phi over the keyframes)

    def bias_key(self, t_s: float) -> int:
        """The gyro bias segment of ``t_s``; one bias for the whole voyage when the sensor states no random walk
        (a constant bias: segments tied with a zero sigma made the system indeterminate)."""
        if self.gyro_random_walk <= 0.0:
            return B_KEY(0)
        return B_KEY(int((t_s - self.t0_s) // self.options.bias_segment_s))

    def speed_key(self, t_s: float) -> int:
        return V_KEY(int((t_s - self.t0_s) // self.options.speed_segment_s))

    def unknown_speed(self, frame: Keyframe) -> bool:
        return self.options.estimate_unknown_speed and not frame.has_speed

    def tilt_factor(self, frame: Keyframe, rotation_key: int, k: int | None = None,
                    along_track: bool = True) -> gtsam.CustomFactor:
        """The keyframe's tilt factor, with the hull acceleration as the options and the frame's speed source say
        (also what the audit evaluates its residuals with); ``k`` the keyframe's index among this graph's (for
        the audit's terms, default the newest); without ``along_track`` the residual is not weighed down along the
        heading (the audit's residual in rad)."""
        options = self.options
        speed_scale = options.estimate_speed_scale and frame.has_speed
        surge, vw = frame.a_known_S[0], frame.vw_S
        regressor = frame.scale_regressor if frame.scale_regressor is not None else (surge, vw)
        if not speed_scale and options.speed_scale:  # a known scale (the held-out half's)
            surge, vw = surge + options.speed_scale * regressor[0], vw + options.speed_scale * regressor[1]
        speed = self.speed_key(frame.t_s) if self.unknown_speed(frame) else None
        if speed is not None:
            surge, vw, regressor = 0.0, frame.w_S, None  # per m/s of speed
        k = self.k if k is None else k
        known = [(coefficient, phi[k]) for coefficient, phi in self.known_terms]
        return tilt_factor(gtsam.noiseModel.Isotropic.Sigma(2, frame.tilt_sigma_rad), rotation_key, frame.accel_m_s2,
                           frame.A_S, surge, vw, LEVER_ARM_KEY if options.estimate_lever_arm else None,
                           SPEED_SCALE_KEY if speed_scale else None, options.lever_arm_m, speed,
                           [(key, phi[k]) for key, phi in self.term_columns], known,
                           frame.along_track_sigma_rad / frame.tilt_sigma_rad if along_track else 0.0,
                           regressor if speed_scale else None)

    def tilt_start(self, frame: Keyframe) -> gtsam.Rot3:
        roll, pitch = inertial.tilt_from_specific_force(frame.accel_m_s2 - frame.a_known_S)
        return gtsam.Rot3.Ypr(0.0, float(pitch), float(roll))

    def add(self, frame: Keyframe, estimate: gtsam.Values | None, propagate: bool):
        """(factors, new values) that ``frame`` brings as keyframe k+1.

        ``estimate`` holds the current solution or start values (the bias to preintegrate about, the attitude
        the gyro carries forward); without ``propagate`` roll and pitch start at the accelerometer tilt.
        """
        options = self.options
        self.k += 1
        k = self.k
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            self.t0_s = frame.t_s
        speed_scale = options.estimate_speed_scale and frame.has_speed
        graph.add(self.tilt_factor(frame, R_KEY(k)))
        if self.unknown_speed(frame):
            self._add_speed(graph, values, estimate, self.speed_key(frame.t_s))
        if k == 0:
            self.previous_t_s = frame.t_s
            if options.estimate_lever_arm:
                graph.add(gtsam.PriorFactorVector(LEVER_ARM_KEY, np.asarray(options.lever_arm_m, dtype=float),
                                                  gtsam.noiseModel.Isotropic.Sigma(3, options.lever_arm_prior_sigma_m)))
                values.insert(LEVER_ARM_KEY, np.asarray(options.lever_arm_m, dtype=float))
            if speed_scale:
                graph.add(gtsam.PriorFactorVector(SPEED_SCALE_KEY, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(
                    1, options.speed_scale_prior_sigma)))
                values.insert(SPEED_SCALE_KEY, np.zeros(1))
            if options.estimate_gyro_scale:
                scale_prior = np.asarray(options.gyro_scale, dtype=float)
                graph.add(gtsam.PriorFactorVector(GYRO_SCALE_KEY, scale_prior, gtsam.noiseModel.Isotropic.Sigma(
                    3, options.gyro_scale_prior_sigma)))
                values.insert(GYRO_SCALE_KEY, scale_prior)
            start = self.tilt_start(frame)
            graph.add(gtsam.PriorFactorRot3(R_KEY(0), start, gtsam.noiseModel.Diagonal.Sigmas(np.array([0.2, 0.2, 1e-3]))))
            graph.add(gtsam.PriorFactorVector(self.bias_key(frame.t_s), np.zeros(3),
                                              gtsam.noiseModel.Isotropic.Sigma(3, options.initial_bias_sigma_rad_s)))
            values.insert(R_KEY(0), start)
            values.insert(self.bias_key(frame.t_s), np.zeros(3))
            return graph, values
        previous_bias, bias = self.bias_key(self.previous_t_s), self.bias_key(frame.t_s)
        self.previous_t_s = frame.t_s
        bias_hat = estimate.atVector(previous_bias) if estimate is not None else np.zeros(3)
        gyro_rad_s = frame.gyro_rad_s
        if not options.estimate_gyro_scale and any(options.gyro_scale):  # a known scale error: true = raw / (1 + s)
            # (the bias estimated is then the raw bias / (1 + s): the same constant, in true-rate units)
            gyro_rad_s = gyro_rad_s / (1.0 + np.asarray(options.gyro_scale, dtype=float))
        pim = gtsam.PreintegratedAhrsMeasurements(self.params, bias_hat)
        for w, dt in zip(gyro_rad_s, frame.dt_s):
            pim.integrateMeasurement(w, float(dt))
        if options.estimate_gyro_scale:  # the AHRSFactor's error and noise, plus the scale (GTSAM's takes none)
            graph.add(gyro_scale_rotation_factor(gtsam.noiseModel.Gaussian.Covariance(pim.preintMeasCov()),
                                                 R_KEY(k - 1), R_KEY(k), previous_bias, GYRO_SCALE_KEY,
                                                 frame.gyro_rad_s, frame.dt_s, bias_hat))
        else:
            graph.add(gtsam.AHRSFactor(R_KEY(k - 1), R_KEY(k), previous_bias, pim))
        if bias != previous_bias:
            graph.add(gtsam.BetweenFactorVector(previous_bias, bias, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(
                3, self.gyro_random_walk * np.sqrt(options.bias_segment_s))))
            values.insert(bias, bias_hat)
        propagated = estimate.atRot3(R_KEY(k - 1)).compose(pim.deltaRij())
        if not propagate:  # batch: roll and pitch from the accelerometer (a gyro chain from a bias of degrees per
            # second would wrap around before LM could pull it back), heading carried by the gyro (the data say
            # nothing else about it, and a heading left at zero costs LM dozens of iterations)
            tilt = self.tilt_start(frame).ypr()
            propagated = gtsam.Rot3.Ypr(propagated.ypr()[0], tilt[1], tilt[2])
        values.insert(R_KEY(k), propagated)
        return graph, values

    def _add_speed(self, graph, values, estimate, key):
        """The unknown speed's segment ``key``: a prior on the first, a random walk from the one before."""
        if (estimate is not None and estimate.exists(key)) or values.exists(key):
            return
        mean, sigma = self.options.speed_prior_m_s
        previous = self.last_speed_key
        if previous is None:
            graph.add(gtsam.PriorFactorVector(key, np.array([mean]), gtsam.noiseModel.Isotropic.Sigma(1, sigma)))
            start = np.array([mean])
        else:
            segments = gtsam.Symbol(key).index() - gtsam.Symbol(previous).index()  # > 1 across a gap in the data
            step = self.options.speed_walk_m_s_sqrt_s * np.sqrt(self.options.speed_segment_s * segments)
            graph.add(gtsam.BetweenFactorVector(previous, key, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, step)))
            start = estimate.atVector(previous) if estimate is not None and estimate.exists(previous) else np.array([mean])
        values.insert(key, start)
        self.last_speed_key = key


class OnlineShip:
    """Incremental fixed-lag smoother (iSAM2 inside): memory and time per keyframe stay bounded over any voyage.

    ``add(frame)`` returns the filtered attitude (roll, pitch, yaw, rad), the current gyro bias and the 3x3
    marginal covariance of the attitude (rad^2, tangent space of R_W_S).
    """

    def __init__(self, graph: ShipGraph, lag_s: float = 60.0, lag_step_s: float = 6.0):
        params = gtsam.ISAM2Params()
        params.setFactorization("QR")  # Cholesky met indeterminate systems on long, tightly linked chains
        self.graph, self.smoother = graph, gtsam.IncrementalFixedLagSmoother(lag_s, params)
        # keyframes leave the window in blocks of lag_step_s (core.solve.lag_stamp_s): one update in 30
        # re-eliminates the whole window instead of each, and the newest attitude's covariance stays cheap
        self.lag_step_s = lag_step_s
        self.estimate = gtsam.Values()  # what the next keyframe reads: see _newest_estimate
        self._keys: set[int] = set()  # every key given to the smoother

    def add(self, frame: Keyframe, covariance: bool = False):
        g, v = self.graph.add(frame, self.estimate if self.graph.k >= 0 else None, propagate=True)
        k = self.graph.k
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        # the constants and the current bias are re-stamped every keyframe so the window never drops them
        for key in (R_KEY(k), self.graph.bias_key(frame.t_s), self.graph.last_speed_key, LEVER_ARM_KEY,
                    SPEED_SCALE_KEY, GYRO_SCALE_KEY):
            if key is not None and (v.exists(key) or self.estimate.exists(key)):
                stamps.insert((key, lag_stamp_s(frame.t_s, self.lag_step_s)))
        self.smoother.update(g, v, stamps)
        self._keys.update(v.keys())
        self.estimate = self._newest_estimate(k, frame)
        yaw, pitch, roll = self.estimate.atRot3(R_KEY(k)).ypr()
        cov = self.smoother.marginalCovariance(R_KEY(k)) if covariance else None
        return (roll, pitch, yaw), self.estimate.atVector(self.graph.bias_key(frame.t_s)), cov

    def _newest_estimate(self, k: int, frame: Keyframe) -> gtsam.Values:
        """The estimate of what the next keyframe and the outputs read: the newest attitude, the current bias and
        speed segment, the constants.  ``calculateEstimate()`` would build every variable of the window at every
        keyframe (a third of the streaming CPU, measured)."""
        s, out = self.smoother, gtsam.Values()
        out.insert(R_KEY(k), s.calculateEstimateRot3(R_KEY(k)))
        for key in (self.graph.bias_key(frame.t_s), self.graph.last_speed_key, LEVER_ARM_KEY, SPEED_SCALE_KEY,
                    GYRO_SCALE_KEY):
            if key is not None and key in self._keys and not out.exists(key):
                out.insert(key, s.calculateEstimateVector(key))
        return out


class ShipSmoother:
    """One recorded voyage: ``batch()`` solves the whole graph at once, ``online()`` replays it keyframe by
    keyframe through :class:`OnlineShip` as a live system would."""

    def __init__(self, inputs: ShipInputs, options: ShipGraphOptions = ShipGraphOptions()):
        self.inputs, self.options = inputs, options
        self.keyframes = keyframes_from_inputs(inputs, options)

    def _graph(self) -> ShipGraph:
        return ShipGraph(self.options, self.inputs.gravity_m_s2, self.inputs.gyro_noise_density,
                         self.inputs.gyro_random_walk)

    def batch(self, progress=quiet) -> ShipEstimate:
        import time
        start = time.perf_counter()
        progress("build the graph")
        builder = self._graph()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for frame in self.keyframes:
            g, v = builder.add(frame, values if builder.k >= 0 else None, propagate=False)
            graph.push_back(g)
            values.insert(v)
        result = optimize(graph, values, max_iterations=50, relative_tolerance=RELATIVE_TOLERANCE, progress=progress)
        ypr = np.array([result.atRot3(R_KEY(k)).ypr() for k in range(len(self.keyframes))])
        bias = np.array([result.atVector(builder.bias_key(f.t_s)) for f in self.keyframes])
        speed = [result.atVector(builder.speed_key(f.t_s))[0] for f in self.keyframes if builder.unknown_speed(f)]
        progress("gyro bias covariance")
        covariance = final_bias_covariance(graph, result, builder.bias_key(self.keyframes[-1].t_s))
        return ShipEstimate(self._times(), ypr[:, 2], ypr[:, 1], ypr[:, 0], bias, time.perf_counter() - start,
                            *_constants(result), np.array(speed) if speed else None, covariance)

    def online(self, lag_s: float = 60.0, progress=quiet) -> ShipEstimate:
        """The filtered attitudes (each as first solved), replayed through :class:`OnlineShip`."""
        import time
        start = time.perf_counter()
        online = OnlineShip(self._graph(), lag_s)
        attitudes, biases, speeds = [], [], []
        for i, frame in enumerate(self.keyframes):
            progress("keyframes (iSAM2)", i, len(self.keyframes))
            rpy, bias, _ = online.add(frame)
            attitudes.append(rpy)
            biases.append(bias)
            if online.graph.unknown_speed(frame):
                speeds.append(online.estimate.atVector(online.graph.last_speed_key)[0])
        rpy = np.array(attitudes)
        try:
            covariance = online.smoother.marginalCovariance(online.graph.bias_key(self.keyframes[-1].t_s))
        except RuntimeError:  # as final_bias_covariance: no axis vouched for
            covariance = None
        return ShipEstimate(self._times(), rpy[:, 0], rpy[:, 1], rpy[:, 2], np.array(biases),
                            time.perf_counter() - start, *_constants(online.estimate),
                            np.array(speeds) if speeds else None, covariance)

    def _times(self) -> np.ndarray:
        return np.array([f.t_s for f in self.keyframes])


def final_bias_covariance(graph, values, key: int) -> np.ndarray | None:
    """The marginal covariance of the final bias segment (GTSAM's sparse marginals), or None when the information
    matrix is singular or too badly conditioned for them (the report then vouches for no axis).  Never the dense
    fallback of :func:`selfcal.core.solve.marginal_covariances`: an hour's voyage has 54,000 unknowns."""
    try:
        return gtsam.Marginals(graph, values).marginalCovariance(key)
    except RuntimeError:
        return None


def _constants(values) -> tuple:
    return (values.atVector(LEVER_ARM_KEY) if values.exists(LEVER_ARM_KEY) else None,
            float(values.atVector(SPEED_SCALE_KEY)[0]) if values.exists(SPEED_SCALE_KEY) else None,
            values.atVector(GYRO_SCALE_KEY) if values.exists(GYRO_SCALE_KEY) else None)
