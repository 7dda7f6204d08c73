"""Solver plumbing shared by every graph: noise models, Levenberg–Marquardt, marginals, data-quality errors."""
from __future__ import annotations

import logging
import math

import gtsam
import numpy as np

from selfcal.core.errors import SelfcalError
from selfcal.core.progress import quiet

log = logging.getLogger(__name__)


class DegenerateDataError(SelfcalError):
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
             relative_tolerance: float = 1e-10, linear_solver: str | None = None, progress=quiet) -> gtsam.Values:
    """Levenberg–Marquardt until the error's relative decrease falls below ``relative_tolerance``.

    ``linear_solver``: GTSAM's linear solver type (e.g. ``"MULTIFRONTAL_QR"`` for badly scaled systems where
    Cholesky meets an indeterminate pivot); default GTSAM's (multifrontal Cholesky).  ``progress(stage)`` is
    told each iteration's error as it ends (:mod:`selfcal.core.progress`).
    """
    params = gtsam.LevenbergMarquardtParams()
    if progress is not quiet:  # GTSAM calls the hook after every iteration
        progress("least squares")
        params.iterationHook = lambda i, before, after: progress(
            f"least squares (iteration {i} done, error {before:.4g} -> {after:.4g})")
    if linear_solver is not None:
        params.setLinearSolverType(linear_solver)
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_tolerance)
    params.setAbsoluteErrorTol(1e-12)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    result = optimizer.optimize()
    log.debug("LM: %d iterations", optimizer.iterations())
    log.debug("LM: error %.6g -> %.6g", graph.error(initial), graph.error(result))
    return result


def marginal_covariances(graph, values, keys, what: str) -> dict[int, np.ndarray]:
    """Marginal covariance of each key; a singular system becomes a DegenerateDataError naming ``what``.

    GTSAM's Cholesky also gives up on systems that are only badly scaled (a weakly observed variable next to
    thousands of tight factors, information ratios ~1e12): those are retried with :func:`dense_marginals`.
    """
    try:
        marginals = gtsam.Marginals(graph, values)
        return {k: marginals.marginalCovariance(k) for k in keys}
    except RuntimeError:
        return dense_marginals(graph, values, keys, what)


def joint_covariance(graph, values, keys, what: str) -> np.ndarray:
    """Joint marginal covariance of several keys (in the given order, each key's tangent block in turn)."""
    keys = list(keys)
    try:
        return np.array(gtsam.Marginals(graph, values).jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix())
    except RuntimeError:
        A, _, offsets = dense_jacobian(graph, values)
        scale = np.maximum(np.linalg.norm(A, axis=0), 1e-300)
        eigenvalues, vectors = np.linalg.eigh((A / scale).T @ (A / scale))
        if eigenvalues.min() <= 1e-13 * eigenvalues.max():
            raise DegenerateDataError(f"the data do not determine {what} (singular information matrix)") from None
        covariance = (vectors / eigenvalues) @ vectors.T / np.outer(scale, scale)
        tangent = values.zeroVectors()
        idx = np.concatenate([np.arange(offsets[k], offsets[k] + tangent.at(k).size) for k in keys])
        return covariance[np.ix_(idx, idx)]


def dense_jacobian(graph, values) -> tuple[np.ndarray, np.ndarray, dict[int, int]]:
    """Whitened Jacobian ``A``, right-hand side ``b`` and each key's first column, linearised at ``values``."""
    ordering = gtsam.Ordering()
    offsets, column = {}, 0
    tangent = values.zeroVectors()
    for k in values.keys():
        ordering.push_back(k)
        offsets[k] = column
        column += tangent.at(k).size
    A, b = graph.linearize(values).jacobian(ordering)
    # own, contiguous copies: LAPACK on GTSAM's view is ~100x slower
    return np.array(A, order="C"), np.array(b).ravel(), offsets


def normal_equations(graph, values) -> tuple[np.ndarray, np.ndarray, float, int, dict[int, int]]:
    """``A^T A``, ``A^T b``, ``b^T b`` and the row count of the whitened linearised system, columns as
    :func:`dense_jacobian`'s (``values``' keys in order, each key's first column in the dict).

    Built from GTSAM's sparse Jacobian, so the cost follows the non-zeros, not rows x columns: the form for
    graphs whose dense Jacobian does not fit in memory (tens of thousands of rows, thousands of columns).
    """
    offsets, column = {}, 0
    tangent = values.zeroVectors()
    for k in values.keys():
        offsets[k] = column
        column += tangent.at(k).size
    linear = graph.linearize(values)
    # GTSAM numbers the sparse Jacobian's columns by the graph's keys in ascending order, 1-based, b last
    to_column = np.concatenate([offsets[k] + np.arange(tangent.at(k).size) for k in sorted(linear.keys())]
                               + [np.array([column])])
    from scipy import sparse  # here: its import costs ~0.4 s of every graph's start-up, online ones included
    i, j, entries = linear.sparseJacobian_()
    rows = sum(graph.at(f).dim() for f in range(graph.size()))
    Ab = sparse.csc_matrix((entries, (i.astype(np.int64) - 1, to_column[j.astype(np.int64) - 1])),
                           shape=(rows, column + 1))
    N = (Ab.T @ Ab).toarray()
    return N[:-1, :-1], N[:-1, -1], float(N[-1, -1]), int(rows), offsets


def dense_marginals(graph, values, keys, what: str) -> dict[int, np.ndarray]:
    """Marginal covariances from the dense, column-equilibrated information matrix (eigen-decomposition):
    units and weak priors do not make it singular, only a direction the data and priors leave free does."""
    covariance, offsets = _dense_covariance(graph, values, what)
    tangent = values.zeroVectors()
    return {k: covariance[offsets[k]:offsets[k] + tangent.at(k).size, offsets[k]:offsets[k] + tangent.at(k).size]
            for k in keys}


def dense_joint_covariance(graph, values, keys, what: str) -> np.ndarray:
    """The joint covariance of ``keys`` (in that order, blocks stacked) as :func:`dense_marginals` computes it."""
    covariance, offsets = _dense_covariance(graph, values, what)
    tangent = values.zeroVectors()
    index = np.concatenate([np.arange(offsets[k], offsets[k] + tangent.at(k).size) for k in keys])
    return covariance[np.ix_(index, index)]


def _dense_covariance(graph, values, what: str) -> tuple[np.ndarray, dict[int, int]]:
    A, _, offsets = dense_jacobian(graph, values)
    scale = np.maximum(np.linalg.norm(A, axis=0), 1e-300)
    eigenvalues, vectors = np.linalg.eigh((A / scale).T @ (A / scale))
    if eigenvalues.min() <= 1e-13 * eigenvalues.max():
        raise DegenerateDataError(f"the data do not determine {what} (singular information matrix)")
    return (vectors / eigenvalues) @ vectors.T / np.outer(scale, scale), offsets


def lag_stamp_s(t_s: float, step_s: float) -> float:
    """The timestamp under which a fixed-lag smoother keeps a variable of time ``t_s``: ``t_s`` rounded up to a
    multiple of ``step_s`` (0: ``t_s`` itself).

    ``gtsam.IncrementalFixedLagSmoother`` marginalises what falls behind the lag at every update, and each
    marginalisation re-eliminates the whole window (its ordering constraint puts the old variables at the
    leaves), which also clears the cached marginals a covariance of the newest state needs: the cost of an
    update and of its covariance grows with the window.  Stamped on a grid, variables leave in blocks once per
    ``step_s``; between, an update re-eliminates only the top of the tree (the newest variables, ordered last).
    The window then holds between ``lag`` and ``lag + step_s`` of history: never less than asked.
    """
    if step_s <= 0:
        return t_s
    return math.ceil(t_s / step_s - 1e-9) * step_s
