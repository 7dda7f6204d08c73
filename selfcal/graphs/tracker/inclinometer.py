"""The inclinometer's samples: each enters at once, provisionally, and is decided when the vibration around it is
known (the accelerometer window centred on it, its own samples after it)."""
from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from selfcal.graphs.tracker.alignment import Pending, up_at_keyframe
from selfcal.graphs.tracker.bookkeeping import FactorBook
from selfcal.graphs.tracker.checks import FrozenOutput, SensorHealth
from selfcal.graphs.tracker.eigen import StateRecursor
from selfcal.graphs.tracker.gate import Gate, innovation
from selfcal.graphs.tracker.options import GatingOptions
from selfcal.graphs.tracker.vibration import InclinometerVibration, noise_covariance

log = logging.getLogger(__name__)

X = gtsam.symbol_shorthand.X


@dataclass
class DeferredSample:
    """An inclinometer sample waiting for the vibration measured around it, with the prediction at its arrival."""

    t_ns: int
    k: int  # the keyframe its factor sits on
    up_B: np.ndarray  # its reading moved to that keyframe
    values: gtsam.Values  # the propagated state at that keyframe
    P_pose: np.ndarray  # and its covariance
    index: int | None = None  # its provisional factor's smoother index (-1: known after this keyframe's update)
    accel_cov: np.ndarray | None = None  # the vibration covariance its provisional factor entered with


class DeferredInclinometer:
    """The inclinometer's samples from arrival (provisional factor) to decision (kept, re-weighted or removed)."""

    def __init__(self, gating: GatingOptions, vibration: InclinometerVibration, gate: Gate, health: SensorHealth,
                 frozen: FrozenOutput, recursor: StateRecursor, book: FactorBook):
        self.gating, self.vibration, self.gate, self.health = gating, vibration, gate, health
        self.frozen, self.recursor, self.book = frozen, recursor, book
        self._waiting: list[DeferredSample] = []

    def arrive(self, m: Pending, k: int, nav_k: gtsam.NavState, values: gtsam.Values, P_pose: np.ndarray,
               t_ns: int) -> list:
        """A sample enters at once, provisionally, with the vibration of the last window (causal), when it passes
        the chi-square gate: the online pose then has it without delay.  Its decision proper waits for the
        centred window (:meth:`decide_ready`), which keeps it, re-weights it or removes it.  [(factor, tag)]."""
        g, vibration = self.gating, self.vibration
        up_B = up_at_keyframe(m.nav.attitude().matrix(), nav_k.attitude().matrix(), m.z)
        vibration.note_sample(m.t_ns)
        self.frozen.check(m.t_ns, m.z, k)
        entry = DeferredSample(m.t_ns, k, up_B, values, P_pose)
        self._waiting.append(entry)
        nominal = vibration.factor(k, up_B, None)
        vibration.add_residual(m.t_ns, np.asarray(nominal.unwhitenedError(values)))
        if self.health.faulty["incl0"] or not g.vibration_inflation:
            return []
        R_W_B = values.atPose3(X(k)).rotation().matrix()
        cov, _ = vibration.accelerometer(R_W_B, t_ns - int(0.5e9 * g.vibration_window_s))
        factor = nominal if cov is None else vibration.factor(k, up_B, cov)
        stat, _ = innovation(factor, values, P_pose)
        if g.chi2 and stat > self.gate.threshold[2]:
            return []
        entry.index, entry.accel_cov = -1, cov
        if self.book.graph_log is not None:  # the audit's record (batch runs only)
            self.book.remember(factor, t_ns=m.t_ns, up_B=up_B, cov=vibration.covariance(cov),
                               accel_cov=vibration.accelerometer(R_W_B, t_ns - int(0.5e9 * g.vibration_window_s),
                                                                 turned=True)[0],
                               f_B=vibration.mean_specific_force(m.t_ns))
        return [(factor, "incl0/provisional")]

    def decide_ready(self, t_ns: int, k: int) -> list:
        """Decide the samples whose centred vibration window is complete (see
        :meth:`InclinometerVibration.deferral_s`): [(factor, tag)] to add at keyframe ``k``."""
        wait_ns = 1e9 * self.vibration.deferral_s()
        ready = [d for d in self._waiting if d.t_ns + wait_ns <= t_ns]
        self._waiting = [d for d in self._waiting if d.t_ns + wait_ns > t_ns]
        accepted = []
        for d in ready:
            factor = self._decide(d, k)
            if factor is not None:
                accepted.append((factor, "incl0"))
        return accepted

    def added(self, indices, tags: list) -> None:
        """The smoother indices of this keyframe's provisional factors (None for those not added after all: their
        sensor was found faulty in this keyframe)."""
        provisional = [d for d in self._waiting if d.index == -1]
        waiting = iter(provisional)
        for idx, tag in zip(indices, tags):
            if tag == "incl0/provisional":
                next(waiting).index = int(idx)
        for d in provisional:
            if d.index == -1:
                d.index = None

    def _decide(self, d: DeferredSample, k: int):
        """One sample's decision: its factor stays on the keyframe it arrived at, its innovation is the one
        predicted at its arrival (before the sample, provisional or not, entered), with the noise of the centred
        window.  The factor to add, or None (rejected, or its provisional factor stands)."""
        g, vibration = self.gating, self.vibration
        R_W_B = d.values.atPose3(X(d.k)).rotation().matrix()
        cov, excused = vibration.accelerometer(R_W_B, d.t_ns)
        base = vibration.factor(d.k, d.up_B, cov)
        causal = vibration.own(d.t_ns)
        factor = vibration.grown(base, causal, cov, d.up_B)
        stat, nu = innovation(factor, d.values, d.P_pose)
        if g.eigen and g.recursor:
            self._recursor_test(factor, d.k, d.t_ns)
        nominal = cov is None and factor is base
        # the soft-fault detector's residual: normalised with the vibration the samples after it show too, when
        # the accelerometer after it (up to 0.5 s, as far as it has arrived) corroborates (energy above its
        # white noise at the loose hint level): a fault's own transients (the state lurching after a ramp) must
        # not excuse it
        monitor = None
        onset = vibration.own(d.t_ns, ahead=True) if g.eigen or self.book.graph_log is not None else 0.0
        later = d.t_ns + int(0.5e9 * g.vibration_window_s)
        if g.eigen and onset > causal and vibration.accelerometer(R_W_B, later)[1]:
            grown = vibration.grown(base, onset, cov, d.up_B)
            if grown is not factor:
                monitor = innovation(grown, d.values, d.P_pose) + (True,)
        # the audit's record: the vibration of a burst's onset, which the accelerometer after the sample shows
        # (significant, the target's rotation not counted) but sees too weakly around it
        if (self.book.graph_log is None or onset <= causal
                or vibration.accelerometer(R_W_B, later, turned=True)[0] is None):
            onset = 0.0
        keep = self.gate.decide("incl0", d.t_ns, stat, nu, k, inflated=not nominal, excused=excused, monitor=monitor)
        if d.index is not None:
            if keep and nominal and d.accel_cov is None:
                self.book.annotate(d.index, onset=onset)
                return None  # the provisional factor stands as it is
            self.book.remove_later(d.index)
        if not keep:
            return None
        if self.book.graph_log is not None:  # the audit's record (batch runs only)
            # cov: the factor's whole noise; accel_cov and own: the vibration alone (the accelerometer's with the
            # target's rotation not counted, the inclinometer's own), which the audit predicts the reading's
            # disturbance from
            self.book.remember(factor, t_ns=d.t_ns, up_B=d.up_B, cov=noise_covariance(factor),
                               accel_cov=vibration.accelerometer(R_W_B, d.t_ns, turned=True)[0], own=causal,
                               onset=onset, f_B=vibration.mean_specific_force(d.t_ns))
        return factor

    def _recursor_test(self, factor, k: int, t_ns: int) -> None:
        """The patent's state recursor (:class:`StateRecursor`) on one factor; its alarm holds the inclinometer
        out."""
        result = self.recursor.test(factor, k)
        if result is None:
            return
        lam_max, healthy = result
        detector = self.recursor.detector
        self.health.decisions.append({"t_ns": int(t_ns), "sensor": "incl0", "test": "eigen_recursor",
                                      "statistic": lam_max, "threshold": detector.threshold,
                                      "lambda_min": detector.last_min, "lower_threshold": detector.lower,
                                      "decision": "normal" if healthy else "fault"})
        if not healthy and not self.health.any_fault():
            self.health.hold_out("incl0", None)
            self.book.remove_recent("incl0", k)
            log.info("incl0 soft fault from the state recursor (lambda_max %.1f, lambda_min %.2f)", lam_max,
                     detector.last_min)
