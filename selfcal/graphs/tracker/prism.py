"""The laser tracker's samples of one keyframe: moved to the keyframe, gated one by one, averaged into one prism
position factor (and one velocity factor) with sigma / sqrt(accepted samples)."""
from __future__ import annotations

import gtsam
import numpy as np

from selfcal.factors import tracker as ft
from selfcal.graphs.tracker.alignment import Pending, prism_positions_at_keyframe, prism_velocities_at_keyframe
from selfcal.graphs.tracker.bookkeeping import FactorBook
from selfcal.graphs.tracker.gate import Gate, prism_position_innovations, prism_velocity_innovation
from selfcal.graphs.tracker.options import SensorNoise

X, V = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V


class PrismFactors:
    """The tracker's position and velocity factors of one keyframe, gated by :class:`Gate`."""

    def __init__(self, noise: SensorNoise, gate: Gate, book: FactorBook):
        self.noise, self.gate, self.book = noise, gate, book

    def factors(self, pending: list[Pending], k: int, nav_k: gtsam.NavState, P_pose: np.ndarray,
                P_vel: np.ndarray, v_start_W: np.ndarray, dt_s: float) -> list:
        """[(factor, tag)] of the tracker samples since the previous keyframe (at ``v_start_W``, ``dt_s`` ago)."""
        n = self.noise
        R_k, r = nav_k.attitude().matrix(), n.r_P_B
        prism_k_W = nav_k.position() + R_k @ r
        Z = prism_positions_at_keyframe(pending, prism_k_W, r)
        stat, nu = prism_position_innovations(Z, prism_k_W, R_k, r, P_pose, n.tracker_sigma_m)
        keep = np.array([self.gate.decide("tracker0", m.t_ns, float(s), v, k) for m, s, v in zip(pending, stat, nu)])
        out = []
        if keep.any():
            noise = gtsam.noiseModel.Isotropic.Sigma(3, n.tracker_sigma_m / np.sqrt(keep.sum()))
            factor = ft.prism_position_factor(noise, X(k), Z[keep].sum(axis=0) / keep.sum(), r)
            if self.book.graph_log is not None:  # the audit's record (batch runs only)
                kept = [m for m, kk in zip(pending, keep) if kk]
                velocities = (np.array([m.velocity_W for m in kept]) if all(m.velocity_W is not None for m in kept)
                              else None)
                self.book.remember(factor, Z=Z[keep], sigma=n.tracker_sigma_m, t_ns=[m.t_ns for m in kept],
                                   v_start=v_start_W,  # the filtered velocity the samples were moved with
                                   V=velocities)
            out.append((factor, "tracker0"))
        with_velocity = [m for m, kk in zip(pending, keep) if kk and m.velocity_W is not None]
        if with_velocity:
            out.extend(self._velocity_factor(with_velocity, k, nav_k, P_pose, P_vel, v_start_W, dt_s))
        return out

    def _velocity_factor(self, samples: list[Pending], k: int, nav_k: gtsam.NavState, P_pose: np.ndarray,
                         P_vel: np.ndarray, v_start_W: np.ndarray, dt_s: float) -> list:
        """The mean of the accepted tracker velocities moved to keyframe k, gated: [(factor, tag)] or []."""
        n, count = self.noise, len(samples)
        R_k, v_k, r = nav_k.attitude().matrix(), nav_k.velocity(), n.r_P_B
        w_B = np.array([m.w_B for m in samples]).sum(axis=0) / count
        v_mean = prism_velocities_at_keyframe(samples, nav_k, w_B, r).sum(axis=0) / count
        stat, nu = prism_velocity_innovation(v_mean, w_B, R_k, v_k, r, P_pose, P_vel, n.tracker_velocity_sigma_m_s,
                                             count)
        if not self.gate.decide("tracker0/velocity", samples[-1].t_ns, stat, nu, k):
            return []
        sigma = n.tracker_velocity_sigma_m_s / np.sqrt(count)
        factor = ft.prism_velocity_factor(gtsam.noiseModel.Isotropic.Sigma(3, sigma), X(k), V(k), v_mean, w_B, r)
        if self.book.graph_log is not None:  # the audit's record (batch runs only)
            self.book.remember(factor, z=v_mean, w_B=w_B, sigma=sigma, a_W=(v_k - v_start_W) / max(dt_s, 1e-3))
        return [(factor, "tracker0/velocity")]
