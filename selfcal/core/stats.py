"""Statistics every system's estimator and audit share: eigenvalue quantiles of Wishart matrices (the
eigenvalue fault detector's thresholds) and the variance inflation of residuals correlated in time.

References
----------
M. S. Bartlett, "On the theory of statistical regression", Proc. R. Soc. Edinburgh 53 (1933) (the
decomposition used to draw Wishart matrices).
O. K. Smith, "Eigenvalues of a symmetric 3 x 3 matrix", Comm. ACM 4(4) (1961) 168.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np


def wishart_lambda_max_quantile(m: int, n: int, alpha: float, draws: int = 2_000_000, seed: int = 20240604) -> float:
    """Upper ``alpha`` quantile of the largest eigenvalue of ``W ~ Wishart_m(n, I)`` (see :func:`_wishart_extremes`)."""
    lam_max, _ = _wishart_extremes(m, n, draws, seed)
    return float(np.quantile(lam_max, 1.0 - alpha))


def wishart_lambda_min_quantile(m: int, n: int, alpha: float, draws: int = 2_000_000, seed: int = 20240604) -> float:
    """Lower ``alpha`` quantile of the smallest eigenvalue of ``W ~ Wishart_m(n, I)`` (m = 2 or 3)."""
    _, lam_min = _wishart_extremes(m, n, draws, seed)
    return float(np.quantile(lam_min, alpha))


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
