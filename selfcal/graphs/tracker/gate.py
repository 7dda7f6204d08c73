"""The chi-square gate (hard faults: spikes, outliers, tracker jumps) and the decision on each measurement.

Before a factor enters, its whitened residual ``b`` and Jacobian ``A`` at the propagated state give the predicted
residual covariance ``S = I + A P A^T`` (``P``: marginal covariance of the previous keyframe grown by the
preintegration noise); ``b^T S^-1 b`` is tested against ``chi2(dim).ppf(1 - gate_alpha)``; a failing factor never
enters.  The normalised residual ``nu = L^-1 b`` (``S = L L^T``) goes on to the soft-fault detector
(:mod:`selfcal.graphs.tracker.eigen`).
"""
from __future__ import annotations

import logging
import math

import numpy as np

from selfcal.core import so3
from selfcal.core.stats import chi2_upper_quantile  # scipy.special would cost ~0.4 s of start-up
from selfcal.graphs.tracker.checks import FrozenOutput, SensorHealth, readmission
from selfcal.graphs.tracker.eigen import EigenDetector
from selfcal.graphs.tracker.options import GatingOptions
from selfcal.models import tracker as mt

log = logging.getLogger(__name__)


def inverse_cholesky(S: np.ndarray) -> np.ndarray:
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


def whiten(S: np.ndarray, r: np.ndarray) -> np.ndarray:
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


def predicted_covariance(P_pose: np.ndarray, P_vel: np.ndarray, pim, P_bias: np.ndarray,
                         R_W_B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Covariance of the keyframe predicted from the previous one: (pose 6x6 [rotation, position], velocity 3x3),
    from the previous keyframe's marginals of pose, velocity and bias (6x6 [accelerometer, gyro]) and its attitude."""
    Q = pim.preintMeasCov()  # preintegration noise only: [rotation, position, velocity, biases]
    dt = pim.deltaTij()
    # P_pose,k = P_pose + Q_pose;  the position also carries the velocity's uncertainty over dt: + dt^2 P_v
    P_pose_k = P_pose + Q[:6, :6]
    P_pose_k[3:, 3:] += dt**2 * P_vel
    # and the bias's own uncertainty: a gyro bias error b_g turns the attitude by dt b_g, an accelerometer one moves
    # the velocity by dt R b_a and the position by dt^2/2 b_a (body axes).  Without it the first keyframes, whose
    # bias is still the prior's (0.05 m/s^2: 5e-3 m/s in 0.1 s, five times the 5-sample mean velocity's noise),
    # rejected a clean prism velocity in half of the runs
    P_a, P_g = P_bias[:3, :3], P_bias[3:, 3:]
    P_pose_k[:3, :3] += dt**2 * P_g
    P_pose_k[3:, 3:] += (0.5 * dt**2) ** 2 * P_a
    return P_pose_k, P_vel + Q[6:9, 6:9] + dt**2 * R_W_B @ P_a @ R_W_B.T  # P_v,k = P_v + Q_v + dt^2 R P_a R^T


def innovation(factor, values, P_pose: np.ndarray) -> tuple[float, np.ndarray]:
    """(statistic, normalised residual) of a pose factor at the propagated state with pose covariance P."""
    return linear_innovation(factor.linearize(values), P_pose)


def linear_innovation(linear, P_pose: np.ndarray) -> tuple[float, np.ndarray]:
    """:func:`innovation` of a factor already linearised at the propagated state (a ``JacobianFactor``)."""
    A, b = linear.jacobian()
    S = A @ P_pose @ A.T
    S.flat[::len(b) + 1] += 1.0  # S = A P A^T + I  (the factor is whitened: its noise is I)
    nu = whiten(S, -b)  # nu = L^-1 r,  r = -b  (normalised residual)
    return float(nu @ nu), nu  # nu^T nu = r^T S^-1 r ~ chi2(dim)


def prism_position_innovations(Z: np.ndarray, prism_k_W: np.ndarray, R_W_B_k: np.ndarray, r_P_B: np.ndarray,
                               P_pose: np.ndarray, sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(statistics (n,), normalised residuals (n, 3)) of the tracker's prism positions moved to the keyframe,
    against the predicted prism ``prism_k_W = p + R r``."""
    H = np.hstack([R_W_B_k @ -so3.hat(r_P_B), R_W_B_k])  # d(p + R r)/d[w, t] = [-R [r]x, R]
    S = H @ P_pose @ H.T
    S.flat[::4] += sigma_m**2  # S = H P H^T + sigma^2 I
    # L^-1 of a 3x3 once, then one small product: scipy's solve_triangular (LAPACK trtrs) costs ~7 ms a call
    # on a loaded machine with OpenBLAS threads, more than the whole keyframe update
    nu = (Z - prism_k_W) @ inverse_cholesky(S).T
    return np.einsum("ij,ij->i", nu, nu), nu


def prism_velocity_innovation(v_mean_W: np.ndarray, w_B: np.ndarray, R_W_B_k: np.ndarray, v_k_W: np.ndarray,
                              r_P_B: np.ndarray, P_pose: np.ndarray, P_vel: np.ndarray, sigma_m_s: float,
                              n_samples: int) -> tuple[float, np.ndarray]:
    """(statistic, normalised residual) of the mean of ``n_samples`` prism velocities against the predicted
    ``v + R (w x r)``."""
    # H = [-R [w x r]x (rotation), 0 (position), I (velocity)]: S = H_rot P_rot H_rot^T + P_v + noise;
    # the mean of n samples: state uncertainty unchanged, measurement noise / n
    H_rot = -R_W_B_k @ so3.hat(mt.cross(w_B, r_P_B))
    S = H_rot @ P_pose[:3, :3] @ H_rot.T + P_vel
    S.flat[::4] += sigma_m_s**2 / n_samples
    nu = whiten(S, v_mean_W - mt.prism_velocity_W(R_W_B_k, v_k_W, w_B, r_P_B))
    return float(nu @ nu), nu


class Gate:
    """The decision on one measurement, logged with its statistic: held out (its sensor is faulty), accepted in
    grace (after a forced readmission), rejected by the chi-square gate, or accepted.  The soft-fault detector
    of a monitored sensor is fed on the way."""

    def __init__(self, gating: GatingOptions, health: SensorHealth, frozen: FrozenOutput):
        self.gating, self.health, self.frozen = gating, health, frozen
        self.threshold = {d: chi2_upper_quantile(d, gating.gate_alpha) for d in (2, 3)}
        self.consecutive_rejects: dict[str, int] = {}
        self.counts = {"accepted": 0, "rejected": 0, "held_out": 0}
        self._quiet_reported: dict[str, bool] = {}  # sensors said once to be quieter than their noise model

    def decide(self, tag: str, t_ns: int, stat: float, nu: np.ndarray, k: int, inflated: bool = False,
               excused: bool = False, monitor: tuple | None = None) -> bool:
        """True = add the factor (keyframe ``k``).  A soft-fault alarm holds the sensor out at once.

        ``inflated``: the factor's noise was grown by measured vibration; ``excused``: the accelerometer shows
        vibration starting, so a reject is no evidence of a fault; ``monitor`` = (statistic, normalised residual,
        inflated) for the soft-fault detector when it differs from the factor's (see
        ``GatingOptions.onset_window``)."""
        sensor = tag.split("/")[0]
        threshold = self.threshold[len(nu)]
        decision = {"t_ns": int(t_ns), "sensor": tag, "test": "chi2", "statistic": stat, "dof": len(nu),
                    "threshold": threshold}
        self.health.decisions.append(decision)
        m_stat, m_nu, m_inflated = monitor if monitor is not None else (stat, nu, inflated)
        detector = self.health.detectors.get(tag)
        # a stuck inclinometer is readmitted by the stuck-output test alone, from its first moving sample on
        stuck = sensor == "incl0" and self.frozen.holds_out(t_ns)
        if self.health.faulty[sensor] or stuck:
            decision["decision"] = "held_out"
            self.counts["held_out"] += 1
            if detector is not None and not stuck:  # monitored while held out: readmitted when a window looks healthy
                self._recovery_test(tag, detector, detector.push(m_nu, m_inflated), t_ns)
            return False
        if self.health.in_grace(sensor, t_ns):
            # readmitted after a long hold-out: it has to pull the state back (tilt and accelerometer bias
            # together, against the bias's random walk: seconds), so it is not gated and cannot be accused until a
            # window of its residuals looks healthy again (or max_grace_s has passed)
            decision["decision"] = "accept_grace"
            self.counts["accepted"] += 1
            if detector is not None:
                lam_max = detector.push(m_nu, m_inflated)
                if lam_max is not None and detector.healthy(lam_max):
                    del self.health.grace_until_ns[sensor]
            return True
        monitored = self.gating.eigen and detector is not None
        if self.gating.chi2 and stat > threshold:
            self.consecutive_rejects[tag] = self.consecutive_rejects.get(tag, 0) + 1
            if monitored:
                decision["decision"] = "reject"
                self.counts["rejected"] += 1
                if excused:
                    decision["vibration"] = True
                    return False
                if monitor is not None and m_stat <= threshold:
                    decision["vibration"] = True  # the samples after it show a burst starting
                # nu sqrt(min(1, threshold / stat)): a rejected sample still goes to the soft-fault detector,
                # shrunk onto the gate's boundary (winsorised: a lone spike adds at most the threshold to the
                # window, while a run of rejects -- a ramp or an offset the gate keeps catching -- fills the window
                # and raises the alarm within seconds); hiding rejects from it would leave a soft fault to the gate
                self._soft_fault_test(tag, detector, m_nu * np.sqrt(min(1.0, threshold / m_stat)), t_ns, k,
                                      m_inflated)
                return False
            if self.consecutive_rejects[tag] <= self.gating.max_consecutive_rejects:
                decision["decision"] = "reject"
                self.counts["rejected"] += 1
                return False
            # an unmonitored sensor (tracker, camera: sole sources of position and azimuth) rejected for so long
            # is more likely right than the state: the state has drifted away and only this sensor can bring it
            # back
            decision["decision"] = "accept_after_rejects"
        else:
            decision["decision"] = "accept"
        self.consecutive_rejects[tag] = 0
        self.counts["accepted"] += 1
        if monitored:
            self._soft_fault_test(tag, detector, m_nu, t_ns, k, m_inflated)
        return True

    def _soft_fault_test(self, tag: str, detector: EigenDetector, nu: np.ndarray, t_ns: int, k: int,
                         inflated: bool) -> None:
        """Feed the soft-fault detector; a due test that fails holds the sensor out, unless one already is
        (single-fault assumption)."""
        lam_max = detector.push(nu, inflated)
        if lam_max is not None and detector.quieter_than_model() and not self._quiet_reported.get(tag):
            # said once: the data, not the sensor, disagree with the model (its stuck-output side stays off)
            self._quiet_reported[tag] = True
            spread = math.sqrt(detector.last_min / detector.n)
            self.health.decisions.append({"t_ns": int(t_ns), "sensor": tag, "test": "eigen", "statistic":
                                          detector.last_min, "threshold": detector.lower, "lambda_max": lam_max,
                                          "decision": "quieter_than_model"})
            log.warning("%s: residuals down to %.2g of the spread its sensor.yaml noise predicts, since the start "
                        "(lambda_min %.3g < %.3g): noise-free data or the stated sigma too large; not a fault, "
                        "but its stuck-output test is off until it shows that noise", tag, spread,
                        detector.last_min, detector.lower)
        if lam_max is None or detector.healthy(lam_max) or self.health.any_fault():
            return
        self.health.declare_fault(tag, t_ns, k, {"test": "eigen", "statistic": lam_max,
                                                 "threshold": detector.threshold, "lambda_min": detector.last_min,
                                                 "lower_threshold": detector.lower})
        log.info("%s soft fault (lambda_max %.1f vs %.1f, lambda_min %.2f vs %.2f)", tag, lam_max,
                 detector.threshold, detector.last_min, detector.lower)

    def _recovery_test(self, tag: str, detector: EigenDetector, lam_max: float | None, t_ns: int) -> None:
        """Readmit a held-out sensor whose monitored residuals pass the recovery test."""
        sensor = tag.split("/")[0]
        held_s = self.health.held_s(sensor, t_ns)
        outcome = readmission(detector, lam_max, held_s, self.gating.max_holdout_s)
        if outcome is None:
            return
        self.health.readmit(sensor, t_ns)
        if outcome == "readmitted_after_holdout":
            # the state is off: the sensor's samples enter ungated until it has come back
            self.health.grace_until_ns[sensor] = int(t_ns + 1e9 * self.gating.max_grace_s)
        self.health.decisions.append({"t_ns": int(t_ns), "sensor": tag, "test": "eigen", "statistic": lam_max,
                                      "threshold": detector.threshold, "lambda_min": detector.last_min,
                                      "lower_threshold": detector.lower, "decision": outcome, "held_out_s": held_s})
        log.info("%s %s after %.0f s (lambda_max %.1f vs %.1f)", tag, outcome, held_s, lam_max, detector.threshold)
