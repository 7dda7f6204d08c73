"""The inertial measurement model every system with an IMU shares (imu, imu-pair, ship, tracker, scan).

Frames: ``S`` is the sensor (body) frame, ``W`` a local-level world frame with z up.  An accelerometer
measures specific force ``f_S = R_W_S^T (a_W + g e_z)`` (m s^-2); at rest that is ``R_W_S^T (0, 0, g)``, so
its direction gives roll and pitch (:func:`tilt_from_specific_force`).  A second point of a rigid body at
``r`` (body frame) feels ``f_1 = f_0 + w_dot x r + w x (w x r)`` (:func:`specific_force_at_lever_arm`).
Sensor noise follows Kalibr's continuous-time model (:class:`ImuNoise`).

References
----------
Kalibr wiki, "IMU Noise Model" (noise densities, random walks and their discrete-time forms).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfcal.core import so3

STANDARD_GRAVITY_M_S2 = 9.80665


def tilt_from_specific_force(f_S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch (rad) of the total force direction, ``f_S`` (N, 3) or (3,), any unit.

    With ``R_W_S = Rz(yaw) Ry(pitch) Rx(roll)`` (ZYX): ``Rz^T`` leaves ``(0, 0, g)`` unchanged,
    ``Ry(pitch)^T`` gives ``g (-sin pitch, 0, cos pitch)``, ``Rx(roll)^T`` gives
    ``f = g (-sin pitch, sin roll cos pitch, cos roll cos pitch)``; pitch lies in [-pi/2, pi/2].
    """
    f = np.asarray(f_S, dtype=float)
    roll = np.arctan2(f[..., 1], f[..., 2])
    pitch = np.arctan2(-f[..., 0], np.hypot(f[..., 1], f[..., 2]))
    return roll, pitch


def specific_force_at_lever_arm(f0_S0, w_S0, w_dot_S0, r_m_S0):
    """Specific force at a point displaced by r (imu0 frame) on a rigid body, in the imu0 frame.

    ``f_1 = f_0 + w_dot x r + w x (w x r)``; all arrays (N, 3) or (3,), SI units.
    """
    r = np.broadcast_to(np.asarray(r_m_S0, dtype=float), np.shape(w_S0))
    return np.asarray(f0_S0) + np.cross(w_dot_S0, r) + np.cross(w_S0, np.cross(w_S0, r))


def lever_arm_jacobian(w_S0, w_dot_S0) -> np.ndarray:
    """d f_1 / d r of :func:`specific_force_at_lever_arm`: [w_dot]x + [w]x[w]x, shape (N, 3, 3)."""
    W = so3.hat(w_S0)
    return so3.hat(w_dot_S0) + W @ W


@dataclass(frozen=True)
class ImuNoise:
    """IMU noise in Kalibr's keys and meaning (continuous-time, per axis).

    Defaults are ADIS16448-class MEMS figures: the noise densities of the EuRoC sensor.yaml, the random walks
    of Kalibr's ADIS16448 example imu.yaml.
    """

    accelerometer_noise_density: float = 2.0e-3  # m s^-2 / sqrt(Hz)
    gyroscope_noise_density: float = 1.6968e-4  # rad s^-1 / sqrt(Hz)
    accelerometer_random_walk: float = 2.0e-4  # m s^-3 / sqrt(Hz)
    gyroscope_random_walk: float = 4.0e-6  # rad s^-2 / sqrt(Hz)

    KEYS = ("accelerometer_noise_density", "gyroscope_noise_density", "accelerometer_random_walk",
            "gyroscope_random_walk")

    @classmethod
    def from_sensor_yaml(cls, meta: dict) -> ImuNoise:
        """From a sensor.yaml dict; missing keys keep the defaults."""
        return cls(**{k: float(meta[k]) for k in cls.KEYS if k in meta})

    @classmethod
    def zero(cls) -> ImuNoise:
        return cls(0.0, 0.0, 0.0, 0.0)

    def to_dict(self) -> dict:
        return {k: float(getattr(self, k)) for k in self.KEYS}

    def white_sigma(self, rate_hz: float) -> tuple[float, float]:
        """Discrete per-sample sigma (accel m s^-2, gyro rad s^-1): ``density * sqrt(rate_hz)``."""
        return (self.accelerometer_noise_density * np.sqrt(rate_hz),
                self.gyroscope_noise_density * np.sqrt(rate_hz))

    def walk_step_sigma(self, rate_hz: float) -> tuple[float, float]:
        """Per-sample bias random-walk step (accel, gyro): ``random_walk * sqrt(1 / rate_hz)``."""
        return (self.accelerometer_random_walk / np.sqrt(rate_hz), self.gyroscope_random_walk / np.sqrt(rate_hz))
