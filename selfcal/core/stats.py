"""Statistics every system's estimator and audit share: eigenvalue quantiles of Wishart matrices (the
eigenvalue fault detector's thresholds) and the variance inflation of residuals correlated in time.

References
----------
M. S. Bartlett, "On the theory of statistical regression", Proc. R. Soc. Edinburgh 53 (1933) (the
decomposition used to draw Wishart matrices).
O. K. Smith, "Eigenvalues of a symmetric 3 x 3 matrix", Comm. ACM 4(4) (1961) 168.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

# The Monte Carlo quantiles of the online tracker's default detectors (graphs/tracker/eigen.py: the inclinometer's
# detector and the state recursor, window 30, 1 false alarm per hour), tabulated so that a run's start-up does not
# pay the 2e6 draws (~0.4 s of CPU).  (m, n, alpha, draws, seed) -> (upper alpha quantile of lambda_max, lower
# alpha quantile of lambda_min); any other key is drawn as before.  Written by :func:`wishart_quantiles_drawn`;
# tests/test_stats.py draws every entry again and compares.
WISHART_TABLE = {
    (2, 30, 6.9444444e-05, 2_000_000, 20240604): (75.08918378622722, 7.216217480338096),
    (2, 30, 0.000208333333, 2_000_000, 20240604): (71.35811998928303, 8.020732451857453),
}


def wishart_lambda_max_quantile(m: int, n: int, alpha: float, draws: int = 2_000_000, seed: int = 20240604) -> float:
    """Upper ``alpha`` quantile of the largest eigenvalue of ``W ~ Wishart_m(n, I)`` (see :func:`_wishart_extremes`)."""
    tabulated = WISHART_TABLE.get((m, n, alpha, draws, seed))
    return tabulated[0] if tabulated else wishart_quantiles_drawn(m, n, alpha, draws, seed)[0]


def wishart_lambda_min_quantile(m: int, n: int, alpha: float, draws: int = 2_000_000, seed: int = 20240604) -> float:
    """Lower ``alpha`` quantile of the smallest eigenvalue of ``W ~ Wishart_m(n, I)`` (m = 2 or 3)."""
    tabulated = WISHART_TABLE.get((m, n, alpha, draws, seed))
    return tabulated[1] if tabulated else wishart_quantiles_drawn(m, n, alpha, draws, seed)[1]


def wishart_quantiles_drawn(m: int, n: int, alpha: float, draws: int = 2_000_000,
                            seed: int = 20240604) -> tuple[float, float]:
    """(upper ``alpha`` quantile of lambda_max, lower ``alpha`` quantile of lambda_min) by Monte Carlo, never from
    :data:`WISHART_TABLE`."""
    lam_max, lam_min = _wishart_extremes(m, n, draws, seed)
    return float(np.quantile(lam_max, 1.0 - alpha)), float(np.quantile(lam_min, alpha))


def chi2_survival(dof: int, x: float) -> float:
    """``P(chi2(dof) > x)`` for an integer ``dof``, in closed form (math only: scipy.special costs ~0.4 s of
    start-up).  Even dof: ``exp(-h) sum_{i < dof/2} h^i / i!``; odd: ``erfc(sqrt(h)) + exp(-h) sum_{i < (dof-1)/2}
    h^(i+1/2) / Gamma(i + 3/2)``, ``h = x / 2`` (terms in logs: no overflow at large dof)."""
    if x <= 0.0:
        return 1.0
    h = 0.5 * x
    log_h = math.log(h)
    if dof % 2 == 0:
        return math.fsum(math.exp(i * log_h - h - math.lgamma(i + 1)) for i in range(dof // 2))
    return math.erfc(math.sqrt(h)) + math.fsum(math.exp((i + 0.5) * log_h - h - math.lgamma(i + 1.5))
                                               for i in range((dof - 1) // 2))


@lru_cache(maxsize=64)
def chi2_upper_quantile(dof: int, alpha: float) -> float:
    """``x`` with ``P(chi2(dof) > x) = alpha`` (scipy's ``chdtri(dof, alpha)``), integer ``dof`` >= 1: bisection on
    :func:`chi2_survival` (decreasing in x) down to adjacent floats."""
    if not (isinstance(dof, int) or float(dof).is_integer()) or dof < 1 or not 0.0 < alpha < 1.0:
        raise ValueError(f"chi2 quantile needs an integer dof >= 1 and 0 < alpha < 1 (got {dof}, {alpha})")
    dof = int(dof)
    lo, hi = 0.0, float(dof) + 10.0
    while chi2_survival(dof, hi) > alpha:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if chi2_survival(dof, mid) > alpha:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@lru_cache(maxsize=16)
def _wishart_extremes(m: int, n: int, draws: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Upper ``alpha`` quantile of the largest eigenvalue of ``W ~ Wishart_m(n, I)`` (Monte Carlo, seeded).

    Bartlett decomposition ``W = T T^T``, ``T`` lower triangular, ``T_ii^2 ~ chi2(n - i)``, ``T_ij ~ N(0, 1)``
    below the diagonal: m(m+1)/2 numbers per draw.  With 2e6 draws the quantile at alpha = 2.8e-4 rests on
    ~560 exceedances (relative error of its tail probability ~4 %).
    """
    rng = np.random.default_rng(seed)
    out_max, out_min = [], []
    chunk = 1_000_000
    for start in range(0, draws, chunk):
        k = min(chunk, draws - start)
        if m in (2, 3):  # W = T T^T entry by entry, eigenvalues in closed form
            d = [np.sqrt(rng.chisquare(n - i, k)) for i in range(m)]
            t10 = rng.standard_normal(k)
            if m == 2:
                a, b, c = d[0] ** 2, d[0] * t10, t10**2 + d[1] ** 2
                root = np.sqrt(0.25 * (a - c) ** 2 + b**2)
                out_max.append(0.5 * (a + c) + root)
                out_min.append(0.5 * (a + c) - root)
                continue
            t20, t21 = rng.standard_normal(k), rng.standard_normal(k)
            w00, w01, w02 = d[0] ** 2, d[0] * t10, d[0] * t20
            w11, w12, w22 = t10**2 + d[1] ** 2, t10 * t20 + d[1] * t21, t20**2 + t21**2 + d[2] ** 2
            # symmetric 3x3, trigonometric form (Smith 1961): q + 2 p cos(acos(det((W - qI)/p) / 2) / 3 + 2 pi j / 3)
            q = (w00 + w11 + w22) / 3.0
            a0, a1, a2 = w00 - q, w11 - q, w22 - q
            p = np.sqrt((a0**2 + a1**2 + a2**2 + 2 * (w01**2 + w02**2 + w12**2)) / 6.0)
            det = a0 * (a1 * a2 - w12**2) - w01 * (w01 * a2 - w12 * w02) + w02 * (w01 * w12 - a1 * w02)
            phi = np.arccos(np.clip(det / p**3 / 2.0, -1.0, 1.0)) / 3.0
            out_max.append(q + 2.0 * p * np.cos(phi))
            out_min.append(q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0))
            continue
        T = np.zeros((k, m, m))
        for i in range(m):
            T[:, i, i] = np.sqrt(rng.chisquare(n - i, k))
            for j in range(i):
                T[:, i, j] = rng.standard_normal(k)
        eig = np.linalg.eigvalsh(T @ np.swapaxes(T, 1, 2))
        out_max.append(eig[:, -1])
        out_min.append(eig[:, 0])
    return np.concatenate(out_max), np.concatenate(out_min)


def correlation_inflation(blocks: list[np.ndarray], max_lag: int = 10) -> float:
    """Variance inflation 1 + 2 sum rho_k of residual sequences (n, 3) correlated in time.

    Least squares with per-sample sigmas treats samples as independent; residuals that are correlated
    (filtered noise, vibration) carry less information, and the covariance must grow by this factor
    (the effective-sample-size correction; the sum stops at the first non-positive autocorrelation).
    """
    inflation = 1.0
    for k in range(1, max_lag + 1):
        num = sum(float(np.sum(b[k:] * b[:-k])) for b in blocks if len(b) > k)
        den = sum(float(np.sum(b * b)) for b in blocks)
        rho = num / den if den > 0 else 0.0
        if rho <= 0:
            break
        inflation += 2 * rho
    return inflation
