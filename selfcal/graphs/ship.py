"""Vessel attitude and gyro bias as a factor graph (batch and iSAM2), corrected by the accelerometer's tilt.

Variables: ``R_k`` (Rot3, body -> local level) at keyframes every ``keyframe_s``, gyro bias ``b_j`` (Vector3)
per bias segment of ``bias_segment_s``.  Factors, all GTSAM's own:

* ``AHRSFactor(R_k, R_k+1, b_j)``: gyro preintegrated between keyframes (``PreintegratedAhrsMeasurements``),
* ``AttitudeFactorRot3(R_k)``: the up direction measured by the accelerometer (total force, known accelerations
  removed) against the world's up, with a sigma that grows with the disturbance the accelerometer itself shows
  (|f| departing from g: heave, surge, vibration), so a rough sea weighs the tilt less instead of biasing it,
* ``BetweenFactorVector(b_j, b_j+1)``: bias random walk, and priors fixing the first attitude (yaw is a gauge:
  without a compass the data cannot tell it) and the first bias.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from selfcal.graphs.solve import optimize
from selfcal.models import ship, so3

R_KEY, B_KEY = gtsam.symbol_shorthand.R, gtsam.symbol_shorthand.B


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


@dataclass(frozen=True)
class ShipGraphOptions:
    keyframe_s: float = 0.2
    bias_segment_s: float = 10.0
    tilt_sigma_rad: float = 0.01  # floor: accelerometer noise and unmodelled small accelerations
    disturbance_gain: float = 3.0  # tilt sigma grows by this times ||f| - g| / g
    remove_known_acceleration: bool = True
    initial_bias_sigma_rad_s: float = 0.1  # uncalibrated MEMS gyros start degrees per second off


@dataclass
class ShipEstimate:
    t_s: np.ndarray  # keyframe times
    roll: np.ndarray
    pitch: np.ndarray
    yaw: np.ndarray
    gyro_bias: np.ndarray  # (K, 3) at the keyframes
    seconds: float = 0.0


def corrected_specific_force(inputs: ShipInputs, remove_known: bool) -> np.ndarray:
    """The accelerometer minus the accelerations the speed log and gyro explain (when asked and possible)."""
    if not remove_known or inputs.speed_m_s is None:
        return inputs.accel_m_s2
    speed_rate = np.gradient(inputs.speed_m_s, inputs.t_s)
    return inputs.accel_m_s2 - ship.known_acceleration_S(inputs.speed_m_s, speed_rate, inputs.gyro_rad_s[:, 2])


def _tilt_noise(f: np.ndarray, g: float, options: ShipGraphOptions):
    disturbance = abs(np.linalg.norm(f) - g) / g
    return gtsam.noiseModel.Isotropic.Sigma(2, options.tilt_sigma_rad + options.disturbance_gain * disturbance)


class ShipSmoother:
    """Builds the graph keyframe by keyframe; ``batch()`` solves it at once, ``online()`` feeds iSAM2 as it goes."""

    def __init__(self, inputs: ShipInputs, options: ShipGraphOptions = ShipGraphOptions()):
        self.inputs, self.options = inputs, options
        t = inputs.t_s
        self.keyframe_index = np.searchsorted(t, np.arange(t[0], t[-1], options.keyframe_s))
        self.f = corrected_specific_force(inputs, options.remove_known_acceleration)
        params = gtsam.PreintegratedRotationParams()
        params.setGyroscopeCovariance(inputs.gyro_noise_density**2 * np.eye(3))
        self.params = params

    def _bias_of(self, k: int) -> int:
        return B_KEY(int(self.inputs.t_s[self.keyframe_index[k]] - self.inputs.t_s[0]) // int(self.options.bias_segment_s))

    def _initial_rotation(self, k: int) -> gtsam.Rot3:
        roll, pitch = ship.tilt_from_specific_force(self.f[self.keyframe_index[k]])
        return gtsam.Rot3.Ypr(0.0, float(pitch), float(roll))

    def factors_for(self, k: int, values_estimate=None, online: bool = False):
        """New factors and initial values that keyframe k brings (k = 0: priors); ``values_estimate`` holds
        the current estimate (the bias to preintegrate about, and online the attitude to propagate)."""
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        i = self.keyframe_index[k]
        up = gtsam.Unit3(np.array([0.0, 0.0, 1.0]))
        f_k = self.f[i]
        graph.add(gtsam.AttitudeFactorRot3(R_KEY(k), up, _tilt_noise(f_k, self.inputs.gravity_m_s2, self.options),
                                           gtsam.Unit3(f_k / np.linalg.norm(f_k))))
        bias_key = self._bias_of(k)
        if k == 0:
            graph.add(gtsam.PriorFactorRot3(R_KEY(0), self._initial_rotation(0),
                                            gtsam.noiseModel.Diagonal.Sigmas(np.array([0.2, 0.2, 1e-3]))))
            graph.add(gtsam.PriorFactorVector(bias_key, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(
                3, self.options.initial_bias_sigma_rad_s)))
            values.insert(R_KEY(0), self._initial_rotation(0))
            values.insert(bias_key, np.zeros(3))
            return graph, values
        j = self.keyframe_index[k - 1]
        previous_bias = self._bias_of(k - 1)
        bias_hat = values_estimate.atVector(previous_bias) if values_estimate is not None else np.zeros(3)
        pim = gtsam.PreintegratedAhrsMeasurements(self.params, bias_hat)
        t = self.inputs.t_s
        for s in range(j, i):
            pim.integrateMeasurement(self.inputs.gyro_rad_s[s], float(t[s + 1] - t[s]))
        graph.add(gtsam.AHRSFactor(R_KEY(k - 1), R_KEY(k), previous_bias, pim))
        if bias_key != previous_bias:
            dt = self.options.bias_segment_s
            graph.add(gtsam.BetweenFactorVector(previous_bias, bias_key, np.zeros(3),
                                                gtsam.noiseModel.Isotropic.Sigma(
                                                    3, self.inputs.gyro_random_walk * np.sqrt(dt))))
            values.insert(bias_key, bias_hat)
        if online:  # propagate the latest estimate with the gyro
            values.insert(R_KEY(k), values_estimate.atRot3(R_KEY(k - 1)).compose(pim.deltaRij()))
        else:  # batch: start every keyframe at its accelerometer tilt; a gyro chain from an unknown bias of
            # degrees per second would wrap around before LM could pull it back
            values.insert(R_KEY(k), self._initial_rotation(k))
        return graph, values

    def batch(self) -> ShipEstimate:
        import time
        start = time.perf_counter()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for k in range(len(self.keyframe_index)):
            g, v = self.factors_for(k, values if k else None)
            graph.push_back(g)
            values.insert(v)
        result = optimize(graph, values, max_iterations=50)
        return self._estimate(result, time.perf_counter() - start)

    def online(self) -> ShipEstimate:
        """iSAM2, one keyframe at a time; the returned attitudes are the filtered ones (each as first solved)."""
        import time
        start = time.perf_counter()
        params = gtsam.ISAM2Params()
        params.setFactorization("QR")  # Cholesky met indeterminate systems on long, tightly linked chains
        isam = gtsam.ISAM2(params)
        current = gtsam.Values()
        rolls, pitches, yaws, biases = [], [], [], []
        for k in range(len(self.keyframe_index)):
            g, v = self.factors_for(k, current if k else None, online=True)
            isam.update(g, v)
            current = isam.calculateEstimate()
            ypr = current.atRot3(R_KEY(k)).ypr()
            yaws.append(ypr[0])
            pitches.append(ypr[1])
            rolls.append(ypr[2])
            biases.append(current.atVector(self._bias_of(k)))
        t = self.inputs.t_s[self.keyframe_index]
        return ShipEstimate(t, np.array(rolls), np.array(pitches), np.array(yaws), np.array(biases),
                            time.perf_counter() - start)

    def _estimate(self, values, seconds) -> ShipEstimate:
        ypr = np.array([values.atRot3(R_KEY(k)).ypr() for k in range(len(self.keyframe_index))])
        bias = np.array([values.atVector(self._bias_of(k)) for k in range(len(self.keyframe_index))])
        return ShipEstimate(self.inputs.t_s[self.keyframe_index], ypr[:, 2], ypr[:, 1], ypr[:, 0], bias, seconds)
