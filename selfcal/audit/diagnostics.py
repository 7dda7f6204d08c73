"""Residual diagnostics: is what a fitted model leaves behind white, unbiased, Gaussian and independent of the
coordinates it was measured at?

Every test here is applied to the **whitened** residuals (equal unit variance under the model, which the tests
assume) and is scale-free, so a noise model whose sigmas are off by a constant factor does not change any
p-value.  Means, RMS values and slopes are reported on the **physical** residuals, in the family's unit.

* mean: one-sample t-test against 0;
* serial correlation: Ljung-Box portmanteau test on the time-ordered residuals;
* normality: D'Agostino-Pearson (``scipy.stats.normaltest``) for n >= 8, Shapiro-Wilk below;
* dependence on a coordinate: linear regression slope t-test (``scipy.stats.linregress``), and a one-way ANOVA
  (``scipy.stats.f_oneway``) over quantile bins of the coordinate for a dependence a straight line misses.
  The strongest coordinate is reported with its p-value Bonferroni-adjusted for the number of coordinates
  tried, so picking the smallest of several p-values does not manufacture a finding.

Two signal tools serve the same purpose on time series: :func:`dominant_period` (Lomb-Scargle for uneven
sampling) and :func:`cross_correlation_lag` (delay between two signals, sub-sample).

References
----------
Ljung, G. M. & Box, G. E. P. (1978). On a measure of lack of fit in time series models. Biometrika 65(2).
D'Agostino, R. & Pearson, E. S. (1973). Tests for departure from normality. Biometrika 60(3).
Zechmeister, M. & Kürster, M. (2009). The generalised Lomb-Scargle periodogram. A&A 496, 577-584.
Baluev, R. V. (2008). Assessing the statistical significance of periodogram peaks. MNRAS 385, 1279-1285.
"""
from __future__ import annotations

import warnings

import numpy as np
from scipy import signal, stats
from scipy.special import gammaln

from selfcal.audit.engine import ResidualFamily
from selfcal.core.signals import cross_correlation_lag  # noqa: F401  (re-exported: one implementation)

TIME_COORDINATE = "time_s"
MIN_NORMALTEST_N = 8  # below: Shapiro-Wilk (normaltest's skew test needs n >= 8)


# --- single tests ---------------------------------------------------------------------------------------------

def ljung_box(x, lags: int | None = None) -> tuple[float, int, float]:
    """Ljung-Box Q statistic of a time-ordered series: ``Q = n (n + 2) sum_{k=1}^{h} rho_k^2 / (n - k)``.

    Under the null (independent values) Q is chi-squared with h degrees of freedom.

    Parameters
    ----------
    x : (n,) array
        Time-ordered values (the mean is removed here).
    lags : int, optional
        Number of autocorrelations h; default ``min(10, n // 5)`` (at least 1), the usual rule for short series.

    Returns
    -------
    (Q, h, p_value)
        NaN statistic and p-value when the series is too short (n < 6) or constant.
    """
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    n = x.size
    h = int(lags) if lags is not None else max(1, min(10, n // 5))
    if n < 6 or h >= n:
        return float("nan"), h, float("nan")
    d = x - x.mean()
    denominator = float(d @ d)
    if denominator <= 0.0:
        return float("nan"), h, float("nan")
    k = np.arange(1, h + 1)
    rho = np.array([d[j:] @ d[:-j] for j in k]) / denominator
    q = float(n * (n + 2) * np.sum(rho**2 / (n - k)))
    return q, h, float(stats.chi2.sf(q, h))


def normality(x) -> tuple[str, float]:
    """(test name, p-value) of the null "x is Gaussian": D'Agostino-Pearson for n >= 8, else Shapiro-Wilk.

    NaN for fewer than 3 values or a constant series.
    """
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if x.size < 3 or np.ptp(x) == 0.0:
        return ("shapiro" if x.size < MIN_NORMALTEST_N else "normaltest"), float("nan")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # kurtosistest warns below n = 20; the p-value is still usable
        if x.size >= MIN_NORMALTEST_N:
            return "normaltest", float(stats.normaltest(x).pvalue)
        return "shapiro", float(stats.shapiro(x).pvalue)


def linear_dependence(y, c) -> tuple[float, float]:
    """(slope, p-value) of the least-squares line ``y = a + slope c`` (t-test of slope = 0); NaN if c is constant."""
    y, c = np.asarray(y, dtype=float), np.asarray(c, dtype=float)
    ok = np.isfinite(y) & np.isfinite(c)
    y, c = y[ok], c[ok]
    if y.size < 3 or np.ptp(c) == 0.0:
        return float("nan"), float("nan")
    fit = stats.linregress(c, y)
    return float(fit.slope), float(fit.pvalue)


def binned_anova(y, c, bins: int | None = None) -> tuple[float, int]:
    """(p-value, number of groups) of a one-way ANOVA of y across quantile bins of c.

    Detects any dependence on c, linear or not (a residual that is high at both ends of c and low in the middle
    has no slope but different bin means).  Default ``bins = clip(n // 5, 2, 6)``: enough values per bin for a
    stable mean.  Tied coordinate values stay in one bin; NaN when fewer than two bins with two values remain.
    """
    y, c = np.asarray(y, dtype=float), np.asarray(c, dtype=float)
    ok = np.isfinite(y) & np.isfinite(c)
    y, c = y[ok], c[ok]
    n = y.size
    bins = int(bins) if bins is not None else int(np.clip(n // 5, 2, 6))
    if n < 4 or np.ptp(c) == 0.0:
        return float("nan"), 0
    edges = np.unique(np.quantile(c, np.linspace(0.0, 1.0, bins + 1)))
    label = np.clip(np.searchsorted(edges, c, side="right") - 1, 0, len(edges) - 2)
    groups = [y[label == g] for g in np.unique(label)]
    groups = [g for g in groups if g.size >= 2]
    if len(groups) < 2 or all(np.ptp(g) == 0.0 for g in groups):
        return float("nan"), len(groups)
    return float(stats.f_oneway(*groups).pvalue), len(groups)


# --- per family -------------------------------------------------------------------------------------------------

def component_names(family: ResidualFamily) -> list[str]:
    """Readable names of a family's residual columns: the quantity for one column, x/y/z for three."""
    k = family.physical.shape[1] if family.physical.ndim == 2 else 1
    if k == 1:
        return [family.quantity]
    if k == 3:
        return ["x", "y", "z"]
    return [str(j) for j in range(k)]


def diagnose(family: ResidualFamily) -> list[dict]:
    """Diagnostics of one residual family, one dict per residual component.

    Parameters
    ----------
    family : ResidualFamily
        Whitened and physical residuals, (n, k), with coordinates (name -> (n,)); ``time_s`` orders the series
        for the Ljung-Box test (the given order is used without it).

    Returns
    -------
    list of dict
        Keys: ``family`` (label), ``component``, ``unit``, ``n``;
        ``mean`` (physical), ``mean_p`` (t-test of zero mean); ``rms`` (physical);
        ``ljung_box_q``, ``ljung_box_lags``, ``ljung_box_p``; ``normality_test``, ``normality_p``;
        ``linear_coordinate``, ``linear_slope`` (physical unit per coordinate unit), ``linear_p``;
        ``anova_coordinate``, ``anova_bins``, ``anova_p``; ``n_coordinates``;
        ``period_s``, ``period_fap``: the strongest periodic term in time (Lomb–Scargle, uneven sampling) and
        its false-alarm probability (NaN without a ``time_s`` coordinate or with fewer than 16 residuals).
        ``linear_p`` and ``anova_p`` belong to the coordinate with the smallest p-value and are
        Bonferroni-adjusted over the ``n_coordinates`` tried (``min(1, m p)``).  NaN where a test cannot run.
    """
    physical = np.asarray(family.physical, dtype=float)
    whitened = np.asarray(family.whitened, dtype=float)
    if physical.ndim == 1:
        physical, whitened = physical[:, None], whitened[:, None]
    n = physical.shape[0]
    coords = {name: np.asarray(v, dtype=float) for name, v in family.coordinates.items() if np.size(v) == n}
    order = np.argsort(coords[TIME_COORDINATE], kind="stable") if TIME_COORDINATE in coords else np.arange(n)
    out = []
    for j, name in enumerate(component_names(family)):
        x, w = physical[:, j], whitened[:, j]
        finite = np.isfinite(w)
        if finite.sum() >= 2 and np.ptp(w[finite]) > 0:
            mean_p = float(stats.ttest_1samp(w[finite], 0.0).pvalue)
        else:
            mean_p = float("nan")
        q, lags, lb_p = ljung_box(w[order])
        test, norm_p = normality(w)
        linear = _strongest(coords, lambda c: linear_dependence(w, c)[1])
        anova = _strongest(coords, lambda c: binned_anova(w, c)[0])
        slope = linear_dependence(x, coords[linear[0]])[0] if linear[0] else float("nan")
        bins = binned_anova(w, coords[anova[0]])[1] if anova[0] else 0
        period = (float("nan"), float("nan"))
        if TIME_COORDINATE in coords and finite.sum() >= 16 and np.ptp(coords[TIME_COORDINATE]) > 0:
            period = dominant_period(coords[TIME_COORDINATE][finite], w[finite])
        out.append({
            "family": family.label, "component": name, "unit": family.unit, "n": int(finite.sum()),
            "mean": float(np.nanmean(x)) if n else float("nan"), "mean_p": mean_p,
            "rms": float(np.sqrt(np.nanmean(x**2))) if n else float("nan"),
            "ljung_box_q": q, "ljung_box_lags": lags, "ljung_box_p": lb_p,
            "normality_test": test, "normality_p": norm_p,
            "linear_coordinate": linear[0], "linear_slope": slope, "linear_p": linear[1],
            "anova_coordinate": anova[0], "anova_bins": bins, "anova_p": anova[1],
            "n_coordinates": len(coords),
            "period_s": period[0], "period_fap": period[1],
        })
    return out


def _strongest(coords: dict, p_of) -> tuple[str | None, float]:
    """The coordinate with the smallest p-value and that p-value, Bonferroni-adjusted over all coordinates."""
    best, best_p = None, float("nan")
    for name, c in coords.items():
        p = p_of(c)
        if np.isfinite(p) and (best is None or p < best_p):
            best, best_p = name, p
    if best is None:
        return None, float("nan")
    return best, float(min(1.0, best_p * len(coords)))


# --- signal tools -------------------------------------------------------------------------------------------------

def dominant_period(t, x, min_period: float | None = None, max_period: float | None = None,
                    oversampling: int = 5) -> tuple[float, float]:
    """Strongest period of an unevenly sampled series and its false-alarm probability.

    Generalised (floating-mean) Lomb-Scargle periodogram, normalised so that the power ``p`` at a frequency is
    the fraction of the variance a sinusoid of that frequency explains (Zechmeister & Kürster 2009).  For
    Gaussian white noise, ``Prob(p > p0) = (1 - p0)^((n - 3) / 2)`` at one frequency; searching the band up to
    ``f_max`` multiplies the chances, which Baluev's (2008) bound accounts for:
    ``FAP = 1 - (1 - Prob) exp(-tau)``, ``tau ~ f_max T_eff (1 - p0)^((n - 4) / 2) sqrt(p0)`` (up to a
    Gamma-function factor), ``T_eff = sqrt(4 pi var(t))``.  A small FAP means the peak is not a chance
    fluctuation of white noise; on white noise the FAP is close to uniformly distributed (it is the
    probability it claims to be).

    Parameters
    ----------
    t : (n,) array
        Sample times (any order, any spacing), e.g. s.
    x : (n,) array
        Values.
    min_period, max_period : float, optional
        Band searched, in the unit of t.  Defaults: twice the median spacing (a pseudo-Nyquist limit for
        uneven sampling), and the time span.
    oversampling : int
        Frequency grid step ``1 / (oversampling T)``: fine enough not to miss a peak between grid points.

    Returns
    -------
    (period, false_alarm_probability)
        NaN, NaN when there are fewer than 5 finite samples or the series is constant.
    """
    t, x = np.asarray(t, dtype=float), np.asarray(x, dtype=float)
    ok = np.isfinite(t) & np.isfinite(x)
    t, x = t[ok], x[ok]
    n = t.size
    if n < 5 or np.ptp(x) == 0.0 or np.ptp(t) == 0.0:
        return float("nan"), float("nan")
    span = float(np.ptp(t))
    spacing = np.diff(np.sort(t))
    spacing = float(np.median(spacing[spacing > 0])) if np.any(spacing > 0) else span / n
    f_lo = 1.0 / (max_period if max_period else span)
    f_hi = 1.0 / (min_period if min_period else 2.0 * spacing)
    if f_hi <= f_lo:
        return float("nan"), float("nan")
    freqs = np.arange(f_lo, f_hi, 1.0 / (oversampling * span))
    if freqs.size == 0:
        freqs = np.array([f_lo])
    power = signal.lombscargle(t, x - x.mean(), 2.0 * np.pi * freqs, normalize=True, floating_mean=True)
    best = int(np.argmax(power))
    p0 = float(np.clip(power[best], 0.0, 1.0))
    # Baluev (2008): FAP ~ 1 - (1 - Prob) exp(-tau), tau the expected number of up-crossings of p0 over the band
    n_null, n_signal = n - 1, n - 3
    single_cdf = 1.0 - (1.0 - p0) ** (0.5 * n_signal)
    effective_span = np.sqrt(4.0 * np.pi * np.var(t))
    gamma = np.sqrt(2.0 / n_null) * np.exp(gammaln(0.5 * n_null) - gammaln(0.5 * (n_null - 1)))
    tau = gamma * f_hi * effective_span * (1.0 - p0) ** (0.5 * (n_signal - 1)) * np.sqrt(0.5 * n_null * p0)
    fap = 1.0 - single_cdf * np.exp(-tau)
    return float(1.0 / freqs[best]), float(np.clip(fap, 0.0, 1.0))
