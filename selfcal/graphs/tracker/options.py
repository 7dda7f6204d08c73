"""What the tracker estimator is told: the sensors' noise and geometry, the fault gating's settings, the solver's."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SENSORS = ("tracker0", "incl0", "cam0")


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
    # keyframes leave the fixed-lag window in blocks of this much (core.solve.lag_stamp_s): the window holds
    # lag_s to lag_s + lag_step_s, and only one update in lag_step_s / keyframe_s re-eliminates all of it
    lag_step_s: float = 1.0
    mode: str = "fixed-lag"  # 'fixed-lag' | 'isam2'
    gating: GatingOptions = GatingOptions()
    keep_graph: bool = False  # keep every factor and keyframe for batch_smooth (memory grows with the run)
    covariance: bool = True  # marginal covariance per output (needed by the gate's P as well)
    initial_gyro_bias_sigma: float = 5e-3
    initial_accel_bias_sigma: float = 0.05
