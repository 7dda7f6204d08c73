"""Solver plumbing shared by every graph: noise models, Levenberg–Marquardt, marginals, data-quality errors."""
from __future__ import annotations

import logging

import gtsam
import numpy as np

log = logging.getLogger(__name__)


class DegenerateDataError(ValueError):
    """The data cannot determine a requested quantity; the message says what motion or data to add."""


def gaussian(sigmas) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=float))


def robust(sigmas, huber_k: float | None):
    """Diagonal Gaussian, wrapped in a Huber kernel when ``huber_k`` (in sigmas) is given.

    Huber with k = 3 keeps ~99 % efficiency on Gaussian noise and bounds the pull of a bad static pose.
    """
    base = gaussian(sigmas)
    if huber_k is None:
        return base
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k), base)


def optimize(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, max_iterations: int = 100) -> gtsam.Values:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    log.debug("LM: error %.6g -> %.6g", graph.error(initial), graph.error(result))
    return result


def marginal_covariances(graph, values, keys, what: str) -> dict[int, np.ndarray]:
    """Marginal covariance of each key; a singular system becomes a DegenerateDataError naming ``what``."""
    try:
        marginals = gtsam.Marginals(graph, values)
        return {k: marginals.marginalCovariance(k) for k in keys}
    except RuntimeError as err:
        raise DegenerateDataError(f"the data do not determine {what} (singular information matrix: {err})") \
            from None
