"""The batch smoother: every keyframe with the factors the online pass accepted, solved at once."""
from __future__ import annotations

import logging
import time

import gtsam
import numpy as np

from selfcal.core.solve import DegenerateDataError, optimize
from selfcal.graphs.tracker.estimator import TrackerEstimator, pose_covariance_W

log = logging.getLogger(__name__)

X = gtsam.symbol_shorthand.X


def gauss_newton(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int = 5,
                 tol: float = 1e-7) -> gtsam.Values:
    """Gauss-Newton from a close start (the online pass's estimates), Levenberg-Marquardt if a step fails.

    From there the problem is nearly linear: 2-3 steps converge (largest tangent step below ``tol``).  GTSAM's
    LM re-evaluates the Python factors for every damping trial, ~5x slower here.
    """
    error = graph.error(values)
    for _ in range(max_iterations):
        delta = graph.linearize(values).optimize()
        new = values.retract(delta)
        new_error = graph.error(new)
        if new_error > error * (1 + 1e-9):
            log.info("Gauss-Newton step raised the error (%.6g -> %.6g): Levenberg-Marquardt", error, new_error)
            return optimize(graph, values, max_iterations=30)
        values, error = new, new_error
        if np.max(np.abs(delta.vector())) < tol:
            break
    return values


def batch_smooth(estimator: TrackerEstimator, covariance: bool = False):
    """Gauss-Newton (LM fallback) over every keyframe with the factors the online pass accepted (not removed).

    Returns (t_ns (K,), poses list[Pose3], covariances list or None).
    """
    if estimator.graph_log is None:
        raise ValueError("the estimator must run with TrackerOptions(keep_graph=True)")
    graph = gtsam.NonlinearFactorGraph()
    for factor, _, _, removed, _ in estimator.graph_log:
        if not removed:
            graph.add(factor)
    if graph.size() == 0:
        raise DegenerateDataError("no keyframe: the recording never had tracker, inclinometer and camera samples")
    t0 = time.perf_counter()
    result = gauss_newton(graph, estimator.initial_values)
    log.info("batch smoother over %d keyframes: %.1f s", len(estimator.keyframe_t_ns), time.perf_counter() - t0)
    poses = [result.atPose3(X(k)) for k in range(len(estimator.keyframe_t_ns))]
    covs = None
    if covariance:
        marginals = gtsam.Marginals(graph, result)
        covs = [pose_covariance_W(pose.rotation().matrix(), marginals.marginalCovariance(X(k)))
                for k, pose in enumerate(poses)]
    return np.array(estimator.keyframe_t_ns, dtype=np.int64), poses, covs
