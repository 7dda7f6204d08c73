"""Sensor checks: which sensor is held out, the stuck-output test, the accelerometer-bias drift test and the
recovery test that readmits a held-out sensor."""
from __future__ import annotations

import logging
import math
from collections import deque

import numpy as np

from selfcal.graphs.tracker.bookkeeping import FactorBook
from selfcal.graphs.tracker.eigen import EigenDetector
from selfcal.graphs.tracker.options import SENSORS, GatingOptions

log = logging.getLogger(__name__)


class SensorHealth:
    """Which sensor is held out and since when, which readmitted one is in its grace, and the decisions of the
    current keyframe (each with its statistic and threshold).

    Single-fault assumption: while one sensor is held out the others' residuals carry its pull on the state, so
    their detectors' windows restart instead of accusing them in cascade.
    """

    def __init__(self, detectors: dict[str, EigenDetector], gating: GatingOptions, book: FactorBook):
        self.detectors = detectors
        self.book = book
        self.faulty = {s: False for s in SENSORS}
        self.fault_t_ns: dict[str, int] = {}
        self.grace_until_ns: dict[str, int] = {}
        self.resettled_ns = 0  # no bias-drift test before (the state re-converges after a hold-out)
        self.decisions: list[dict] = []
        self._resettle_s = gating.bias_drift_resettle_s

    def any_fault(self) -> bool:
        return any(self.faulty.values())

    def in_grace(self, sensor: str, t_ns: int) -> bool:
        return t_ns < self.grace_until_ns.get(sensor, 0)

    def held_s(self, sensor: str, t_ns: int) -> float:
        return (t_ns - self.fault_t_ns.get(sensor, t_ns)) * 1e-9

    def hold_out(self, sensor: str, t_ns: int | None) -> None:
        """Hold the sensor out from ``t_ns`` (None: the state recursor's alarm, which leaves the hold-out clock of
        ``max_holdout_s`` as it was) and restart every detector's window."""
        self.faulty[sensor] = True
        if t_ns is not None:
            self.fault_t_ns[sensor] = int(t_ns)
        for detector in self.detectors.values():
            detector.reset()

    def declare_fault(self, tag: str, t_ns: int, k: int, test: dict) -> None:
        """Hold ``tag``'s sensor out and remove its factors still in the smoother; log ``test`` as the decision."""
        sensor = tag.split("/")[0]
        self.hold_out(sensor, t_ns)
        self.decisions.append({"t_ns": int(t_ns), "sensor": tag, **test, "decision": "fault"})
        self.book.remove_recent(sensor, k)

    def readmit(self, sensor: str, t_ns: int) -> None:
        """Readmit the sensor; the readmitted inclinometer pulls tilt and accelerometer bias back together, so the
        bias-drift test waits ``bias_drift_resettle_s``."""
        self.faulty[sensor] = False
        for detector in self.detectors.values():
            detector.reset()
        self.resettled_ns = int(t_ns + 1e9 * self._resettle_s)


def readmission(detector: EigenDetector, lam_max: float | None, held_s: float, max_holdout_s: float) -> str | None:
    """The recovery test of a held-out sensor on the last test of its monitored (not added) residuals:
    ``'recovered'`` when a window passes both sides (:meth:`EigenDetector.certifies_recovery`),
    ``'readmitted_after_holdout'`` after ``max_holdout_s`` if its residuals still have their noise (``lambda_min``
    above the lower threshold, or a sensor that never showed it: not stuck), None while it stays held out."""
    if lam_max is None:
        return None
    if detector.certifies_recovery(lam_max):
        return "recovered"
    if held_s > max_holdout_s and detector.keeps_its_noise():
        return "readmitted_after_holdout"
    return None


class FrozenOutput:
    """The inclinometer's stuck-output test (``GatingOptions.frozen_samples``): held out when its output repeats
    exactly that many times, readmitted (to the chi-square gate) as soon as it moves again.

    A working sensor's noise never repeats both axes; the eigenvalue detector's window would take seconds to see
    the missing noise."""

    def __init__(self, samples: int, health: SensorHealth):
        self.samples = samples  # 0: the test is off
        self.health = health
        self.stuck = False
        self._previous_up_B = None
        self._repeats = 0
        self._moving_since_ns = 0  # the first moving sample after a stuck spell (samples before it are decided later)

    def holds_out(self, t_ns: int) -> bool:
        """A sample at ``t_ns`` is held out by this test: the output is stuck, or was when the sample was taken."""
        return self.stuck or t_ns < self._moving_since_ns

    def check(self, t_ns: int, up_B: np.ndarray, k: int) -> None:
        """One raw reading (up direction, body frame): a fault when it has just repeated ``samples`` times (and
        no sensor is held out yet), a readmission on the first moving reading of a stuck spell."""
        if not self.samples:
            return
        same = self._previous_up_B is not None and np.array_equal(up_B, self._previous_up_B)
        self._previous_up_B = up_B
        self._repeats = self._repeats + 1 if same else 0
        health = self.health
        if self._repeats == self.samples and not health.any_fault():
            health.declare_fault("incl0", t_ns, k, {"test": "frozen", "statistic": self.samples,
                                                    "threshold": self.samples})
            self.stuck = True
            log.info("incl0 stuck: %d identical outputs", self.samples + 1)
        elif not same and self.stuck:
            self.stuck = False
            self._moving_since_ns = int(t_ns)
            held_s = health.held_s("incl0", t_ns)
            health.readmit("incl0", t_ns)
            health.decisions.append({"t_ns": int(t_ns), "sensor": "incl0", "test": "frozen", "statistic": 0,
                                     "threshold": self.samples, "decision": "recovered", "held_out_s": held_s})
            log.info("incl0 moves again after %.0f s stuck", held_s)


class BiasDrift:
    """The accelerometer-bias drift test (``GatingOptions.bias_drift_z``) of the inclinometer.

    A slow inclinometer ramp can be followed by the state without residuals: the smoother tilts and lets the
    accelerometer bias absorb g x tilt.  Each keyframe's bias increment normalised by the random walk,
    ``s = (b_k - b_k-1) / (sigma_rw sqrt(dt))``, is N(0, 1) per axis without drift; over the last ``n``,
    ``z = max |sum s| / sqrt(n)`` on the horizontal body axes (x, y).
    """

    def __init__(self, gating: GatingOptions, accel_random_walk: float, health: SensorHealth):
        self.gating, self.health = gating, health
        self._increments: deque = deque(maxlen=gating.bias_drift_window)
        self._sum = np.zeros(2)  # running sum of the increments in the window
        self._previous = None
        self._random_walk = accel_random_walk

    def check(self, accel_bias: np.ndarray, t_ns: int, k: int, dt_s: float, since_start_s: float) -> None:
        """The keyframe's accelerometer bias (m/s^2, body); on an alarm the inclinometer is held out and its recent
        factors are removed at the next update."""
        g, health = self.gating, self.health
        if not g.eigen or dt_s <= 0:
            return
        if health.faulty["incl0"] or health.in_grace("incl0", t_ns):
            # held out or pulling the state back: the bias moves legitimately, start again
            self._increments.clear()
            self._previous = None
            return
        z = self._window_z(accel_bias, dt_s)
        settling = since_start_s < g.bias_drift_settle_s or t_ns < health.resettled_ns
        if z is None or settling or z <= g.bias_drift_z or health.any_fault():
            return
        health.declare_fault("incl0", t_ns, k, {"test": "bias_drift", "statistic": z, "threshold": g.bias_drift_z})
        self._increments.clear()
        log.info("incl0 soft fault from the accelerometer bias drift (z %.1f > %.1f)", z, g.bias_drift_z)

    def _window_z(self, accel_bias: np.ndarray, dt_s: float) -> float | None:
        """Add the bias increment since the previous keyframe; z once the window is full."""
        previous, self._previous = self._previous, accel_bias
        if previous is None:
            return None
        increments = self._increments
        if len(increments) == increments.maxlen:
            self._sum = self._sum - increments[0]
        step = (accel_bias[:2] - previous[:2]) / (self._random_walk * math.sqrt(dt_s))
        increments.append(step)
        self._sum = step if len(increments) == 1 else self._sum + step
        if len(increments) < increments.maxlen:
            return None
        return max(abs(x) for x in self._sum.tolist()) / math.sqrt(increments.maxlen)
