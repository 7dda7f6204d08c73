"""Signal helpers shared by estimators and diagnostics (pure numpy/scipy)."""
from __future__ import annotations

import numpy as np
from scipy import signal


def cross_correlation_lag(t, a, b, max_lag: float | None = None) -> float:
    """Delay of ``b`` behind ``a`` (in the unit of t) that maximises their correlation: ``b(t) ~ a(t - lag)``.

    Both signals are sampled at the same times ``t``; uneven times are linearly interpolated onto a uniform
    grid at the median spacing.  The means are removed, the full cross-correlation is searched for its
    maximum (within ``+-max_lag`` if given), and the peak is refined to a fraction of a sample by the vertex of
    the parabola through the peak and its two neighbours.

    Parameters
    ----------
    t : (n,) array
        Common sample times, increasing.
    a, b : (n,) array
        The two signals.
    max_lag : float, optional
        Largest |lag| searched (unit of t); default: the whole overlap.

    Returns
    -------
    float
        The lag; positive when b is a delayed copy of a.  NaN when either signal is constant.
    """
    t, a, b = (np.asarray(v, dtype=float) for v in (t, a, b))
    order = np.argsort(t, kind="stable")
    t, a, b = t[order], a[order], b[order]
    dt = float(np.median(np.diff(t)))
    if not np.allclose(np.diff(t), dt, rtol=1e-6, atol=0.0):
        grid = np.arange(t[0], t[-1] + 0.5 * dt, dt)
        a, b, t = np.interp(grid, t, a), np.interp(grid, t, b), grid
    a, b = a - a.mean(), b - b.mean()
    norm = np.sqrt((a @ a) * (b @ b))
    if norm == 0.0:
        return float("nan")
    corr = signal.correlate(b, a, mode="full", method="auto") / norm
    lags = signal.correlation_lags(b.size, a.size, mode="full")
    if max_lag is not None:
        inside = np.abs(lags) <= max_lag / dt + 1  # keep one neighbour beyond for the parabola
        corr = np.where(inside, corr, -np.inf)
    k = int(np.argmax(corr))
    shift = 0.0
    if 0 < k < corr.size - 1 and np.all(np.isfinite(corr[k - 1:k + 2])):
        y0, y1, y2 = corr[k - 1], corr[k], corr[k + 1]
        curvature = y0 - 2.0 * y1 + y2
        if curvature < 0.0:
            # vertex of the parabola through (-1, y0), (0, y1), (1, y2)
            shift = 0.5 * (y0 - y2) / curvature
    return float((lags[k] + shift) * dt)
