"""The laser-tracker target as a factor graph, online (iSAM2 / fixed-lag) and offline (batch), with fault gating.

One engine, :class:`TrackerEstimator` (:mod:`.estimator`), consumes samples in timestamp order.  IMU samples are
preintegrated; every ``keyframe_s`` a keyframe ``(X_k, V_k, B_k)`` enters with a ``CombinedImuFactor`` and the
factors of the measurements that arrived since the previous keyframe (:mod:`selfcal.factors.tracker`).  Its
steps, one module each:

- :mod:`.alignment`: a measurement taken at ``t_m`` is moved to the keyframe time ``t_k`` with the IMU-propagated
  motion between the two instants.
- :mod:`.gate`: the chi-square gate (hard faults: spikes, outliers, tracker jumps),
  ``b^T S^-1 b`` with ``S = I + A P A^T`` against ``chi2(dim).ppf(1 - gate_alpha)``, and the decision on each
  measurement (every decision is returned with its statistic).
- :mod:`.eigen`: the eigenvalue detector (soft faults: bias ramps, a stuck output).  The normalised residuals of
  the inclinometer's factors fill a sliding window of ``n``; every ``stride`` samples the extreme eigenvalues of
  ``W = sum nu nu^T`` are compared with the thresholds for which a fault-free sensor (``W ~ Wishart_m(n, I)``)
  raises ``false_alarms_per_hour`` at most.  On detection all the sensor's factors still inside the smoother are
  removed again (``factorsToRemove``) and its new factors are held out; it is readmitted when a full window of
  its (monitored, not added) residuals passes the same test.  Rejected inclinometer samples go to the detector
  too, winsorised onto the gate's boundary, so a ramp the gate keeps catching is declared within seconds.
- :mod:`.vibration`: vibration is modelled, not alarmed: the inclinometer factor's covariance grows with the
  vibration the accelerometer shows over a window centred on the sample (the sample enters provisionally at once
  and is re-decided when the window is complete) and with the high-frequency energy of its own residuals.
- :mod:`.checks`: which sensor is held out; the stuck-output test (an inclinometer repeating its output exactly,
  ``GatingOptions.frozen_samples`` times, is held out at once and readmitted with its first moving sample); the
  accelerometer-bias drift test (a slow ramp the state follows); the recovery test.
- :mod:`.prism` and :mod:`.inclinometer`: each sensor's path from its samples to the factors of a keyframe (the
  camera's, one factor per sample, is inline in :mod:`.estimator`).
- :mod:`.bookkeeping`: the smoother's factor indices per sensor and the log of every factor.
- :mod:`.options`: sensor noise and geometry, gating and solver settings.

Solvers: ``'isam2'`` (gtsam.ISAM2, the whole history), ``'fixed-lag'`` (gtsam.IncrementalFixedLagSmoother over
``lag_s``: bounded memory over hours), and :func:`batch_smooth` (:mod:`.batch`: the same accepted factors over
all keyframes, Gauss-Newton from the online estimates, Levenberg-Marquardt if a step fails).
"""
from selfcal.graphs.tracker.batch import batch_smooth, gauss_newton
from selfcal.graphs.tracker.eigen import EigenDetector
from selfcal.graphs.tracker.estimator import TrackerEstimator
from selfcal.graphs.tracker.options import UNGATED, GatingOptions, SensorNoise, TrackerOptions

__all__ = ["UNGATED", "EigenDetector", "GatingOptions", "SensorNoise", "TrackerEstimator", "TrackerOptions",
           "batch_smooth", "gauss_newton"]
