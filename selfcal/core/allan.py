"""Allan variance of a rate-type time series: the measured curve, its statistics, and the curves noise terms predict.

Pure statistics of a uniformly sampled series (angular rate, specific force), independent of what a caller
decides from them; :mod:`selfcal.audit.noise` fits noise models to these curves and decides.

Noise terms.  The Allan variance (AVAR) that each noise term predicts, in closed form (IEEE Std 952-1997,
Annex C; El-Sheimy et al. 2008)::

    white noise, density N (Kalibr ``*_noise_density``)       AVAR = N^2 / tau
    bias instability (flicker), B, flat part                   AVAR = (2 ln 2 / pi) B^2
    rate random walk, K (Kalibr ``*_random_walk``)             AVAR = K^2 tau / 3
    first-order Gauss-Markov, std sigma, correlation time T    AVAR = sigma^2 (2 x - 3 + 4 e^-x - e^-2x) / x^2,
                                                                      x = tau / T

Statistics of the measured curve.  At each tau the overlapping Allan variance is (very nearly) a scaled
chi-square variable, ``AVAR_hat = AVAR chi2_nu / nu``, with ``nu`` the equivalent degrees of freedom of
Greenhall's algorithm (:func:`allantools.edf_greenhall`) for the power-law noise type at that tau.  In log
space this law has the exact mean ``ln AVAR + psi(nu/2) - ln(nu/2)`` and variance ``psi'(nu/2)`` (``psi`` the
digamma function; :func:`log_chi2_law`), so a fit there can remove the small-``nu`` bias of the long-tau
points instead of being pulled down by it.  Taus stop at an eighth of the series, where ``nu`` is still about
3 or more.  The noise type at each tau is the local slope of a curve: of the measured one for the curve's own
error bars (``AllanCurve.adev_err``, :func:`noise_type_from_slope`), of a model curve for a fit
(:func:`model_alpha`).

Correlation between tau points.  Estimates at neighbouring octaves share data: octave neighbours correlate by
about 0.53 for white noise, 0.7 for flicker, 0.89 for random walk.  :func:`oadev_correlation` computes the
correlation from the estimator's kernels for white and for random-walk noise and interpolates by the local
noise type (the midpoint reproduces flicker's 0.7).  This is an approximation (Gauss-Markov and mixed segments
get interpolated correlations).

References
----------
IEEE Std 952-1997, "IEEE Standard Specification Format Guide and Test Procedure for Single-Axis Interferometric
    Fiber Optic Gyros", Annex C (Allan variance of the noise terms).
N. El-Sheimy, H. Hou, X. Niu, "Analysis and modeling of inertial sensors using Allan variance", IEEE Trans.
    Instrum. Meas. 57(1), 140-149, 2008 (Allan variance of exponentially correlated noise).
C. A. Greenhall, W. J. Riley, "Uncertainty of stability variances based on finite differences", 35th PTTI, 2003
    (equivalent degrees of freedom).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable

import allantools
import numpy as np
from scipy import signal, special

FLICKER_FACTOR = 2.0 * math.log(2.0) / math.pi  # AVAR of flicker (flat part) = FLICKER_FACTOR B^2
STOP_RATIO = 8.0


# --- Allan deviation ---------------------------------------------------------------------------------------------

@dataclass
class AllanCurve:
    """Overlapping Allan deviation of one or three axes, with its statistics.

    Unpacks as ``taus_s, adev, adev_err = curve``.  Arrays are (K,) for one axis, (K, 3) for three.

    Attributes
    ----------
    taus_s : (K,) averaging times, s.
    adev : measured overlapping Allan deviation (unit of the samples).
    adev_err : 1-sigma error of ``adev``, ``adev / sqrt(2 edf)`` (first order in ``1/edf``).
    edf : equivalent degrees of freedom (Greenhall) of each Allan variance estimate.
    alpha : power-law exponent of the frequency (here: rate) noise assumed for ``edf`` at each tau
        (0 white, -1 flicker, -2 random walk), from the local slope of ``adev``.
    n_samples, rate_hz : length and rate of the series.
    """

    taus_s: np.ndarray
    adev: np.ndarray
    adev_err: np.ndarray
    edf: np.ndarray
    alpha: np.ndarray
    n_samples: int
    rate_hz: float

    def __iter__(self):
        return iter((self.taus_s, self.adev, self.adev_err))

    @property
    def n_axes(self) -> int:
        return 1 if self.adev.ndim == 1 else self.adev.shape[1]

    def axis(self, i: int) -> AllanCurve:
        """The curve of axis ``i`` (a one-axis curve is its own axis 0)."""
        if self.adev.ndim == 1:
            if i != 0:
                raise IndexError(f"one-axis curve has no axis {i}")
            return self
        return AllanCurve(self.taus_s, self.adev[:, i], self.adev_err[:, i], self.edf[:, i], self.alpha[:, i],
                          self.n_samples, self.rate_hz)

    def confidence_interval(self, ci: float = 0.682689492137) -> tuple[np.ndarray, np.ndarray]:
        """Chi-square confidence interval ``(lo, hi)`` of ``adev`` (allantools.confidence_interval)."""
        lo, hi = np.empty_like(self.adev), np.empty_like(self.adev)
        for idx in np.ndindex(self.adev.shape):
            lo[idx], hi[idx] = allantools.confidence_interval(float(self.adev[idx]), float(self.edf[idx]), ci)
        return lo, hi


def noise_type_from_slope(taus_s: np.ndarray, adev: np.ndarray) -> np.ndarray:
    """Power-law exponent alpha of rate noise per tau, from the local log-log slope of the Allan deviation.

    ``AVAR ~ tau^mu`` with ``mu = -alpha - 1`` for rate ("frequency") data; the slope is the least-squares slope
    over the point and its two neighbours, ``alpha`` is rounded and clipped to [-2, 0] (white to random walk).
    Types above white (quantization, alpha > 0) are counted as white: they matter only at the shortest taus,
    where the edf is large whatever the type.  A noisy slope at long tau mostly errs towards alpha < 0, whose
    edf is smaller: the error bars then err on the large (conservative) side.
    """
    lt, la = np.log(taus_s), np.log(adev)
    k = len(lt)
    alpha = np.zeros(k, dtype=int)
    for i in range(k):
        sl = slice(max(i - 1, 0), min(i + 2, k))
        if sl.stop - sl.start < 2:
            continue
        slope = np.polyfit(lt[sl], la[sl], 1)[0]
        alpha[i] = int(np.clip(np.rint(-2.0 * slope - 1.0), -2, 0))
    return alpha


def tau_list(n: int, rate_hz: float, taus="octave", stop_ratio: float = STOP_RATIO) -> np.ndarray:
    """Averaging times (s) for a series of ``n`` samples: whole numbers of samples ``m`` with ``m <= n / stop_ratio``.

    ``"octave"``: m = 1, 2, 4, ...; ``"decade"``: m = 1, 2, 4, 10, 20, 40, ...; an array: its values rounded to
    whole samples.  The stop ratio 8 keeps every point above about 3 equivalent degrees of freedom (at m = n/4,
    allantools' own limit, an overlapping estimate can rest on a single degree of freedom).
    """
    m_max = n / stop_ratio
    if isinstance(taus, str):
        if taus == "octave":
            m = 2.0 ** np.arange(0, max(int(np.floor(np.log2(m_max))), 0) + 1)
        elif taus == "decade":
            m = np.array([f * 10.0**k for k in range(int(np.log10(max(m_max, 1))) + 1) for f in (1, 2, 4)])
        else:
            raise ValueError(f"taus must be 'octave', 'decade' or an array of s, got {taus!r}")
    else:
        m = np.rint(np.asarray(taus, dtype=float) * rate_hz)
    m = np.unique(m[(m >= 1) & (m <= max(m_max, 1))])
    return m / rate_hz


def allan_curve(x, rate_hz: float, taus="octave", stop_ratio: float = STOP_RATIO) -> AllanCurve:
    """Overlapping Allan deviation (allantools.oadev) per axis, with edf-based error bars.

    Parameters
    ----------
    x : array_like (N,) or (N, 3)
        Rate-type samples (angular rate, specific force) of a static sensor, uniformly sampled.
    rate_hz : float
        Sample rate, Hz.
    taus : {"octave", "decade"} or array_like
        Averaging times (see :func:`tau_list`); ``"octave"`` keeps neighbouring points a factor 2 apart.
    stop_ratio : float
        Longest tau is ``N / stop_ratio`` samples.

    Returns
    -------
    AllanCurve
        Unpacks as ``taus_s, adev, adev_err``.

    Notes
    -----
    allantools' own error ``adev / sqrt(n_terms)`` ignores that overlapping terms are correlated; the error here
    comes from Greenhall's equivalent degrees of freedom instead, ``adev_err = adev / sqrt(2 edf)``.
    """
    x = np.asarray(x, dtype=float)
    one_axis = x.ndim == 1
    cols = x[:, None] if one_axis else x
    if cols.ndim != 2 or cols.shape[0] < 16:
        raise ValueError(f"need (N,) or (N, k) samples with N >= 16, got shape {x.shape}")
    if not np.all(np.isfinite(cols)):
        raise ValueError("samples hold NaN or inf")
    n = cols.shape[0]
    taus_in = tau_list(n, rate_hz, taus, stop_ratio)
    taus_ref = None
    adevs, errs, edfs, alphas = [], [], [], []
    for j in range(cols.shape[1]):
        t, ad, _, _ = allantools.oadev(cols[:, j], rate=float(rate_hz), data_type="freq", taus=taus_in)
        if taus_ref is None:
            taus_ref = t
        elif not np.array_equal(t, taus_ref):
            raise ValueError("axes gave different tau lists")
        if not np.all(ad > 0):  # a constant channel carries no information (and breaks the log-space fit)
            raise ValueError(f"axis {j}: zero Allan deviation (constant samples?)")
        alpha = noise_type_from_slope(t, ad)
        edf = edf_for(alpha, np.rint(t * rate_hz).astype(int), n)
        adevs.append(ad)
        errs.append(ad / np.sqrt(2.0 * edf))
        edfs.append(edf)
        alphas.append(alpha)
    stack = (lambda a: a[0]) if one_axis else (lambda a: np.column_stack(a))
    return AllanCurve(np.asarray(taus_ref, dtype=float), stack(adevs), stack(errs), stack(edfs), stack(alphas),
                      n, float(rate_hz))


def stack_curves(curves: list[AllanCurve]) -> AllanCurve:
    """One curve of several axes from one-axis curves of the same series (same taus)."""
    c0 = curves[0]
    col = lambda name: np.column_stack([getattr(c, name) for c in curves])  # noqa: E731
    return AllanCurve(c0.taus_s, col("adev"), col("adev_err"), col("edf"), col("alpha"), c0.n_samples, c0.rate_hz)


# --- Allan variance of the noise terms ---------------------------------------------------------------------------

def avar_white(taus_s, density):
    """``N^2 / tau``: white rate noise of density N (unit / sqrt(Hz)) (IEEE 952 Annex C, angle random walk)."""
    return density**2 / np.asarray(taus_s, dtype=float)


def avar_flicker(taus_s, bias_instability):
    """``(2 ln 2 / pi) B^2``: flat part of flicker (1/f) rate noise, B the bias instability (IEEE 952 Annex C)."""
    return FLICKER_FACTOR * bias_instability**2 * np.ones_like(np.asarray(taus_s, dtype=float))


def avar_random_walk(taus_s, random_walk):
    """``K^2 tau / 3``: random walk of the rate, K in unit / s / sqrt(Hz) (IEEE 952 Annex C; Kalibr random_walk)."""
    return random_walk**2 * np.asarray(taus_s, dtype=float) / 3.0


def avar_gauss_markov(taus_s, sigma, tau_c_s):
    """First-order Gauss-Markov rate noise ``R(u) = sigma^2 exp(-|u| / T)``, T = ``tau_c_s``::

        AVAR(tau) = sigma^2 T / tau [2 - T / tau (3 - 4 exp(-tau / T) + exp(-2 tau / T))]

    (El-Sheimy et al. 2008, eq. for exponentially correlated noise, with their ``q_c^2 = 2 sigma^2 / T``;
    from ``AVAR = (4 Phi(tau) - Phi(2 tau)) / (2 tau^2)``, ``Phi(t) = 2 int_0^t (t - u) R(u) du``).
    Limits: ``2 sigma^2 T / tau`` (white, density ``sigma sqrt(2 T)``) for tau >> T, and ``K^2 tau / 3`` with
    ``K^2 = 2 sigma^2 / T`` (random walk) for tau << T, where the series ``2x/3 - x^2/2 + 7x^3/30 - x^4/12``
    (x = tau / T) replaces the closed form to avoid cancellation.
    """
    x = np.asarray(taus_s, dtype=float) / tau_c_s
    small = x < 1e-2
    xs = np.where(small, 1.0, x)
    closed = (2.0 * xs - 3.0 + 4.0 * np.exp(-xs) - np.exp(-2.0 * xs)) / xs**2
    series = x * (2.0 / 3.0 - x * (0.5 - x * (7.0 / 30.0 - x / 12.0)))
    return sigma**2 * np.where(small, series, closed)


# --- statistics of the estimates ---------------------------------------------------------------------------------

def log_chi2_law(edf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean offset and std of ``ln(chi2_nu / nu)``: ``psi(nu/2) - ln(nu/2)`` and ``sqrt(psi'(nu/2))``."""
    half = 0.5 * np.asarray(edf, dtype=float)
    return special.digamma(half) - np.log(half), np.sqrt(special.polygamma(1, half))


def _difference_kernel(m: int, noise: str) -> np.ndarray:
    """Weights of ``d_i(m)`` (half the difference of adjacent m-sample means) on the driving white sequence.

    ``white``: on the rate samples themselves, ``(-1 x m, +1 x m) / (m sqrt 2)``; ``random_walk``: on the
    steps of a random-walking rate, the running sum of the former, a triangle ``min(v, 2m - v) / (m sqrt 2)``.
    """
    if noise == "white":
        return np.concatenate([-np.ones(m), np.ones(m)]) / (m * math.sqrt(2.0))
    v = np.arange(1, 2 * m)
    return np.minimum(v, 2 * m - v) / (m * math.sqrt(2.0))


@functools.lru_cache(maxsize=32)
def _oadev_correlation_pure(m: tuple, n: int, noise: str, m_ref: int, m_max: int) -> np.ndarray:
    k = len(m)
    corr = np.eye(k)
    for i in range(k):
        for j in range(i + 1, k):
            m1, m2 = m[i], m[j]  # m1 < m2
            # scale invariance: the same correlation at m / q with lags times q (q = 1 keeps it exact)
            q = max(1.0, m1 / m_ref, m2 / m_max)
            m1s, m2s = max(int(round(m1 / q)), 1), max(int(round(m2 / q)), 1)
            n1, n2 = n + 1 - 2 * m1, n + 1 - 2 * m2  # terms of each overlapping estimate

            def weighted(ma, mb, na, nb):
                ka, kb = _difference_kernel(ma, noise), _difference_kernel(mb, noise)
                c = signal.fftconvolve(ka, kb[::-1])  # c[l + len(kb) - 1] = Cov(d_i(ma), d_(i+l)(mb)), unit drive
                lag = (np.arange(c.size) - (kb.size - 1)) * q
                count = np.clip(np.minimum(na, nb - lag) - np.maximum(0, -lag), 0, None)  # term pairs at lag
                return float(np.sum(count * c**2)) / (na * nb)

            s12 = weighted(m1s, m2s, n1, n2)
            corr[i, j] = corr[j, i] = s12 / math.sqrt(weighted(m1s, m1s, n1, n1) * weighted(m2s, m2s, n2, n2))
    return corr


def oadev_correlation(m, n: int, alpha=None, m_ref: int = 64, m_max: int = 4096) -> np.ndarray:
    """Correlation matrix of overlapping Allan variance estimates at averaging factors ``m`` of ``n`` samples.

    For Gaussian data ``AVAR_hat(m) = mean_i d_i(m)^2``, so ``Cov(AVAR_hat(m1), AVAR_hat(m2)) = 2 / (n1 n2)
    sum_(i,j) Cov(d_i(m1), d_j(m2))^2``: for a pure noise type, a sum over lags of the squared
    cross-correlation of the two difference kernels (:func:`_difference_kernel`), weighted by the number of term
    pairs at each lag.  Computed exactly for white and for random-walk rate noise, except that long kernels
    are scaled down to ``m_ref`` .. ``m_max`` samples (the correlation is scale invariant at fixed ``n / m``).
    Octave neighbours correlate by about 0.53 (white) and 0.89 (random walk); the same matrix holds for
    ``ln AVAR_hat`` to first order.

    ``alpha`` (per point: 0 white, -1 flicker, -2 random walk; see :func:`noise_type_from_slope`) mixes the
    two: pair (i, j) gets ``(1 - w) R_white + w R_rw`` with ``w = -(alpha_i + alpha_j) / 4``.  Flicker, half
    way, and mixed pairs are interpolations: an approximation, as is the use of noise types read from the
    measured curve.  Without ``alpha`` the white-noise matrix is returned.
    """
    order = np.argsort(m)
    ms = tuple(int(x) for x in np.asarray(m)[order])
    white = _oadev_correlation_pure(ms, int(n), "white", m_ref, m_max)
    if alpha is None:
        corr = white
    else:
        rw = _oadev_correlation_pure(ms, int(n), "random_walk", m_ref, m_max)
        a = -np.asarray(alpha, dtype=float)[order] / 2.0
        w = 0.5 * (a[:, None] + a[None, :])
        corr = (1.0 - w) * white + w * rw
    w_eig, v = np.linalg.eigh(corr)
    if w_eig.min() < 1e-3:  # interpolation can cost positive definiteness: lift the spectrum, keep unit diagonal
        corr = (v * np.clip(w_eig, 1e-3, None)) @ v.T
        d = np.sqrt(np.diag(corr))
        corr = corr / np.outer(d, d)
    inv = np.argsort(order)
    return corr[np.ix_(inv, inv)]


@functools.lru_cache(maxsize=4096)
def _edf(alpha: int, m: int, n: int) -> float:
    # allantools counts N in phase points: n rate samples integrate to n + 1 phase points
    return float(allantools.edf_greenhall(alpha, 2, m, n + 1, overlapping=True))


def edf_for(alpha, m, n: int) -> np.ndarray:
    """Greenhall edf of overlapping AVAR at averaging factors ``m``; a fractional ``alpha`` (between white, 0,
    and random walk, -2) interpolates ``ln edf`` between its two integer neighbours."""
    alpha = np.clip(np.asarray(alpha, dtype=float), -2.0, 0.0)
    out = np.empty(alpha.shape)
    for i, (a, mi) in enumerate(zip(alpha, np.asarray(m, dtype=int))):
        lo, hi = math.floor(a), math.ceil(a)
        e_lo, e_hi = _edf(lo, int(mi), n), _edf(hi, int(mi), n)
        out[i] = e_lo if lo == hi else math.exp(math.log(e_lo) + (a - lo) * (math.log(e_hi) - math.log(e_lo)))
    return out


def model_alpha(avar: Callable[[np.ndarray], np.ndarray], taus_s: np.ndarray) -> np.ndarray:
    """Local power-law exponent of rate noise, ``alpha = -d ln AVAR / d ln tau - 1``, of a model curve, in
    [-2, 0] (0 white, -1 flicker, -2 random walk; fractional between)."""
    h = 1e-3
    mu = (np.log(avar(taus_s * math.exp(h))) - np.log(avar(taus_s * math.exp(-h)))) / (2.0 * h)
    return np.clip(-mu - 1.0, -2.0, 0.0)
