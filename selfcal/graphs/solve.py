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


def optimize(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, max_iterations: int = 100,
             relative_tolerance: float = 1e-10) -> gtsam.Values:
    """Levenberg–Marquardt until the error's relative decrease falls below ``relative_tolerance``."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_tolerance)
    params.setAbsoluteErrorTol(1e-12)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    result = optimizer.optimize()
    log.debug("LM: %d iterations", optimizer.iterations())
    log.debug("LM: error %.6g -> %.6g", graph.error(initial), graph.error(result))
    return result


def marginal_covariances(graph, values, keys, what: str) -> dict[int, np.ndarray]:
    """Marginal covariance of each key; a singular system becomes a DegenerateDataError naming ``what``."""
    try:
        marginals = gtsam.Marginals(graph, values)
        return {k: marginals.marginalCovariance(k) for k in keys}
    except RuntimeError as err:
        reason = " ".join(str(err).split()[:8])
    # GTSAM's Cholesky gives up on systems that are only badly scaled (a weak prior next to thousands of tight
    # factors); the dense information matrix, inverted by eigen-decomposition, tells those from singular ones
    ordering = gtsam.Ordering()
    offsets, column = {}, 0
    for k in values.keys():
        ordering.push_back(k)
        offsets[k] = column
        column += values.zeroVectors().at(k).size
    A, _ = graph.linearize(values).jacobian(ordering)
    information = np.array(A.T @ A)
    scale = 1.0 / np.sqrt(np.maximum(np.diag(information), 1e-300))  # Jacobi scaling: units do not make it singular
    eigenvalues, vectors = np.linalg.eigh(information * np.outer(scale, scale))
    if eigenvalues[0] <= 1e-12 * eigenvalues[-1]:
        raise DegenerateDataError(f"the data do not determine {what} (singular information matrix: {reason})")
    covariance = np.outer(scale, scale) * ((vectors / eigenvalues) @ vectors.T)
    out = {}
    for k in keys:
        idx = offsets[k] + np.arange(values.zeroVectors().at(k).size)
        out[k] = covariance[np.ix_(idx, idx)]
    return out
