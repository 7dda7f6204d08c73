"""The generic term library: what a residual may depend on when no catalog effect explains it.

Real instruments fail in ways nobody listed.  After the catalog, the audit offers every residual family's
quantities a **term**: a correction ``sum_i c_i phi_i(x)`` of a plain form in one coordinate ``x`` (the
*driver*: time, an auxiliary channel, a state quantity such as the specific force or the range), with the
coefficients ``c`` estimated inside the graph like any catalog effect.  The forms are one table,
:data:`FORMS`; a newcomer adds a form there and nothing else changes.

Every basis is built on the driver scaled to about [-1, 1], ``u = (x - x0) / h`` (``x0`` the middle of the
recording's range, ``h`` its half-width), so the columns are well conditioned whatever the unit; the
estimates are reported back in the driver's own unit (coefficients of ``(x - x0)^k``, amplitude and phase of a
harmonic, the size of a step) together with the term's peak-to-peak over the range seen.  ``x0`` and ``h`` are
fixed once per recording, so training and held-out folds use the same basis.

Forms (``form`` in the audit JSON):

==========  ==========================================================  =========================
form        basis of ``u`` (and its meaning)                              applies to
==========  ==========================================================  =========================
poly1       ``u``                     linear in the driver                  every coordinate
poly2       ``u, u^2``                quadratic                             every coordinate
poly3       ``u, u^2, u^3``           cubic (a warm-up, a saturation)       every coordinate
step        ``H(x - x_s)``            a change point at ``x_s``             time and monotone drivers
harmonic    ``sin k x, cos k x``      k-th harmonic of an angle (k = 1, 2); angles (k span >= 0.5 rad);
            ``sin 2 pi f t, cos ..``  of time at the periodogram's peak     time at the residual's
                                                                          strongest f
product     ``(x / h) v``             a state driver times a centred        state x (time, channels)
                                      time/channel driver (a drifting gain)
==========  ==========================================================  =========================

A step's locations are candidates of their own; neighbouring ones are nearly the same test, which the effective
number of tests accounts for (:func:`effective_number`).

References
----------
J. Li, L. Ji, "Adjusting multiple testing in multilocus analyses using the eigenvalues of a correlation
matrix", Heredity 95 (2005) 221-227 (the effective number of correlated tests).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import stats

STEP_LOCATIONS = 25  # change points tried at most: between consecutive rows of the driver's inner half (each side
# keeps a quarter of the rows: a step near an end would fit a few rows' noise, not a change)
ANGLE_HARMONICS = (1, 2)
MIN_HARMONIC_SWEEP_RAD = 0.5  # a k-th harmonic is offered where the angle sweeps k * span >= 0.5 rad: over less,
# sin and cos of k x are a parabola to within (k span / 2)^3 / 6 < 0.3 % of their amplitude, and the polynomials
# say the same under the plainer name (measured: a 3 % roll-from-pitch coupling of an inclinometer, pitch steered
# over 0.07 rad, was named a harmonic in pitch on 4 of 13 runs instead of poly1).  The ship's heading sweeps 0.57 rad
# and more on the turning voyages: its harmonics stay
MIN_DISTINCT = 4  # a coordinate with fewer distinct values carries no shape to fit
NOISE_MULTIPLE = 3.0  # a coordinate whose spread is below this many times its own noise is skipped (measured:
# a laser-tracker target at rest, its speed's sd 0.4-0.7 mm/s against a keyframe velocity noise of 1.1-1.4 mm/s,
# named a distance term in speed at p ~ 1e-8 on 2 of 40 yawed runs; a moving one, 50-60 mm/s against 1.2 mm/s)


@dataclass(frozen=True)
class Coordinate:
    """A driver offered to the term library: its values where the residuals are, its unit and kind."""

    name: str
    values: np.ndarray
    unit: str = ""
    kind: str = "state"  # "time", "channel" (an auxiliary column), "state" (a quantity of the system), "angle",
    # "level" (a state offered in polynomials only: its products with a channel are a drifting gain the base has)
    solo: bool = True  # False: offered only as the second factor of products (its own terms live elsewhere)
    noise: float = 0.0  # the noise of one of its values (its unit), where the adapter knows it: a coordinate that
    # varies by less than NOISE_MULTIPLE times that is its own noise, not a driver

    @property
    def usable(self) -> str | None:
        """None if the coordinate can drive a term, else why not (one line, for the audit's notes)."""
        v = np.asarray(self.values, dtype=float)
        if v.size == 0 or not np.all(np.isfinite(v)):
            return f"{self.name}: not finite everywhere"
        if np.unique(np.round(v, 12)).size < MIN_DISTINCT:
            return f"{self.name}: constant (fewer than {MIN_DISTINCT} distinct values)"
        if self.noise > 0.0 and np.std(v) < NOISE_MULTIPLE * self.noise:
            unit = f" {self.unit}" if self.unit else ""
            return f"{self.name}: varies within its own noise (sd {np.std(v):.2g} against {self.noise:.2g}{unit})"
        return None


@dataclass(frozen=True)
class Scale:
    """``u = (x - x0) / h`` for one driver, fixed for the recording."""

    x0: float
    h: float

    @classmethod
    def of(cls, values) -> Scale:
        v = np.asarray(values, dtype=float)
        lo, hi = float(np.min(v)), float(np.max(v))
        return cls(0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-300))

    def __call__(self, x) -> np.ndarray:
        return (np.asarray(x, dtype=float) - self.x0) / self.h


@dataclass(frozen=True)
class Form:
    """One row of the library: a named family of basis functions of one (or two) drivers."""

    name: str
    words: str  # "{quantity} {words} {driver}" reads as the finding's meaning, e.g. "quadratic in"
    applies: Callable[[Coordinate], bool]
    basis: Callable[[np.ndarray, tuple], np.ndarray]  # (u or raw x, params) -> (n, q) columns
    scaled: bool = True  # the basis takes u (True) or the raw driver (harmonics of angles, steps)


def _poly(degree: int):
    return lambda u, params: np.stack([u**k for k in range(1, degree + 1)], axis=1)


def _step(x, params):
    return (np.asarray(x) >= params[0]).astype(float)[:, None]


def _harmonic(x, params):
    """``params = (k,)``: k-th harmonic of an angle (rad); ``params = (f_hz, "time")``: frequency f of time."""
    arg = params[0] * np.asarray(x) if len(params) == 1 else 2.0 * np.pi * params[0] * np.asarray(x)
    return np.stack([np.sin(arg), np.cos(arg)], axis=1)


FORMS: dict[str, Form] = {f.name: f for f in (
    Form("poly1", "linear in", lambda c: True, _poly(1)),
    Form("poly2", "quadratic in", lambda c: True, _poly(2)),
    Form("poly3", "cubic in", lambda c: True, _poly(3)),
    Form("step", "with a step in", lambda c: c.kind == "time" or _monotone(c.values), _step, scaled=False),
    Form("harmonic", "harmonic in", lambda c: c.kind in ("angle", "time"), _harmonic, scaled=False),
    Form("product", "linear in the product", lambda c: True, lambda uv, params: uv[:, None]),
)}


def _monotone(values) -> bool:
    d = np.diff(np.asarray(values, dtype=float))
    return bool(np.all(d >= 0) or np.all(d <= 0))


@dataclass(frozen=True)
class Term:
    """A generic correction: form, driver(s), fixed scaling and the form's chosen parameters."""

    form: str
    driver: str
    scale: Scale
    params: tuple = ()
    second: str | None = None  # the other driver of a product
    second_scale: Scale | None = None

    @property
    def label(self) -> str:
        drivers = f"{self.driver}*{self.second}" if self.second else self.driver
        extra = f"@{self.params[0]:.6g}" if self.form in ("step", "harmonic") and self.params else ""
        return f"{self.form}({drivers}){extra}"

    def columns(self, coordinates: dict[str, np.ndarray]) -> np.ndarray:
        """Basis columns (n, q) at the given coordinate values."""
        form = FORMS[self.form]
        x = np.asarray(coordinates[self.driver], dtype=float)
        if self.form == "product":
            return form.basis(self.scale(x) * self.second_scale(np.asarray(coordinates[self.second], float)), ())
        return form.basis(self.scale(x) if form.scaled else x, self.params)

    @property
    def searched(self) -> float:
        """The search the term's parameter was picked by: for the harmonic of time at the periodogram's peak,
        Baluev's ``W = f_max T_eff`` of the band searched (about n/2 for even sampling); 0 for every other term."""
        return float(self.params[2]) if self.form == "harmonic" and len(self.params) > 2 else 0.0

    def search_corrected(self, p_value: float) -> float:
        """The false-alarm probability of the strongest peak of a band searched, given its single-frequency p-value
        (Baluev 2008, large-n form): ``1 - (1 - p) exp(-tau)``, ``tau = W p sqrt(ln 1/p)``.  On white noise
        the peak passes a single-frequency test at 1e-4 about n/2 x 3 times more often than 1e-4 (measured in
        tests/test_audit_open_world.py); the correction gives the rate it claims."""
        p = float(min(max(p_value, 0.0), 1.0))
        if self.searched <= 0.0 or p <= 0.0 or p >= 1.0:
            return p
        tau = self.searched * p * np.sqrt(np.log(1.0 / p))
        return float(-np.expm1(np.log1p(-p) - tau))

    def dof(self) -> int:
        return int(self.columns({self.driver: np.array([0.0, 1.0]),
                                 **({self.second: np.array([0.0, 1.0])} if self.second else {})}).shape[1])

    def meaning(self, quantity: str, driver_unit: str = "", span=None) -> str:
        unit = f" [{driver_unit}]" if driver_unit else ""
        drivers = f"{self.driver} x {self.second}" if self.second else self.driver
        where = ""
        if self.form == "step":
            where = f" at {self.params[0]:.4g}{(' ' + driver_unit) if driver_unit else ''}"
        elif self.form == "harmonic":
            where = (f" (order {self.params[0]:g})" if len(self.params) == 1
                     else f" (frequency {self.params[0]:.4g} Hz)")
        return f"{quantity} {FORMS[self.form].words} {drivers}{unit}{where}"


# --- candidate terms of one coordinate set --------------------------------------------------------------------

class TermKeys:
    """The graph keys of the terms an adapter fits: one per basis column, ``<symbol><n>`` numbered in the order the
    terms are first asked for (``symbol`` a letter the system's own graph does not use)."""

    def __init__(self, symbol: str = "u"):
        self.symbol, self._keys = symbol, {}

    def __call__(self, term: Term) -> list[int]:
        import gtsam
        if term not in self._keys:
            start = sum(len(k) for k in self._keys.values())
            self._keys[term] = [gtsam.symbol(self.symbol, start + j) for j in range(term.dof())]
        return self._keys[term]


def terms_for(coordinates: list[Coordinate], residual_for_frequency: np.ndarray | None = None,
              time: np.ndarray | None = None, products: bool = True) -> list[Term]:
    """Every term the library offers for these drivers.

    ``residual_for_frequency`` (time-ordered like ``time``) picks the harmonic-in-time frequency: the peak of its
    Lomb-Scargle periodogram.  Products pair each state or angle driver with each time/channel driver (a gain that
    drifts with temperature is ``f_x`` times ``temperature``).
    """
    out = []
    for c in (c for c in coordinates if c.solo):
        scale = Scale.of(c.values)
        for name in ("poly1", "poly2", "poly3"):
            out.append(Term(name, c.name, scale))
        if FORMS["step"].applies(c):
            out += [Term("step", c.name, scale, (x,)) for x in step_locations(c.values)]
        if c.kind == "angle":
            span = float(np.ptp(c.values))
            out += [Term("harmonic", c.name, scale, (float(k),)) for k in ANGLE_HARMONICS
                    if k * span >= MIN_HARMONIC_SWEEP_RAD]
        elif c.kind == "time" and residual_for_frequency is not None and time is not None:
            peak = strongest_frequency(time, residual_for_frequency)
            if peak is not None:
                out.append(Term("harmonic", c.name, scale, (peak[0], "time", peak[1])))
    if products:
        states = [c for c in coordinates if c.kind in ("state", "angle") and c.solo]
        others = [c for c in coordinates if c.kind in ("time", "channel")]
        # a state driver enters by its own value (a gain acts on x, not on x minus its mid-range: a scale that
        # drifts with temperature is x (T - T0)); the time/channel driver is centred
        out += [Term("product", a.name, Scale(0.0, max(float(np.max(np.abs(a.values))), 1e-300)), (), b.name,
                     Scale.of(b.values)) for a in states for b in others]
    return out


def step_locations(values) -> list[float]:
    """Change points between consecutive distinct values of the driver inside its 25 %..75 % quantiles (at most
    ``STEP_LOCATIONS``, evenly chosen): a step can sit at any row boundary there, not only on a coarse grid."""
    v = np.unique(np.asarray(values, dtype=float))
    lo, hi = np.quantile(values, [0.25, 0.75])
    mids = 0.5 * (v[1:] + v[:-1])
    mids = mids[(mids >= lo) & (mids <= hi)]
    if mids.size > STEP_LOCATIONS:
        mids = mids[np.round(np.linspace(0, mids.size - 1, STEP_LOCATIONS)).astype(int)]
    return [float(x) for x in mids]


def strongest_frequency(t, x) -> tuple[float, float] | None:
    """Frequency (1/unit of t) of the strongest periodic component of x (Lomb-Scargle) and the band searched as
    Baluev's ``W = f_max T_eff`` (``T_eff = sqrt(4 pi var t)``, ``f_max`` the pseudo-Nyquist of
    :func:`~selfcal.audit.diagnostics.dominant_period`); None if undefined."""
    from selfcal.audit.diagnostics import dominant_period
    t, x = np.asarray(t, dtype=float), np.asarray(x, dtype=float)
    if x.ndim == 2:
        x = x[:, int(np.argmax(np.var(x, axis=0)))]
    period, _ = dominant_period(t, x)
    if not np.isfinite(period) or period <= 0:
        return None
    spacing = np.diff(np.sort(t))
    f_max = 0.5 / float(np.median(spacing[spacing > 0]))
    return float(1.0 / period), f_max * float(np.sqrt(4.0 * np.pi * np.var(t)))


def effective_number(columns: list[np.ndarray]) -> float:
    """Effective number of independent tests among candidates (Li & Ji 2005) from their first basis columns.

    ``M_eff = sum_i f(|lambda_i|)``, ``f(x) = I(x >= 1) + (x - floor(x))``, over the eigenvalues of the
    correlation matrix of the columns: identical candidates count once, unrelated ones once each.
    """
    if not columns:
        return 0.0
    X = np.column_stack([c - c.mean() for c in columns])
    norms = np.linalg.norm(X, axis=0)
    X = X[:, norms > 0] / norms[norms > 0]
    if X.shape[1] == 0:
        return 0.0
    lam = np.abs(np.linalg.eigvalsh(X.T @ X))
    return float(np.sum((lam >= 1).astype(float) + (lam - np.floor(lam))))


def residual_score(whitened: np.ndarray, columns: np.ndarray) -> tuple[float, int, int]:
    """F statistic of regressing whitened residuals (n,) on centred columns (n, q): (F, q, n - q - 1).

    On the residuals of a fitted model this is a lower bound of the score test on the whole graph (the model's
    own parameters could only absorb part of the term, never add to it), so it never overstates evidence.
    """
    y = np.asarray(whitened, dtype=float)
    X = np.asarray(columns, dtype=float)
    X = X - X.mean(axis=0)
    ok = np.isfinite(y) & np.all(np.isfinite(X), axis=1)
    y, X = y[ok] - y[ok].mean(), X[ok]
    n = y.size
    rank = np.linalg.matrix_rank(X) if X.size else 0
    if rank == 0 or n - rank - 1 <= 0:
        return 0.0, max(rank, 1), max(n - rank - 1, 1)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    explained = float(np.sum((X @ coef) ** 2))
    rss = float(y @ y) - explained
    dof = n - rank - 1
    return explained / rank / max(rss / dof, 1e-300), int(rank), int(dof)


def f_pvalue(f_stat: float, dof: int, dof_den: int) -> float:
    return float(stats.f.sf(f_stat, dof, dof_den))


# --- estimates in the driver's own units ------------------------------------------------------------------------

def describe(term: Term, coefficients: np.ndarray, covariance: np.ndarray, coordinates: dict[str, np.ndarray],
             unit: str = "", driver_unit: str = "") -> tuple[dict, dict]:
    """A fitted term's estimate and 1-sigma in the contract's style, in the driver's own units.

    Parameters
    ----------
    coefficients : (q, k) array
        Coefficients of the q basis columns for each of the k residual components (axes).
    covariance : (q k, q k) array
        Their joint covariance, ordered column by column (column i's k components together).
    coordinates : dict
        The driver values seen (name -> array): the term's range and peak-to-peak come from them.

    Returns
    -------
    (estimate, std)
        Keys by form: ``coefficients`` of ``(x - x0)^j`` with ``x0`` and the powers (poly), ``step`` and its
        location ``at`` (step), ``amplitude`` and ``phase_rad`` (harmonic, ``A sin(arg + phase)``),
        ``coefficient`` of ``(x - x0)(y - y0)`` (product); always ``peak_to_peak`` over the values seen, the
        driver's ``range`` and the ``unit`` of the residual.
    """
    C = np.atleast_2d(np.asarray(coefficients, dtype=float))
    q, k = C.shape
    P = np.asarray(covariance, dtype=float).reshape(q * k, q * k)
    sigma = np.sqrt(np.clip(np.diag(P), 0.0, None)).reshape(q, k)
    x = np.asarray(coordinates[term.driver], dtype=float)
    estimate: dict = {"unit": unit, "range": [float(x.min()), float(x.max())]}
    std: dict = {}
    if term.form in ("poly1", "poly2", "poly3"):
        powers = np.arange(1, q + 1)
        factor = term.scale.h ** powers.astype(float)
        estimate.update(coefficients=(C / factor[:, None]).tolist(), x0=term.scale.x0, powers=powers.tolist(),
                        coefficient_unit=[f"{unit} per {driver_unit or 'unit'}^{j}" for j in powers])
        std["coefficients"] = (sigma / factor[:, None]).tolist()
    elif term.form == "step":
        estimate.update(step=C[0].tolist(), at=float(term.params[0]))
        std["step"] = sigma[0].tolist()
    elif term.form == "harmonic":
        a, b = C[0], C[1]
        amplitude = np.hypot(a, b)
        safe = np.where(amplitude > 0, amplitude, 1.0)
        # d A / d(a, b) = (a, b) / A;  d phase / d(a, b) = (-b, a) / A^2  (A sin(arg + phase) = a sin + b cos)
        var_a, var_b = sigma[0] ** 2, sigma[1] ** 2
        cov_ab = np.array([P[j, k + j] for j in range(k)])
        amp_sigma = np.sqrt(np.clip((a**2 * var_a + b**2 * var_b + 2 * a * b * cov_ab) / safe**2, 0, None))
        phase_sigma = np.sqrt(np.clip((b**2 * var_a + a**2 * var_b - 2 * a * b * cov_ab) / safe**4, 0, None))
        estimate.update(amplitude=amplitude.tolist(), phase_rad=np.arctan2(b, a).tolist(),
                        **({"order": float(term.params[0])} if len(term.params) == 1 else
                           {"frequency_hz": float(term.params[0])}))
        std.update(amplitude=amp_sigma.tolist(), phase_rad=phase_sigma.tolist())
    elif term.form == "product":
        factor = term.scale.h * term.second_scale.h
        estimate.update(coefficient=(C[0] / factor).tolist(), x0=[term.scale.x0, term.second_scale.x0],
                        coefficient_unit=f"{unit} per ({driver_unit or 'unit'} x unit of {term.second})")
        std["coefficient"] = (sigma[0] / factor).tolist()
    ptp, ptp_sigma = _peak_to_peak(term, C, P, coordinates)
    estimate["peak_to_peak"], std["peak_to_peak"] = ptp.tolist(), ptp_sigma.tolist()
    return estimate, std


def _peak_to_peak(term: Term, C: np.ndarray, P: np.ndarray, coordinates: dict) -> tuple[np.ndarray, np.ndarray]:
    """Per component: max - min of the fitted term over the values seen, and its 1-sigma (delta method at the
    extreme points: ``g = phi(x_max) - phi(x_min)``, ``sigma^2 = g^T P_j g``)."""
    B = term.columns(coordinates)  # (n, q)
    values = B @ C  # (n, k)
    q, k = C.shape
    ptp, sigma = np.zeros(k), np.zeros(k)
    for j in range(k):
        hi, lo = int(np.argmax(values[:, j])), int(np.argmin(values[:, j]))
        g = B[hi] - B[lo]
        idx = np.arange(q) * k + j
        ptp[j] = values[hi, j] - values[lo, j]
        sigma[j] = float(np.sqrt(max(g @ P[np.ix_(idx, idx)] @ g, 0.0)))
    return ptp, sigma
