"""Noise-model audit of static IMU data: is white noise alone enough, or does the bias wander?

The measured overlapping Allan deviation of each axis (:func:`selfcal.core.allan.allan_curve`) is compared with
the Allan deviation that noise models predict in closed form (:mod:`selfcal.core.allan`: white noise, flicker,
rate random walk, first-order Gauss-Markov; IEEE Std 952-1997, Annex C; El-Sheimy et al. 2008).

The base model is white noise only, its density read from the short-tau part of the curve (tau <= 1 s) or
declared (Kalibr).  The extensions are white + random walk, white + Gauss-Markov, white + flicker and white +
flicker + random walk.  On each axis the extension with the lowest BIC is accepted when

1. it is significantly better on the whole series: BIC lower than that of the best-fitting white model by more
   than 10 ("very strong" on the Kass and Raftery scale, posterior odds above 150:1; the margin also covers the
   approximations below: the correlation model, parameters on a boundary or unidentified under the null), and
2. it predicts held-out data: fitted on the first half of the series, it gives the Allan curve of the second
   half a higher likelihood than the white model fitted on the first half does.

Statistics of the measured curve.  The fits work in log space, where the Allan variance estimate at each tau
(a scaled chi-square variable with Greenhall's equivalent degrees of freedom ``nu``) has an exact mean and
variance (:func:`selfcal.core.allan.log_chi2_law`): the small-``nu`` bias of the long-tau points is removed
instead of pulling the fit down.  In a fit, the noise type at each tau is the local slope of the model curve
being fitted (iteratively reweighted), so every model is scored with the statistics it implies; the curve's own
error bars (``AllanCurve.adev_err``, for display) use the slope of the measured curve.

Correlation between tau points.  Estimates at neighbouring octaves share data; the fits use the full
covariance of the points, with the correlation of :func:`selfcal.core.allan.oadev_correlation` (exact for white
and for random-walk noise, interpolated by the local noise type).  This is an approximation (Gauss-Markov and
mixed segments get interpolated correlations).  Its effect, measured by simulation: white-noise series never
come near the acceptance threshold (delta BIC >= -6 over 600 axes of 1e5 samples), and the spread of fitted
parameters around the truth matches the reported std (RMS of the normalised error 1.0-1.2 over 120 axes each
of white + random walk and white + Gauss-Markov; |error| > 3 std for 1-2 % of the axes, against 0.27 % for a
Gaussian: the finite record makes the tails heavier).

Model error.  A real sensor's curve carries features no candidate model has (an internal filter at the
shortest taus, a bump from a periodic disturbance), and the statistical errors there are tiny (a million
samples give ``nu ~ 1e5``).  Each fit therefore has one more parameter, a model-error std ``f`` of ``ln
AVAR`` added to every point and fitted by maximum likelihood: ~0 on data that a model describes, a few tenths
on real data, where it keeps a handful of misfit short-tau points from dictating the long-tau parameters.

References
----------
IEEE Std 952-1997, "IEEE Standard Specification Format Guide and Test Procedure for Single-Axis Interferometric
    Fiber Optic Gyros", Annex C (Allan variance of the noise terms).
N. El-Sheimy, H. Hou, X. Niu, "Analysis and modeling of inertial sensors using Allan variance", IEEE Trans.
    Instrum. Meas. 57(1), 140-149, 2008 (Allan variance of exponentially correlated noise).
C. A. Greenhall, W. J. Riley, "Uncertainty of stability variances based on finite differences", 35th PTTI, 2003
    (equivalent degrees of freedom).
R. E. Kass, A. E. Raftery, "Bayes factors", J. Am. Stat. Assoc. 90, 773-795, 1995 (delta BIC < -10: very strong).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import optimize, stats

from selfcal.core.allan import (FLICKER_FACTOR, AllanCurve, allan_curve, avar_flicker, avar_gauss_markov,
                                avar_random_walk, avar_white, edf_for, log_chi2_law, model_alpha,
                                oadev_correlation, stack_curves)

log = logging.getLogger(__name__)

BIC_THRESHOLD = -10.0
SHORT_TAU_MAX_S = 1.0
# the model-error term f (std of ln AVAR) lives in [MODEL_ERROR_MIN, 10]; at the lower end it is negligible
# against every statistical error (s_i >= ~1.6e-3 for a million samples), so "f = 0" is reachable
MODEL_ERROR_MIN = 1e-5
EXTENSIONS = ("random_walk", "gauss_markov", "flicker", "flicker_random_walk")
QUANTITIES = {"accel": ("m s^-2", "accelerometer"), "gyro": ("rad s^-1", "gyroscope")}


# --- models and fits ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class NoiseModel:
    """A sum of noise terms: parameter names and the Allan variance as a function of ``(taus, *params)``."""

    name: str
    params: tuple[str, ...]
    avar: Callable[..., np.ndarray]

    @property
    def n_params(self) -> int:
        return len(self.params)


MODELS = {
    "white": NoiseModel("white", ("white_density",), lambda t, n: avar_white(t, n)),
    "random_walk": NoiseModel("random_walk", ("white_density", "random_walk"),
                              lambda t, n, k: avar_white(t, n) + avar_random_walk(t, k)),
    "gauss_markov": NoiseModel("gauss_markov", ("white_density", "sigma", "tau_s"),
                               lambda t, n, s, tc: avar_white(t, n) + avar_gauss_markov(t, s, tc)),
    "flicker": NoiseModel("flicker", ("white_density", "bias_instability"),
                          lambda t, n, b: avar_white(t, n) + avar_flicker(t, b)),
    "flicker_random_walk": NoiseModel("flicker_random_walk", ("white_density", "bias_instability", "random_walk"),
                                      lambda t, n, b, k: avar_white(t, n) + avar_flicker(t, b)
                                      + avar_random_walk(t, k)),
}


@dataclass
class ModelFit:
    """A noise model fitted to an Allan curve by maximum likelihood in log Allan variance.

    The residuals ``r_i = ln AVAR_hat_i - ln AVAR_model_i - m_i`` (``m_i``: mean of ``ln(chi2_nu / nu)``, module
    notes) are Gaussian with covariance ``C = S R S + f^2 I``: ``S = diag(s_i)`` the stds of ``ln(chi2_nu /
    nu)``, ``R`` the correlation of the overlapping estimates (:func:`oadev_correlation`), both for the noise
    types of the model curve (:func:`model_alpha`), ``f`` a model-error term fitted with the parameters.
    ``nll = r^T C^-1 r + ln det C`` is -2 log-likelihood (constants dropped), ``chi2 = r^T C^-1 r``,
    ``bic = nll + k ln n`` over the ``n`` tau points (``k`` model parameters plus ``f``).
    ``std`` is from ``(J^T C^-1 J)^-1`` (J: derivatives of ``ln AVAR_model`` with respect to the log
    parameters; ``cov_log`` is that covariance), mapped to the parameters by the delta method; NaN for a
    parameter the curve does not constrain or that sits on a bound.
    """

    model: str
    params: dict[str, float]
    std: dict[str, float]
    cov_log: np.ndarray
    model_error: float
    nll: float
    chi2: float
    n_points: int
    fixed: bool = False

    @property
    def k(self) -> int:
        """Free parameters (the model-error term included)."""
        return 1 + (0 if self.fixed else MODELS[self.model].n_params)

    @property
    def bic(self) -> float:
        return self.nll + self.k * math.log(self.n_points)

    def avar(self, taus_s) -> np.ndarray:
        return MODELS[self.model].avar(np.asarray(taus_s, dtype=float), *self.params.values())

    def adev(self, taus_s) -> np.ndarray:
        return np.sqrt(self.avar(taus_s))

    def score(self, curve: AllanCurve) -> float:
        """-2 log-likelihood of another (e.g. held-out) one-axis curve under this fit, its ``f`` included."""
        return _score(curve, self.avar, self.model_error)[0]


class _LogLikelihood:
    """Gaussian likelihood of ``ln AVAR_hat`` on one axis for a given noise type per point (``alpha``).

    Mean ``ln AVAR_model + m_i``, covariance ``C(f) = S R S + f^2 I``: ``m_i``, ``S = diag(s_i)`` the mean
    offset and std of ``ln(chi2_nu / nu)`` with Greenhall's ``nu`` for ``alpha``, ``R`` the correlation of the
    estimates for ``alpha`` (:func:`oadev_correlation`), ``f`` the model-error term.
    """

    def __init__(self, curve: AllanCurve, alpha: np.ndarray):
        m = np.rint(curve.taus_s * curve.rate_hz).astype(int)
        offset, self.s = log_chi2_law(edf_for(alpha, m, curve.n_samples))
        self.y = np.log(curve.adev**2) - offset
        # C(f) = V diag(lam + f^2) V^T from one eigendecomposition of S R S: every f costs a matrix product
        corr = oadev_correlation(m, curve.n_samples, alpha)
        self.lam, self.vec = np.linalg.eigh(corr * np.outer(self.s, self.s))

    def whitener(self, f: float) -> np.ndarray:
        """``W`` with ``W^T W = C(f)^-1``: ``W r`` are independent unit-variance residuals."""
        return self.vec.T / np.sqrt(self.lam + f**2)[:, None]

    def terms(self, r: np.ndarray, f: float) -> tuple[float, float]:
        """``(nll, chi2)``: ``r^T C^-1 r + ln det C`` and ``r^T C^-1 r`` for residuals ``r`` (log AVAR)."""
        v = self.lam + f**2
        chi2 = float(np.sum((self.vec.T @ r) ** 2 / v))
        return chi2 + float(np.sum(np.log(v))), chi2

    def ml_model_error(self, r: np.ndarray) -> float:
        """The model-error term f maximising the likelihood of residuals ``r``."""
        lo, hi = math.log(MODEL_ERROR_MIN), math.log(10.0)
        u2 = (self.vec.T @ r) ** 2

        def nll(log_f):
            v = self.lam + math.exp(2.0 * log_f)
            return float(np.sum(u2 / v + np.log(v)))

        res = optimize.minimize_scalar(nll, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
        return math.exp(res.x) if res.fun < nll(lo) else MODEL_ERROR_MIN


def _score(curve: AllanCurve, avar: Callable[[np.ndarray], np.ndarray], model_error: float) -> tuple[float, float]:
    """``(nll, chi2)`` of a model Allan variance (function of tau) against a one-axis curve."""
    like = _LogLikelihood(curve, model_alpha(avar, curve.taus_s))
    return like.terms(like.y - np.log(avar(curve.taus_s)), model_error)


def _initial_guesses(model: str, curve: AllanCurve) -> list[np.ndarray]:
    t, a = curve.taus_s, curve.adev
    n0 = a[0] * math.sqrt(t[0])
    floor = max(float(np.min(a)), 1e-300)
    k0 = max(float(np.max(a * np.sqrt(3.0 / t))), 1e-300) * 0.1
    if model == "white":
        return [np.array([n0])]
    if model == "random_walk":
        return [np.array([n0, k]) for k in (k0, 10 * k0)]
    if model == "flicker":
        b0 = floor / math.sqrt(FLICKER_FACTOR)
        return [np.array([n0, b]) for b in (0.3 * b0, b0)]
    if model == "flicker_random_walk":
        b0 = floor / math.sqrt(FLICKER_FACTOR)
        return [np.array([n0, b, k]) for b in (0.3 * b0, b0) for k in (0.1 * k0, k0)]
    # gauss_markov: a start at every other octave correlation time, sigma from the excess over white noise
    excess = max(float(np.max(a**2 - n0**2 / t)), floor**2)
    return [np.array([n0, math.sqrt(2.0 * excess), tc]) for tc in t[::2]]


def _bounds(model: str, curve: AllanCurve) -> tuple[np.ndarray, np.ndarray]:
    """Bounds on the log parameters: amplitudes within a wide range of the curve's scale, T within the taus."""
    t, a = curve.taus_s, curve.adev
    scale = float(np.max(a) * math.sqrt(t[-1]))  # generous amplitude scale for all densities
    lo, hi = [], []
    for p in MODELS[model].params:
        if p == "tau_s":
            lo.append(math.log(t[0]))
            hi.append(math.log(100.0 * t[-1]))
        else:
            lo.append(math.log(scale * 1e-10))
            hi.append(math.log(scale * 1e4))
    return np.array(lo), np.array(hi)


def fit_noise_model(curve: AllanCurve, model: str) -> ModelFit:
    """Fit ``model`` (a key of MODELS) to a one-axis Allan curve by generalised least squares in log AVAR.

    The covariance of the points is ``S R S + f^2 I`` (see :class:`ModelFit`): the statistical errors with the
    correlation of neighbouring taus, both for the noise type the model has at each tau, plus a model-error
    term ``f`` fitted by maximum likelihood with the parameters.  On data the model describes, ``f`` goes to
    ~0 and the fit is a plain (correlated) chi-square; on real data ``f`` absorbs what no candidate model
    describes (e.g. a sensor's internal filter at the shortest taus), which would otherwise dominate the fit
    through the tiny statistical errors there.  Iteratively reweighted: generalised least squares for the
    parameters with the covariance of the previous iterate, then the maximum-likelihood ``f``, then the noise
    types of the new model curve.  Parameters are fitted as logarithms (positive, scale-free) from several
    starting points; the best likelihood wins.

    Returns
    -------
    ModelFit
    """
    if curve.adev.ndim != 1:
        raise ValueError("fit_noise_model takes a one-axis curve (AllanCurve.axis(i))")
    spec = MODELS[model]
    t = curve.taus_s
    lo, hi = _bounds(model, curve)

    def avar_of(theta):
        p = np.exp(theta)
        return lambda taus: spec.avar(taus, *p)

    def likelihood(theta):
        return _LogLikelihood(curve, model_alpha(avar_of(theta), t))

    best = (math.inf, None, None)
    for p0 in _initial_guesses(model, curve):
        theta, f = np.clip(np.log(p0), lo + 1e-9, hi - 1e-9), MODEL_ERROR_MIN
        like = likelihood(theta)
        prev = math.inf
        for _ in range(60):
            w, y = like.whitener(f), like.y
            theta = optimize.least_squares(lambda th: w @ (y - np.log(avar_of(th)(t))), theta, bounds=(lo, hi),
                                           method="trf", xtol=1e-8, ftol=1e-8, gtol=1e-8, max_nfev=500).x
            like = likelihood(theta)
            r = like.y - np.log(avar_of(theta)(t))
            f = like.ml_model_error(r)
            cur = like.terms(r, f)[0]
            if cur < best[0]:
                best = (cur, theta, f)
            if abs(prev - cur) < 1e-4:  # -2 ln L: 1e-4 is far below any decision threshold
                break
            prev = cur
    _, theta, f = best
    p = np.exp(theta)
    like = likelihood(theta)
    # Jacobian of ln AVAR_model with respect to the log parameters, by central differences
    jac = np.empty((len(t), len(theta)))
    for j in range(len(theta)):
        h = np.zeros_like(theta)
        h[j] = 1e-6
        jac[:, j] = (np.log(avar_of(theta + h)(t)) - np.log(avar_of(theta - h)(t))) / 2e-6
    wj = like.whitener(f) @ jac
    # a parameter the curve does not constrain (a term driven to ~0, e.g. K of white data) or pinned at a
    # bound has no Gaussian error: NaN (null in JSON); the model then reduces to a smaller one, which the BIC
    # prefers anyway.  The covariance of the others is the inverse of their Fisher block.
    norms = np.linalg.norm(wj, axis=0)
    free = (norms > 1e-6 * norms.max()) & (theta - lo > 1e-3) & (hi - theta > 1e-3)
    cov = np.full((len(theta), len(theta)), np.nan)
    if free.any():
        cov[np.ix_(free, free)] = np.linalg.pinv(wj[:, free].T @ wj[:, free])
    std = p * np.sqrt(np.clip(np.diag(cov), 0.0, None))
    nll, chi2 = like.terms(like.y - np.log(avar_of(theta)(t)), f)
    return ModelFit(model, {k: float(x) for k, x in zip(spec.params, p)},
                    {k: float(x) for k, x in zip(spec.params, std)}, cov, f, nll, chi2, len(t))


def fixed_white(curve: AllanCurve, density: float) -> ModelFit:
    """The white-noise model with a given (declared) density: only the model-error term is fitted."""
    like = _LogLikelihood(curve, np.zeros(curve.taus_s.size))
    r = like.y - np.log(avar_white(curve.taus_s, density))
    f = like.ml_model_error(r)
    nll_best, chi2 = like.terms(r, f)
    return ModelFit("white", {"white_density": float(density)}, {"white_density": 0.0}, np.zeros((1, 1)), f,
                    nll_best, chi2, len(curve.taus_s), fixed=True)


def relative_errors(pred_adev: np.ndarray, measured_adev: np.ndarray) -> tuple[float, float]:
    """``(max, rms)`` of ``|pred / measured - 1|`` over the tau points (fractions, not percent)."""
    e = np.abs(np.asarray(pred_adev) / np.asarray(measured_adev) - 1.0)
    return float(np.max(e)), float(np.sqrt(np.mean(e**2)))


# --- the audit -----------------------------------------------------------------------------------------------------

@dataclass
class AxisNoise:
    """Audit of one axis: fits on the whole series and on half A, checks against half B.

    ``base`` is the white model of the predictions: the declared density if one was given, else the density
    fitted on the short-tau part (:func:`short_tau_white`).  ``white`` is the white model fitted on the whole
    curve (the best white model: the conservative reference of the significance and held-out tests).
    ``extensions`` holds every extended model fitted on the whole series, ``best`` names the one with the
    lowest BIC; ``delta_bic = BIC(best) - BIC(white)``; ``lr_statistic`` is ``nll(white) - nll(best)``.
    ``*_err`` are ``(max, rms)`` of ``|pred / measured - 1|`` over the taus of the whole-series curve
    (``heldout_*``: predictions fitted on half A against the curve of half B; ``heldout_nll_*``: -2
    log-likelihood of half B's curve under the white and the extended fit of half A).
    """

    axis: int
    curve: AllanCurve
    base: ModelFit
    white: ModelFit
    extensions: dict[str, ModelFit]
    best: str
    delta_bic: float
    lr_statistic: float
    p_value: float
    base_err: tuple[float, float]
    extended_err: tuple[float, float]
    heldout_curve: AllanCurve
    heldout_base: ModelFit
    heldout_extended: ModelFit
    heldout_nll_base: float
    heldout_nll_extended: float
    heldout_base_err: tuple[float, float]
    heldout_extended_err: tuple[float, float]
    significant: bool
    predicts_heldout: bool

    @property
    def accepted(self) -> bool:
        return self.significant and self.predicts_heldout

    @property
    def extended(self) -> ModelFit:
        return self.extensions[self.best]

    @property
    def final(self) -> ModelFit:
        """The model the audit keeps for this axis: the extension if accepted, else the base."""
        return self.extended if self.accepted else self.base

    def base_adev(self, taus_s=None) -> np.ndarray:
        return self.base.adev(self.curve.taus_s if taus_s is None else taus_s)

    def extended_adev(self, taus_s=None) -> np.ndarray:
        return self.extended.adev(self.curve.taus_s if taus_s is None else taus_s)


@dataclass
class NoiseAuditResult:
    """Noise audit of one quantity (accel or gyro) of one sensor; ``finding`` is None when nothing is accepted."""

    sensor: str
    quantity: str
    rate_hz: float
    n_samples: int
    declared_white_density: float | None
    axes: list[AxisNoise]
    finding: dict | None = None
    bic_threshold: float = BIC_THRESHOLD
    taus: object = "octave"

    @property
    def accepted(self) -> bool:
        return self.finding is not None

    @property
    def curve(self) -> AllanCurve:
        return self.axes[0].curve if len(self.axes) == 1 else stack_curves([a.curve for a in self.axes])

    def predict(self, static_samples) -> list[dict]:
        """Check this audit's fits against another series of the same sensor (e.g. a second run).

        Returns, per axis, ``base_err``, ``extended_err`` and ``final_err`` (``(max, rms)`` of ``|pred / measured
        - 1|`` over the other series' taus) and ``nll_white``, ``nll_extended`` (-2 log-likelihood of the other
        curve under this audit's white and extended fits, model-error terms included).
        """
        other = allan_curve(static_samples, self.rate_hz, self.taus)
        out = []
        for a in self.axes:
            c = other.axis(a.axis)
            out.append({"base_err": relative_errors(a.base.adev(c.taus_s), c.adev),
                        "extended_err": relative_errors(a.extended.adev(c.taus_s), c.adev),
                        "final_err": relative_errors(a.final.adev(c.taus_s), c.adev),
                        "nll_white": a.white.score(c), "nll_extended": a.extended.score(c)})
        return out

    def summary(self) -> dict:
        """Per-axis figures as plain JSON-valid values (errors in percent)."""
        out = []
        for a in self.axes:
            out.append({
                "axis": a.axis, "best_extension": a.best, "accepted": a.accepted, "significant": a.significant,
                "predicts_heldout": a.predicts_heldout, "delta_bic": a.delta_bic, "p_value": a.p_value,
                "base": a.base.params, "extended": a.extended.params,
                "extended_std": {k: _nullable(v) for k, v in a.extended.std.items()},
                "model_error": {"white": a.white.model_error, "extended": a.extended.model_error},
                "base_error_pct": {"max": 100 * a.base_err[0], "rms": 100 * a.base_err[1]},
                "extended_error_pct": {"max": 100 * a.extended_err[0], "rms": 100 * a.extended_err[1]},
                "heldout_base_error_pct": {"max": 100 * a.heldout_base_err[0], "rms": 100 * a.heldout_base_err[1]},
                "heldout_extended_error_pct": {"max": 100 * a.heldout_extended_err[0],
                                               "rms": 100 * a.heldout_extended_err[1]},
                "tau_range_s": [float(a.curve.taus_s[0]), float(a.curve.taus_s[-1])],
            })
        return {"sensor": self.sensor, "quantity": self.quantity, "rate_hz": self.rate_hz,
                "n_samples": self.n_samples, "accepted": self.accepted, "axes": out, "finding": self.finding}


def short_tau_white(curve: AllanCurve, tau_max_s: float = SHORT_TAU_MAX_S) -> ModelFit:
    """White model with its density from the short-tau part of a one-axis curve (taus up to ``tau_max_s``,
    at least three points; IEEE 952 reads the angle/velocity random walk at tau = 1 s), then scored (its
    model-error term fitted) on the whole curve."""
    keep = max(int(np.sum(curve.taus_s <= tau_max_s)), 3)
    short = AllanCurve(curve.taus_s[:keep], curve.adev[:keep], curve.adev_err[:keep], curve.edf[:keep],
                       curve.alpha[:keep], curve.n_samples, curve.rate_hz)
    density = fit_noise_model(short, "white")
    fit = fixed_white(curve, density.params["white_density"])
    fit.std = dict(density.std)
    fit.fixed = False  # the density was fitted (on part of the curve): it counts as a parameter
    return fit


def _audit_axis(i: int, full: AllanCurve, half_a: AllanCurve, half_b: AllanCurve, declared: float | None,
                bic_threshold: float) -> AxisNoise:
    white = fit_noise_model(full, "white")
    base = short_tau_white(full) if declared is None else fixed_white(full, declared)
    extensions = {m: fit_noise_model(full, m) for m in EXTENSIONS}
    best = min(extensions, key=lambda m: extensions[m].bic)
    ext = extensions[best]
    delta_bic = ext.bic - white.bic
    lr = max(white.nll - ext.nll, 0.0)
    # likelihood-ratio p-value, nominal: the nested parameters sit on the boundary (K = 0) or are unidentified
    # under the null (T when sigma = 0), so Wilks' chi-square law is only a guide here; the decision uses BIC
    p_value = float(stats.chi2.sf(lr, ext.k - white.k))
    # held out: the same two models, fitted on half A, predict half B's curve
    ho_white = fit_noise_model(half_a, "white")
    ho_base = short_tau_white(half_a) if declared is None else fixed_white(half_a, declared)
    ho_ext = fit_noise_model(half_a, best)
    tb = half_b.taus_s
    ho_nll_base = ho_white.score(half_b)
    ho_nll_ext = ho_ext.score(half_b)
    ho_base_err = relative_errors(ho_base.adev(tb), half_b.adev)
    ho_ext_err = relative_errors(ho_ext.adev(tb), half_b.adev)
    # the decision uses the predictive likelihood of half B's curve (log space, noise-weighted, symmetric);
    # |pred / measured - 1| is reported but not used: it is bounded by 1 for an under-prediction and unbounded
    # for an over-prediction, so it favours a white model that falls far below a wandering bias
    predicts = ho_nll_ext < ho_nll_base
    t = full.taus_s
    return AxisNoise(i, full, base, white, extensions, best, float(delta_bic), float(lr), p_value,
                     relative_errors(base.adev(t), full.adev), relative_errors(ext.adev(t), full.adev),
                     half_b, ho_base, ho_ext, float(ho_nll_base), float(ho_nll_ext), ho_base_err, ho_ext_err,
                     bool(delta_bic < bic_threshold), bool(predicts))


def _pooled_rms(pairs: list[tuple[np.ndarray, np.ndarray]]) -> float:
    e = np.concatenate([p / m - 1.0 for p, m in pairs])
    return float(np.sqrt(np.mean(e**2)))


def _nullable(x) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


def _finding(axes: list[AxisNoise], sensor: str, quantity: str) -> dict:
    """The audit-contract finding for accepted axes (the others keep the white model, reported as such)."""
    est = {"model": [], "sigma": [], "tau_s": [], "random_walk": [], "bias_instability": [], "white_density": []}
    std = {k: [] for k in est if k != "model"}
    for a in axes:
        f = a.final
        p, s = f.params, f.std
        est["model"].append(f.model)
        est["white_density"].append(p["white_density"])
        std["white_density"].append(s["white_density"])
        gm = f.model == "gauss_markov"
        est["sigma"].append(p["sigma"] if gm else None)
        std["sigma"].append(s["sigma"] if gm else None)
        est["tau_s"].append(p["tau_s"] if gm else None)
        std["tau_s"].append(s["tau_s"] if gm else None)
        if gm:  # short-tau random-walk equivalent, K^2 = 2 sigma^2 / T (delta method for its std)
            k = p["sigma"] * math.sqrt(2.0 / p["tau_s"])
            jac = np.array([0.0, 1.0, -0.5]) * k  # d k / d log(params)
            est["random_walk"].append(k)
            std["random_walk"].append(float(math.sqrt(max(jac @ f.cov_log @ jac, 0.0))))
        else:
            est["random_walk"].append(p.get("random_walk"))
            std["random_walk"].append(s.get("random_walk"))
        est["bias_instability"].append(p.get("bias_instability"))
        std["bias_instability"].append(s.get("bias_instability"))
    accepted = [a for a in axes if a.accepted]
    lr = sum(a.lr_statistic for a in accepted)
    ddof = sum(a.extended.k - a.white.k for a in accepted)
    t = axes[0].curve.taus_s
    tb = axes[0].heldout_curve.taus_s
    return {
        "effect": "bias_instability", "sensor": sensor, "quantity": quantity, "target": f"{sensor}/{quantity}",
        "meaning": "bias wanders (random walk / Gauss-Markov): white-noise model too optimistic",
        "estimate": {k: [_nullable(v) if not isinstance(v, str) else v for v in vals] for k, vals in est.items()},
        "std": {k: [_nullable(v) for v in vals] for k, vals in std.items()},
        "evidence": {"diagnostic": "Allan deviation vs white-noise prediction", "statistic": float(lr),
                     "p_value": float(stats.chi2.sf(lr, ddof)), "statistic_kind": "likelihood ratio, -2 ln",
                     "axes": [a.axis for a in accepted]},
        "gain": {
            "rms_before": _pooled_rms([(a.base.adev(t), a.curve.adev) for a in axes]),
            "rms_after": _pooled_rms([(a.final.adev(t), a.curve.adev) for a in axes]),
            "delta_bic": float(sum(a.delta_bic for a in accepted)),
            "heldout_rms_before": _pooled_rms([(a.heldout_base.adev(tb), a.heldout_curve.adev) for a in axes]),
            "heldout_rms_after": _pooled_rms([((a.heldout_extended if a.accepted else a.heldout_base).adev(tb),
                                               a.heldout_curve.adev) for a in axes]),
            "metric": "RMS over axes and octave taus of |predicted / measured Allan deviation - 1|",
        },
    }


def noise_audit(static_samples, rate_hz: float, quantity: str, declared_white_density=None, sensor: str = "imu0",
                taus="octave", bic_threshold: float = BIC_THRESHOLD) -> NoiseAuditResult:
    """Audit the noise model of static samples: does white noise alone explain the Allan deviation?

    Parameters
    ----------
    static_samples : array_like (N, 3)
        Accelerometer (m s^-2) or gyro (rad s^-1) samples of a sensor at rest, uniformly sampled; constant
        offsets (bias, gravity, earth rate) do not affect the Allan deviation.
    rate_hz : float
        Sample rate, Hz.
    quantity : {"accel", "gyro"}
        Which sensor the samples come from (named in the finding).
    declared_white_density : float or array_like (3,), optional
        Declared white-noise density (Kalibr ``accelerometer_noise_density`` / ``gyroscope_noise_density``):
        the base prediction then uses it.  The significance test always compares the extension with the
        *fitted* white model, so a mis-declared level is never reported as bias instability.
    sensor : str
        Sensor name for the finding.
    taus : {"octave", "decade"} or array_like
        Averaging times (see :func:`allan_curve`); octave spacing is the one the statistics assume.
    bic_threshold : float
        An extension must lower the BIC by more than this (default -10: "very strong" evidence on the Kass and
        Raftery scale, posterior odds above 150:1 for equal priors, and a margin for the approximate
        correlation model and for parameters on a boundary or unidentified under the null).

    Returns
    -------
    NoiseAuditResult
        Per axis: fits (base, extensions), errors of the predicted Allan curves in percent, held-out check.
        ``finding`` is the audit-contract dict with effect ``bias_instability`` when at least one axis accepts
        an extension, else None.  In it, ``gain.rms_*`` are RMS relative errors ``|pred / measured - 1|`` of the
        predicted Allan deviation over the axes and octave taus (``heldout_*``: fitted on the first half,
        measured on the second).  ``estimate`` holds, per axis, ``model`` (``white`` if not accepted,
        ``random_walk``, ``gauss_markov``, ``flicker`` or ``flicker_random_walk``), ``sigma`` and ``tau_s``
        (Gauss-Markov std and correlation time; null for the other models, e.g. a pure random walk is the
        limit ``tau_s -> inf``), ``random_walk`` (K, Kalibr's ``*_random_walk``; for Gauss-Markov its short-tau
        equivalent ``sigma sqrt(2 / tau_s)``), ``bias_instability`` (B) and ``white_density`` (N).
    """
    if quantity not in QUANTITIES:
        raise ValueError(f"quantity must be one of {sorted(QUANTITIES)}, got {quantity!r}")
    x = np.asarray(static_samples, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"static_samples must be (N, 3), got shape {x.shape}")
    n = x.shape[0]
    if n < 2000:
        raise ValueError(f"need at least 2000 static samples for an Allan analysis, got {n}")
    declared = None if declared_white_density is None else np.broadcast_to(
        np.asarray(declared_white_density, dtype=float), (3,))
    full = allan_curve(x, rate_hz, taus)
    half_a = allan_curve(x[: n // 2], rate_hz, taus)
    half_b = allan_curve(x[n // 2:], rate_hz, taus)
    axes = [_audit_axis(i, full.axis(i), half_a.axis(i), half_b.axis(i),
                        None if declared is None else float(declared[i]), bic_threshold) for i in range(3)]
    result = NoiseAuditResult(sensor, quantity, float(rate_hz), n,
                              None if declared is None else [float(d) for d in declared], axes,
                              bic_threshold=bic_threshold, taus=taus)
    if any(a.accepted for a in axes):
        result.finding = _finding(axes, sensor, quantity)
    for a in axes:
        log.info("%s %s axis %d: best %s, delta BIC %.1f, held-out %s, accepted %s", sensor, quantity, a.axis,
                 a.best, a.delta_bic, a.predicts_heldout, a.accepted)
    return result


# --- noise figures for Kalibr's imu.yaml ----------------------------------------------------------------------------

@dataclass
class KalibrNoise:
    """White-noise density N and rate random walk K per axis, read from the Allan analysis, as Kalibr wants them.

    ``white_density``: N of the white (slope -1/2) line, ``sigma(tau) = N / sqrt(tau)``, i.e. its value at
    tau = 1 s.  ``random_walk``: K of the +1/2 line, ``sigma(tau) = K sqrt(tau / 3)`` (its value at tau = 3 s),
    where :func:`noise_audit` accepts a model with a random walk on that axis (for Gauss-Markov, the short-tau
    equivalent ``sigma sqrt(2 / T)``, only when T exceeds the longest tau); NaN where the curve shows none.  ``random_walk_bound``: the largest K the
    curve allows, ``min over tau of sigma_hi(tau) sqrt(3 / tau)`` with ``sigma_hi`` the upper end of the
    one-sigma (68 %) confidence interval: a +1/2 line above it would lie above the measured curve.  ``*_std``:
    1-sigma of the fits (NaN where not available).  Units: those of the samples (m s^-2 or rad s^-1) per
    sqrt(Hz) for N, per s per sqrt(Hz) for K.
    """

    quantity: str
    white_density: np.ndarray
    white_density_std: np.ndarray
    random_walk: np.ndarray
    random_walk_std: np.ndarray
    random_walk_bound: np.ndarray
    duration_s: float
    tau_max_s: float

    @property
    def random_walk_seen(self) -> bool:
        return bool(np.any(np.isfinite(self.random_walk)))


def kalibr_noise(static_samples, rate_hz: float, quantity: str, sensor: str = "imu0") -> KalibrNoise:
    """Kalibr's noise figures (per axis) of static samples: :func:`noise_audit` where the series is long enough
    for it (2000 samples), else the white line alone (:func:`short_tau_white`, no random walk)."""
    x = np.asarray(static_samples, dtype=float)
    nan3 = np.full(3, np.nan)
    curve = allan_curve(x, rate_hz)
    if len(x) >= 2000:
        estimate = _finding(noise_audit(x, rate_hz, quantity, sensor=sensor).axes, sensor, quantity)
        est, std = estimate["estimate"], estimate["std"]
        as_array = lambda values: np.array([np.nan if v is None else v for v in values], dtype=float)  # noqa: E731
        white, white_std = as_array(est["white_density"]), as_array(std["white_density"])
        walk, walk_std = as_array(est["random_walk"]), as_array(std["random_walk"])
        # a Gauss-Markov bias is a random walk only over taus shorter than its correlation time: one that
        # decorrelates within the curve (an internal filter at 10 ms, a settling transient) is none
        short_gm = (np.array(est["model"]) == "gauss_markov") & ~(as_array(est["tau_s"]) >= curve.taus_s[-1])
        walk[short_gm], walk_std[short_gm] = np.nan, np.nan
    else:
        fits = [short_tau_white(curve.axis(i)) for i in range(3)]
        white = np.array([f.params["white_density"] for f in fits])
        white_std = np.array([f.std["white_density"] for f in fits])
        walk, walk_std = nan3, nan3.copy()
    _, adev_hi = curve.confidence_interval()
    bound = np.min(adev_hi * np.sqrt(3.0 / curve.taus_s)[:, None], axis=0)
    return KalibrNoise(quantity, white, white_std, walk, walk_std, bound, len(x) / float(rate_hz),
                       float(curve.taus_s[-1]))
