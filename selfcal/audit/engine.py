"""The audit engine: find what a fitted model gets wrong, name the cause, extend the model, measure the gain.

Any system plugs in through :class:`AuditSystem`: it fits a factor graph for a set of effects (on all data or
on the training half of a fold), returns whitened residual families with their coordinates, and offers a
catalog of candidate effects.  The engine is the same for every system:

1. Evidence for each candidate is a score (Lagrange-multiplier) test on the linearised graph: the drop in
   whitened residual sum of squares that one Gauss–Newton step with the candidate's extra variables would
   give, as an F statistic against the residual variance.  It needs no refit, so every candidate is ranked.
2. Candidates significant at ``alpha / m`` (Bonferroni over the m candidates still open) are refitted in
   order of evidence; one is accepted only if it lowers the BIC AND the held-out residual (cross-validated
   over contiguous blocks in time: all families whitened - the whole held-out graph where the adapter solves
   one - and its own target family not worse by more than the sampling sigma of its paired held-out change), so an
   effect must predict data it was not fitted to.
3. Repeat until nothing significant is left.  No finding is a valid answer.
4. When another candidate explains the data about as well as the accepted one (BIC within 6, "strong
   evidence" on Kass & Raftery's scale) and loses its own evidence once the accepted one is in, the finding
   records the ambiguity instead of hiding it.

After the catalog, the **generic term library** (:mod:`selfcal.audit.terms`) is searched with the same
machinery, for systems whose adapter offers drivers (``term_coordinates``): a term is a correction of a plain
form (polynomial, step, harmonic, product) in one coordinate, fitted inside the graph; its finding has
``effect: "unlisted"`` with the ``driver`` and ``form`` that describe it.  Multiple testing is corrected over
the effective number of library candidates (Li & Ji 2005), since nested and neighbouring terms are correlated.

No false attribution: a catalog effect is accepted only if its estimate is physically plausible (the adapter's
``plausible``) and no generic term on the same residual explains it better held-out while encompassing it
(significant on top of the catalog effect, with the catalog effect no longer significant on top of the term).
Every candidate that passed the significance test but was not accepted is kept in ``rejected`` with the reason
(``bic``, ``heldout``, ``implausible``, ``outdone``), and the final model's residuals get a verdict per family in
``remaining``: whiteness (Ljung-Box) and the strongest term left, so "no finding" is never said where the data
held evidence.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from collections.abc import Callable
from typing import Protocol

import gtsam
import numpy as np
from scipy import linalg, special, stats

from selfcal.audit import terms as library
from selfcal.audit.terms import Coordinate, Term
from selfcal.core.progress import quiet
from selfcal.core.stats import correlation_inflation
from selfcal.core.solve import DegenerateDataError, dense_jacobian, normal_equations

log = logging.getLogger(__name__)

FAMILY_ALPHA = 1e-3  # family-wise false-finding probability per search step: a false finding sends a user
# recalibrating for nothing, so it is kept rare (about 2 % of 20 null recordings may show one)
AMBIGUITY_BIC = 6.0
# ... or, where the rival has more parameters than BIC lets pass, its fit is within this whitened chi-square of the
# accepted one (the data prefer the accepted by under ~2.5 sigma): a 3 cm prism height error and the 1 mrad
# inclinometer pitch bias it resembles (seen from ~30 m, both tilt the camera's beam) fit 1.3 apart in
# chi-square on noise-free data and correlate 0.995 in a joint fit, one parameter apart (BIC 8.6 for that alone)
AMBIGUITY_CHI2 = 6.0
# An effect no catalog predicts needs stronger evidence than one physics expects: the library searches many
# shapes after the fact, and what the models leave at the noise level (a static interval's last transient, a
# pose's micro-motion) makes its many tests fail more often than the F distribution says.  Measured on 40 null
# multi-position recordings: about 10x too many per-test p-values below 1e-3.  So the library's family-wise
# level is 1e-5 (about 4.4 sigma), and its false-finding rate is measured in benchmarks/audit_recall.py.
LIBRARY_ALPHA = 1e-5
LIBRARY_ATTEMPTS = 3  # significant library terms refitted per step, strongest evidence first
TIE_ATTEMPTS = 2  # library terms tied in evidence with the first that passes, refitted too (best held-out taken)
RESCORED = 3  # library terms per step scored again with the correlation inflation of the model that holds them
TARGET_WORSE_SIGMAS = 1.0  # a candidate is refused when its own target family's held-out whitened RSS rises by
# more than one sampling sigma of the paired change: a veto against an effect that pays elsewhere (the IMU chain)
# while its target gets worse, not a second evidence test (the score test and the whole held-out graph are that).
# "Not worse at all" (physical RMS) refused real effects at the sampling noise: a 24 ms tracker clock offset at
# F = 42 (held-out graph 3839 -> 3811; target -0.32 sigma, benchmarks/audit_catalog_recall.py seed 3014).  Measured
# on the tracker's tests: a real inclinometer bias on top of a lever arm -0.59 sigma (accepted); an inclinometer
# bias on top of a TRUE 3 cm lever-arm error -1.01 sigma (refused; the data alone prefer the bias there, F 1902 vs
# 1256 at the base, so this margin is thin: tests/test_tracker_audit.py::test_audit_names_a_wrong_prism_lever_arm)
COLLINEAR = 1e-2  # a library column within 0.6 deg of the model's columns adds nothing the model lacks (measured:
# duplicates of a catalog parameter sit at 1e-4..1e-3 after rounding and linearisation, real new shapes above 0.1)


@dataclass
class ResidualFamily:
    """Residuals of one sensor quantity, with the coordinates each residual has (for diagnostics and plots)."""

    sensor: str
    quantity: str  # e.g. "accel" (|f| - g per pose), "gyro" (static rate), "gyro_motion" (direction after a move)
    unit: str
    whitened: np.ndarray  # (n, k)
    physical: np.ndarray  # (n, k)
    coordinates: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (n,)
    channels: tuple[str, ...] = ()  # which coordinates are auxiliary channels of the recording
    angles: tuple[str, ...] = ()  # which coordinates are angles (rad): harmonics of them are offered

    @property
    def label(self) -> str:
        return f"{self.sensor}/{self.quantity}"

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.physical**2)))


@dataclass(frozen=True)
class Candidate:
    """One catalog entry: a stable effect name, its physical meaning, what it acts on, where to look."""

    effect: str
    sensor: str
    meaning: str
    target: str  # quantity of the residual family it explains (its gain is measured there)
    coordinate: str  # the coordinate its residual signature depends on (for plots)
    term: Term | None = None  # a generic term of the library (effect "unlisted")

    @property
    def key(self) -> str:
        if self.term is not None:
            return f"unlisted:{self.term.label}@{self.sensor}:{self.target}"
        return f"{self.effect}@{self.sensor}:{self.target}"

    @property
    def label(self) -> str:
        """The residual family it explains, ``sensor/quantity``."""
        return f"{self.sensor}/{self.target}"


UNLISTED = "unlisted"


def entry_name(entry: dict) -> str:
    """What a finding, rejection or ``ambiguous_with`` rival of the JSON names: a catalog effect, or a library term
    as ``form in driver`` (``x second_driver`` for a product)."""
    if entry.get("effect") != UNLISTED or not entry.get("driver"):
        return str(entry.get("effect"))
    second = f" x {entry['second_driver']}" if entry.get("second_driver") else ""
    return f"{entry['form']} in {entry['driver']}{second}"


def generic_candidate(term: Term, sensor: str, target: str, unit: str = "") -> Candidate:
    """A library term as a candidate of the search (``effect: "unlisted"``)."""
    return Candidate(UNLISTED, sensor, term.meaning(f"{sensor}/{target}", unit), target, term.driver, term)


@dataclass
class Fit:
    """A solved graph for a set of effects."""

    effects: tuple[Candidate, ...]
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    families: list[ResidualFamily]
    context: object = None  # system-specific (e.g. the assembled graph with its key layout)

    @property
    def n_obs(self) -> int:
        return int(sum(self.graph.at(i).dim() for i in range(self.graph.size())))

    @property
    def n_params(self) -> int:
        return int(self.values.dim())

    @property
    def rss(self) -> float:
        return 2.0 * self.graph.error(self.values)

    def bic(self) -> float:
        """Gaussian BIC with the residual scale estimated: n ln(RSS/n) + k ln n (robust to mis-scaled sigmas)."""
        n = self.n_obs
        return n * np.log(self.rss / n) + self.n_params * np.log(n)

    def family(self, quantity: str, sensor: str | None = None) -> ResidualFamily | None:
        for fam in self.families:
            if fam.quantity == quantity and (sensor is None or fam.sensor == sensor):
                return fam
        return None


def variance_factor(fit: Fit) -> float:
    """A-posteriori variance factor RSS / (n - k): scales a fit's covariance to the residuals it really left."""
    return fit.rss / max(fit.n_obs - fit.n_params, 1)


class AuditSystem(Protocol):
    name: str
    base_model: str
    base_effects: tuple[Candidate, ...]
    folds: int

    def candidates(self) -> list[Candidate]: ...

    def fit(self, effects: tuple[Candidate, ...], fold: int | None = None) -> Fit: ...

    def extend(self, fit: Fit, candidate: Candidate):
        """(graph with the candidate added, fit's values + the candidate's nominal ones, new columns) for
        :func:`score_test`.  Optional where the adapter has ``extend_all`` (:func:`extend_one`)."""

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        """Residual families of the held-out part of ``fold``, predicted with ``fit`` (trained on the rest)."""

    # heldout_fit(fit, fold) -> Fit (optional): the held-out part's solved graph with its families, where the
    #     held-out part has factors beyond the families (the engine then compares the whole graph's RSS)

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        """The candidate's estimate and 1-sigma in the contract's keys and units."""

    # Optional hooks (looked up with getattr):
    #   residual_correlation(fit) -> float: variance inflation 1 + 2 sum rho_k of residuals correlated in time
    #   term_coordinates(fit) -> {target quantity: [Coordinate]}: drivers its graph takes generic terms in
    #       (the candidates' ``term`` then reaches fit / extend / heldout / estimate)
    #   plausible(candidate, estimate) -> str | None: why an estimate is physically implausible
    #   catalog_term(candidate) -> (driver, form) | None: the library term a catalog effect is identical to
    #   information_form = True: score tests from the normal equations (:func:`scorers`), for a base graph that is
    #       full rank and too large for the dense Jacobian


def extend_one(system, fit: Fit, candidate: Candidate):
    """``system.extend``, or for an adapter that only has ``extend_all`` (one graph for many candidates), that with
    the one candidate: (graph, values, new columns)."""
    if hasattr(system, "extend"):
        return system.extend(fit, candidate)
    graph, values, groups = system.extend_all(fit, [candidate])
    return graph, values, groups[0]


def score_test(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
               new_columns: list[tuple[int, np.ndarray]]) -> tuple[float, int, int]:
    """F statistic of adding variables to a graph solved without them: (F, numerator dof, denominator dof).

    ``new_columns`` lists (key, indices into that variable's tangent vector) that are new: whole new variables,
    or new entries of a grown one (e.g. misalignment added to a scale-only matrix).  Linearised at ``values``:
    RSS drop of the least-squares step with all columns against the step without the new ones, over the
    residual variance of the extended fit.
    """
    A, b, offsets = dense_jacobian(graph, values)
    new = np.concatenate([offsets[k] + np.asarray(idx, dtype=int) for k, idx in new_columns])
    keep = np.setdiff1d(np.arange(A.shape[1]), new)
    rss_old = _lstsq_rss(A[:, keep], b)
    rss_new = _lstsq_rss(A, b)
    rank_gain = np.linalg.matrix_rank(A) - np.linalg.matrix_rank(A[:, keep])
    n_new = int(max(rank_gain, 1))
    dof_den = max(A.shape[0] - np.linalg.matrix_rank(A), 1)
    f_stat = ((rss_old - rss_new) / n_new) / max(rss_new / dof_den, 1e-300)
    return float(max(f_stat, 0.0)), n_new, int(dof_den)


def score_tests(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                groups: list[list[tuple[int, np.ndarray]]]) -> list[tuple[float, int, int]]:
    """:func:`score_test` of many candidates at once, from one graph holding all of them at their nominal values.

    Each group lists one candidate's new columns; the other candidates' columns are left out of its test.  One
    linearisation and one orthonormal basis ``Q`` of the base columns serve every candidate: its columns are
    projected off the base (``T' = T - Q Q^T T``), and the RSS drop is ``r^T T' (T'^T T')^+ T'^T r`` with ``r``
    the base residual.  A direction of ``T'`` shorter than ``COLLINEAR`` times the candidate's own column norm
    is a direction the model already has (a library term that duplicates a catalog parameter): it adds no
    degree of freedom and no evidence, whatever rounding leaves in it.
    """
    A, b, offsets = dense_jacobian(graph, values)
    columns = [np.concatenate([offsets[k] + np.asarray(idx, dtype=int) for k, idx in group]) for group in groups]
    candidate_columns = np.unique(np.concatenate(columns)) if columns else np.array([], dtype=int)
    base = np.setdiff1d(np.arange(A.shape[1]), candidate_columns)
    U, sv, _ = np.linalg.svd(A[:, base], full_matrices=False)
    rank_base = int(np.sum(sv > 1e-10 * max(sv.max(initial=0.0), 1e-300)))
    Q = U[:, :rank_base]  # orthonormal basis of the base columns' span
    r = b - Q @ (Q.T @ b)
    rss_old = float(r @ r)
    out = []
    for col in columns:
        T = A[:, col]
        own = max(float(np.linalg.norm(T, 2)), 1e-300)
        T = T - Q @ (Q.T @ T)
        U, sv, _ = np.linalg.svd(T, full_matrices=False)
        gain = int(np.sum(sv > COLLINEAR * own))
        drop = float(np.sum((U[:, :gain].T @ r) ** 2))
        n_new = max(gain, 1)
        dof_den = max(A.shape[0] - rank_base - gain, 1)
        f_stat = (drop / n_new) / max((rss_old - drop) / dof_den, 1e-300)
        out.append((float(max(f_stat, 0.0)), n_new, int(dof_den)))
    return out


# --- the same tests from the normal equations (large graphs) ------------------------------------------------------

SINGULAR = 1e-13  # an eigenvalue of the column-equilibrated information below this fraction of the largest is a
# direction the data leave free (as core.solve.dense_marginals): the normal equations resolve no finer
NEW_DIRECTION = 1e-5  # new columns' direction off the base, relative to their own length, below which it is one
# the base already has (the normal equations' rounding, eps x condition, sits near 1e-6 in these units; the dense
# test's rank tolerance is finer, ~1e-11: on the encoder's cases both give the same dof, F within 1e-11)


def information_score_test(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                           new_columns: list[tuple[int, np.ndarray]]) -> tuple[float, int, int]:
    """:func:`score_test` from the normal equations: the same statistic without the dense Jacobian.

    With ``T`` the new columns and ``H`` the information ``A^T A``, projecting ``T`` off the base columns gives
    the Schur complement ``S = T'^T T'`` and ``t = T'^T r`` (``r`` the base residual); the RSS drop is
    ``t^T S^+ t`` and the rank gain the rank of ``S``.  For adapters whose base graph is full rank (gauge fixed,
    priors on weakly seen variables): ``information_form = True``.
    """
    H, g, bb, rows, offsets = normal_equations(graph, values)
    new = np.concatenate([offsets[k] + np.asarray(idx, dtype=int) for k, idx in new_columns])
    S, t, rss_old, rank_base = _schur_complement(H, g, bb, new)
    scale = np.sqrt(np.diag(H)[new])  # each new column's own length: S in these units compares with 1
    scale[scale == 0] = 1.0
    lam, V = np.linalg.eigh(S / np.outer(scale, scale))
    keep = lam > NEW_DIRECTION**2
    drop = float(np.sum((V[:, keep].T @ (t / scale)) ** 2 / lam[keep]))
    n_new = int(max(np.sum(keep), 1))
    dof_den = max(rows - rank_base - int(np.sum(keep)), 1)
    f_stat = (drop / n_new) / max((rss_old - drop) / dof_den, 1e-300)
    return float(max(f_stat, 0.0)), n_new, int(dof_den)


def information_score_tests(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                            groups: list[list[tuple[int, np.ndarray]]]) -> list[tuple[float, int, int]]:
    """:func:`score_tests` from the normal equations (see :func:`information_score_test`).

    The singular values of a candidate's projected columns ``T'`` are the square roots of the eigenvalues of
    its block of ``S``; its RSS drop is ``sum_i (v_i^T t)^2 / lambda_i`` over the directions longer than
    ``COLLINEAR`` times its own columns' norm, as the dense test keeps them.
    """
    H, g, bb, rows, offsets = normal_equations(graph, values)
    columns = [np.concatenate([offsets[k] + np.asarray(idx, dtype=int) for k, idx in group]) for group in groups]
    candidate_columns = np.unique(np.concatenate(columns)) if columns else np.array([], dtype=int)
    S, t, rss_old, rank_base = _schur_complement(H, g, bb, candidate_columns)
    position = {c: i for i, c in enumerate(candidate_columns)}
    out = []
    for col in columns:
        idx = np.array([position[c] for c in col])
        own_squared = max(float(np.linalg.eigvalsh(H[np.ix_(col, col)])[-1]), 1e-300)
        lam, V = np.linalg.eigh(S[np.ix_(idx, idx)])
        keep = lam > COLLINEAR**2 * own_squared
        gain = int(np.sum(keep))
        drop = float(np.sum((V[:, keep].T @ t[idx]) ** 2 / lam[keep]))
        n_new = max(gain, 1)
        dof_den = max(rows - rank_base - gain, 1)
        f_stat = (drop / n_new) / max((rss_old - drop) / dof_den, 1e-300)
        out.append((float(max(f_stat, 0.0)), n_new, int(dof_den)))
    return out


def _schur_complement(H: np.ndarray, g: np.ndarray, bb: float, new: np.ndarray):
    """``(S, t, RSS of the base, base rank)`` for the columns ``new`` against the others, in the columns' units.

    Equilibrated (unit diagonal) before the Cholesky factorisation of the base block; a base column no row
    touches carries nothing and is left out (the dense test's rank does the same).  A base the data and priors
    do not determine is refused: this form needs the base full rank.
    """
    base = np.setdiff1d(np.flatnonzero(np.diag(H) > 0), new)
    scale = np.sqrt(np.diag(H))
    scale[scale == 0] = 1.0
    Hs, gs = H / np.outer(scale, scale), g / scale
    H_bb, H_bn = Hs[np.ix_(base, base)], Hs[np.ix_(base, new)]
    X = np.zeros((0, new.size + 1))
    if base.size:
        try:
            factor = linalg.cho_factor(H_bb)
            # reciprocal condition number, LAPACK's estimate from the factor (O(n^2), not an eigen-decomposition)
            rcond, _ = linalg.lapack.dpocon(factor[0], float(np.max(np.sum(np.abs(H_bb), axis=0))),
                                            uplo="L" if factor[1] else "U")
        except linalg.LinAlgError:
            rcond = 0.0
        if rcond <= SINGULAR:
            raise DegenerateDataError("the base model's graph is singular: the score tests need its information "
                                      "full rank")
        X = linalg.cho_solve(factor, np.column_stack([H_bn, gs[base]]))
    S = (Hs[np.ix_(new, new)] - H_bn.T @ X[:, :-1]) * np.outer(scale[new], scale[new])
    t = (gs[new] - H_bn.T @ X[:, -1]) * scale[new]
    rss_old = bb - float(gs[base] @ X[:, -1])
    return 0.5 * (S + S.T), t, rss_old, int(base.size)


def scorers(system):
    """(one candidate's test, many candidates' tests) for ``system``: from the normal equations where its adapter
    says ``information_form = True`` (a full-rank base too large for the dense Jacobian), else dense."""
    if getattr(system, "information_form", False):
        return information_score_test, information_score_tests
    return score_test, score_tests


def _lstsq_rss(A: np.ndarray, b: np.ndarray) -> float:
    if A.shape[1] == 0:
        return float(b @ b)
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    r = b - A @ x
    return float(r @ r)


@dataclass
class Trial:
    candidate: Candidate
    f_stat: float
    p_value: float
    dof: int
    log_p: float | None = None  # ln p where p underflows to 0 (strong effects): orders the evidence beyond it
    raw: tuple[float, int] | None = None  # (F, denominator dof) before the correlation inflation divided them

    @property
    def explained(self) -> float:
        """The whitened sum of squares the candidate explains (the score statistic, ``dof F``)."""
        return self.f_stat * self.dof

    def ties_with(self, other: "Trial") -> bool:
        """``other`` explains as much as this trial within this one's sampling spread: under the alternative the
        score statistic is a non-central chi-square, sd ``sqrt(2 (dof + 2 lambda))``, ``lambda`` ~ explained - dof
        (a cubic in a ship's heading explained 103 and its true second harmonic 88, sd 20)."""
        spread = np.sqrt(2.0 * (self.dof + 2.0 * max(self.explained - self.dof, 0.0)))
        return self.explained - other.explained < spread

    @property
    def evidence_order(self) -> float:
        """ln p: smaller is stronger evidence, also where p itself underflows to 0."""
        return self.log_p if self.log_p is not None else float(np.log(max(self.p_value, 1e-320)))


def _trial(candidate: Candidate, f_stat: float, dof: int, dof_den: int, inflation: float = 1.0) -> Trial:
    """A scored candidate, its F and denominator dof divided by the residuals' correlation ``inflation``; a library
    term picked by a search (the periodogram's peak frequency) is corrected for it."""
    raw = (f_stat, dof_den)
    f_stat, dof_den = f_stat / inflation, max(int(dof_den / inflation), 1)
    p = float(stats.f.sf(f_stat, dof, dof_den))
    p = p if candidate.term is None else candidate.term.search_corrected(p)
    # two effects of thousands of sigmas both have p = 0: the one with the stronger evidence is tried first (a
    # 4 mrad inclinometer bias, F = 35676, and the 13 cm lever arm it resembles, F = 22672, were tried in the
    # catalog's order, and the lever arm, accepted first, kept the bias out on held-out data)
    log_p = None
    if p == 0.0:  # scipy's logsf underflows too there
        log_p = float(stats.f.logsf(f_stat, dof, dof_den))
        log_p = log_p if np.isfinite(log_p) else chi2_log_tail(dof * f_stat, dof)
    return Trial(candidate, f_stat, p, dof, log_p, raw)


def chi2_log_tail(x: float, k: int) -> float:
    """ln P(chi^2_k > x) for x >> k, where the tail underflows: the upper incomplete gamma's asymptotic series,
    ``(k/2 - 1) ln(x/2) - x/2 - ln Gamma(k/2) + ln(1 + (k/2 - 1) / (x/2))``.

    The prefactor is what ranks a lower polynomial degree against a higher one that explains the same: a linear
    term in a scan's range explained 2931.2 and the quadratic 2931.4; with the leading term ``-x/2`` alone the
    quadratic had the stronger evidence, with the prefactor the linear term leads by ln(x/2)/2 = 3.6 (seed 2006)."""
    half_k, half_x = 0.5 * k, 0.5 * x
    return float((half_k - 1.0) * np.log(half_x) - half_x - special.gammaln(half_k)
                 + np.log1p((half_k - 1.0) / half_x))


@dataclass
class Rejection:
    """Why a significant candidate was not accepted: ``bic``, ``heldout``, ``implausible`` or ``outdone``."""

    reason: str
    measured: dict  # delta BIC, held-out RSS before/after, and the reason's own detail


@dataclass
class Heldout:
    """Cross-validated residuals of one model: whitened RSS over all families, per family RSS and RMS, and per
    family each held-out row's whitened sum of squares (one array per fold, in time order) for paired comparisons."""

    rss: float
    rss_by_label: dict[str, float]
    rms_by_label: dict[str, float]
    rows_by_label: dict[str, list[np.ndarray]] = field(default_factory=dict)


def target_change(before: Heldout, after: Heldout, label: str) -> tuple[float, float] | None:
    """(drop, sampling sigma) of one family's held-out whitened RSS from ``before`` to ``after``, paired by row.

    The same held-out rows predicted by two models: the change per row ``d_i`` (before less after) is what varies
    between recordings, so the sum's sigma is ``sqrt(n var(d) c)`` with ``c`` the variance inflation of ``d`` in
    time (rows of one fold are consecutive; a smooth misfit makes neighbouring rows change together).  None where
    the rows do not pair (a family missing, or a different number of rows)."""
    old, new = before.rows_by_label.get(label), after.rows_by_label.get(label)
    if not old or not new or [len(a) for a in old] != [len(a) for a in new]:
        return None
    d = [a - b for a, b in zip(old, new)]
    flat = np.concatenate(d)
    if flat.size < 2:
        return None
    centred = [x - flat.mean() for x in d]
    inflation = correlation_inflation(centred, max_lag=max(10, min(flat.size // 20, 200)))
    return float(flat.sum()), float(np.sqrt(flat.size * np.var(flat, ddof=1) * inflation))


@dataclass
class AuditResult:
    system: str
    base_model: str
    findings: list[dict]
    final_effects: tuple[Candidate, ...]
    base_fit: Fit
    final_fit: Fit
    history: list[dict]  # per search step: the trials (evidence table) and what was accepted
    fits: list[Fit]  # base, then after each accepted finding
    rejected: list[dict] = field(default_factory=list)  # passed the significance test, not accepted (reason)
    remaining: dict = field(default_factory=dict)  # family label -> verdict on the final model's residuals
    notes: list[str] = field(default_factory=list)  # coordinates skipped, phases not offered

    @property
    def significant_evidence(self) -> bool:
        """Whether anything passed the significance test (accepted or not)."""
        return bool(self.findings or self.rejected)

    def to_json(self) -> dict:
        """The audit contract of ARCHITECTURE.md (extra keys are additions, never changes)."""
        final = [self.base_model] + [c.effect for c in self.final_effects if c not in self.base_fit.effects]
        out = {"system": self.system, "base_model": self.base_model, "findings": self.findings,
               "final_model": final,
               "residual_rms": {f.label: f.rms for f in self.final_fit.families},
               "rejected": self.rejected, "remaining": self.remaining}
        if self.notes:
            out["notes"] = self.notes
        return out


def _heldout(system: AuditSystem, effects) -> Heldout:
    """Held-out whitened RSS, and per family label, summed over folds.

    The total is the whole held-out graph's where the adapter solves one (``heldout_fit``): the metric the score
    test and the BIC use.  The families alone miss what the held-out states pay elsewhere: without an effect
    they bend to absorb it and move its cost into factors no family shows (a late tracker's states pull against
    the IMU factors; measured on a 24 ms clock offset: the families' held-out drop 6.6, the graph's 12.2)."""
    rss, rss_by, sq, count, rows = 0.0, {}, {}, {}, {}
    heldout_fit = getattr(system, "heldout_fit", None)
    for fold in range(system.folds):
        fit = system.fit(effects, fold)
        held = heldout_fit(fit, fold) if heldout_fit is not None else None
        families = held.families if held is not None else system.heldout(fit, fold)
        by_family = {fam.label: float(np.sum(fam.whitened**2)) for fam in families}
        rss += held.rss if held is not None else sum(by_family.values())
        for fam in families:
            rss_by[fam.label] = rss_by.get(fam.label, 0.0) + by_family[fam.label]
            sq[fam.label] = sq.get(fam.label, 0.0) + float(np.sum(fam.physical**2))
            count[fam.label] = count.get(fam.label, 0) + fam.physical.size
            rows.setdefault(fam.label, []).append(_rows_in_time_order(fam))
    return Heldout(rss, rss_by, {label: np.sqrt(sq[label] / count[label]) for label in sq}, rows)


def _rows_in_time_order(family: ResidualFamily) -> np.ndarray:
    """Each residual row's whitened sum of squares, ordered by the family's time coordinate where it has one."""
    w = np.asarray(family.whitened, dtype=float)
    per_row = np.sum(w.reshape(len(w), -1) ** 2, axis=1)
    time = next((np.asarray(v, dtype=float) for name, v in family.coordinates.items()
                 if driver_name(name) == "time" and np.shape(v) == per_row.shape), None)
    return per_row if time is None else per_row[np.argsort(time, kind="stable")]


def run_audit(system: AuditSystem, max_findings: int = 8, alpha: float = FAMILY_ALPHA,
              progress: Callable = quiet) -> AuditResult:
    """Search the catalog, then the generic term library, one accepted extension at a time.

    ``progress(stage)`` is called as the base fit and each step start (:mod:`selfcal.core.progress`)."""
    search = _Search(system, alpha, progress)
    search.run(max_findings)
    return search.result()


class _Search:
    """The search's state (current model, its held-out residuals, findings, rejections) and its steps."""

    def __init__(self, system: AuditSystem, alpha: float, progress):
        self.system, self.alpha = system, alpha
        self.progress = progress or (lambda message: None)
        self.library_alpha = min(alpha, LIBRARY_ALPHA)
        self.effects = tuple(system.base_effects)
        self.progress(f"fitting the base model ({system.base_model})")
        self.fit = self.base_fit = system.fit(self.effects)
        self.fits = [self.fit]
        self.progress(f"cross-validating the base model ({system.folds} folds)")
        self.held = _heldout(system, self.effects)
        self.findings: list[dict] = []
        self.history: list[dict] = []
        self.rejected: dict[str, dict] = {}
        self.notes: list[str] = list(getattr(system, "notes", ()))  # the adapter's own (scenes left out, ...)
        self.offers_terms = hasattr(system, "term_coordinates")

    # --- the search --------------------------------------------------------------------------------------------

    def run(self, max_findings: int) -> None:
        """The catalog until nothing more is accepted, then the library.  A library term that outdoes a catalog
        finding on its residual has that finding rejected, and the search starts again without it; a finding the
        later ones made redundant likewise (a library term is dropped where it stands: :meth:`redundant_finding`)."""
        banned: set[str] = set()  # keys of findings outdone (never offered again)
        while True:
            while len(self.findings) < max_findings:
                catalog = [c for c in self.system.candidates() if c not in self.effects and c.key not in banned]
                if not catalog or not self.step(catalog, len(catalog), "catalog"):
                    break
            outdone = None
            if not self.offers_terms:
                note = (f"{self.system.name}: no generic term library in this system's graph yet; the remaining "
                        "structure is reported, not modelled")
                if note not in self.notes:
                    self.notes.append(note)
            while self.offers_terms and len(self.findings) < max_findings:
                generic = [c for c in self.generic_candidates() if c.key not in banned]
                if not generic:
                    break
                # True: a term was accepted; search on until none is (the first, strongest term must not end the
                # search: on the real Hilti flat.yaml the base accelerometer's harmonic in arm_angle, p = 0, was
                # left unmodelled behind the prism's cubic in joint 1 when it did)
                outdone = self.step(generic, self.library_tests(generic), "library")
                if outdone is not True:
                    break
            if not isinstance(outdone, Candidate):
                outdone = self.redundant_finding()
            if outdone is None:
                outdone = self.needless_degree()
            if outdone is None:
                break
            banned.add(outdone.key)
            if outdone.term is not None and outdone in self.effects:
                self.drop(outdone)  # a library term the later findings made redundant: the rest stands
            else:
                self.restart()
        if len(self.findings) >= max_findings:
            self.notes.append(f"the search stopped at its cap of {max_findings} findings: more may be significant "
                              "(see `remaining`)")
        # estimates and sigmas come from the final model: an effect accepted later changes the earlier ones
        # (gains stay as measured at the step each effect was accepted)
        for finding, cand in zip(self.findings, [c for c in self.effects if c not in self.base_fit.effects]):
            estimate, std = self.system.estimate(self.fit, cand)
            finding["estimate"], finding["std"] = estimate, std

    def drop(self, cand: Candidate) -> None:
        """The model without one accepted library term, the others kept (stepwise regression's backward step).

        Not a restart: on ship seed 2011 a harmonic in time went in first, the true heading harmonic after it,
        and the time harmonic was then redundant; started again from the base model without it, the search
        took another first term, banned that too, and ended with nothing named beside a 25.7 sigma effect.  The
        gains of the findings after it stay as measured (with it in the model)."""
        found = [c for c in self.effects if c not in self.base_fit.effects]
        self.findings.pop(found.index(cand))
        self.effects = tuple(c for c in self.effects if c != cand)
        self.fit = self.system.fit(self.effects)
        self.fits.append(self.fit)
        self.held = _heldout(self.system, self.effects)

    def restart(self) -> None:
        """Back to the base model (rejections and notes are kept)."""
        self.effects = tuple(self.system.base_effects)
        self.fit = self.base_fit
        self.fits = [self.fit]
        self.held = _heldout(self.system, self.effects)
        self.findings, self.history = [], []

    def library_tests(self, generic: list[Candidate]) -> float:
        """The effective number of library tests: correlated terms (nested polynomials, neighbouring step
        locations, the same driver for two targets' rows) count as far as they are independent (Li & Ji)."""
        return max(library.effective_number(self._first_columns(generic)), 1.0)

    def step(self, candidates: list[Candidate], n_tests: float, phase: str):
        """Score every candidate, refit the significant ones in order of evidence, accept the first that passes.

        Returns True when one was accepted, False when none was, and in the library phase the catalog effect a
        term outdoes (the caller restarts the search without it).  A library step tries at most
        ``LIBRARY_ATTEMPTS`` significant terms: each costs a refit and the cross-validation.
        """
        self.progress(f"{phase}: score {len(candidates)} candidates")
        trials = sorted(self.score_many(candidates, self.fit), key=lambda t: t.evidence_order)
        threshold = (self.alpha if phase == "catalog" else self.library_alpha) / n_tests
        self.progress(f"step {len(self.history) + 1} ({phase}): {len(trials)} candidates, best "
                          f"{trials[0].candidate.key} p={trials[0].p_value:.3g}")
        if phase == "library":
            trials = self.rescored_under_alternative(trials, threshold)
        significant = [t for t in trials if t.p_value < threshold]
        if phase == "library":
            significant = [t for t in significant if not _adds_nothing_over_lower_degree(t, trials)]
            significant = significant[:LIBRARY_ATTEMPTS]
        accepted, outdone = None, None
        for trial in significant:
            if phase == "library" and self.nested_catalog(trial.candidate):
                # a polynomial of a driver a catalog effect is linear in: tried in its place, not on top of it
                outdone = self.outdone_catalog_effect(trial, self.nested_catalog(trial.candidate))
                if outdone is not None:
                    break
                self.reject(trial, Rejection("heldout", {"in_place_of": [c.effect for c in
                                                                        self.nested_catalog(trial.candidate)]}))
                continue
            outcome = self.attempt(trial)
            if isinstance(outcome, Rejection):
                self.reject(trial, outcome)
                continue
            if phase == "library":
                trial, outcome = self.best_of_ties(trial, outcome, significant[significant.index(trial) + 1:])
            # a term that pays on top of the model may still explain a catalog finding better than the finding
            # does (a quadratic where a linear catalog effect took the slope): then the finding goes instead
            outdone = self.outdone_catalog_effect(trial) if phase == "library" else None
            if outdone is None:
                accepted = (trial, *outcome)
            break
        if phase == "library" and accepted is None and outdone is None:
            outdone = self.outdone_by_weaker_term(trials, n_tests)
        self.history.append({"step": len(self.history) + 1, "phase": phase, "threshold": threshold,
                             "trials": [{"candidate": t.candidate.key, "F": t.f_stat, "p_value": t.p_value}
                                        for t in trials],
                             "accepted": accepted[0].candidate.key if accepted else None})
        if outdone is not None:
            return outdone
        if accepted is None:
            return False
        self.accept(*accepted, trials, threshold)
        return True

    def best_of_ties(self, trial: Trial, outcome, rest: list[Trial]):
        """(trial, outcome) of the library term that predicts held-out data best among ``trial`` (accepted by
        :meth:`attempt`) and the next ones whose evidence ties with it (:meth:`Trial.ties_with`).

        Which of two shapes in one driver the score test puts first is then decided by sampling noise: a cubic
        in a ship's heading scored p = 4.3e-12 against the true second harmonic's 7.4e-12 (held-out 1116 against
        407).  Held-out: the whitened RSS plus the term's dof (the acceptance's own margin).  Rivals not taken
        are neither rejected nor recorded here: the next step scores them on top.

        The library only: catalog look-alikes that tie are physics the data cannot tell apart, and held-out data,
        which favour the fewer parameters, then pick at random (measured, tracker 3 cm prism lever arm, 20 seeds:
        the lever arm named on 4 instead of 13, the inclinometer bias on 16, once without its ambiguity); the
        catalog keeps the evidence order and says the ambiguity (``ambiguous_with``).

        Polynomials of one driver on one family are not rivals: one holds the other, so a higher degree ties
        whenever the lower one is the truth and held-out noise picks it now and then (measured at 3d8e954: a scan
        range slope named as poly2/poly3 on 3 of 20 seeds, a ship bias in roll^2 as a cubic on 3 of 20); the
        higher degree enters only by its own significance on top, at the next step."""
        def predictive(t, held):
            return held.rss + t.dof
        best, best_outcome = trial, outcome
        for rival in [t for t in rest if trial.ties_with(t) and not _same_polynomial(trial, t)][:TIE_ATTEMPTS]:
            if self.nested_catalog(rival.candidate):
                continue
            rival_outcome = self.attempt(rival)
            if isinstance(rival_outcome, Rejection):
                continue
            if predictive(rival, rival_outcome[1]) < predictive(best, best_outcome[1]):
                best, best_outcome = rival, rival_outcome
        return best, best_outcome

    def score(self, candidate: Candidate, fit: Fit) -> Trial:
        """Score test of one candidate against ``fit``, corrected for residuals correlated in time (a library
        term's with the collinearity rule of :func:`score_tests`)."""
        graph, values, columns = extend_one(self.system, fit, candidate)
        one, many = scorers(self.system)
        if candidate.term is None:
            f_stat, dof, dof_den = one(graph, values, columns)
        else:
            f_stat, dof, dof_den = many(graph, values, [columns])[0]
        return _trial(candidate, f_stat, dof, dof_den, self.inflation(fit))

    def score_many(self, candidates: list[Candidate], fit: Fit) -> list[Trial]:
        """Score tests of many candidates: from one graph holding them all where the system builds one
        (``extend_all``: library terms), else one :func:`score_test` each."""
        extend_all = getattr(self.system, "extend_all", None)
        if extend_all is None or any(c.term is None for c in candidates):
            return [self.score(c, fit) for c in candidates]
        graph, values, groups = extend_all(fit, candidates)
        inflation = self.inflation(fit)
        trials = []
        for cand, (f_stat, dof, dof_den) in zip(candidates, scorers(self.system)[1](graph, values, groups)):
            trials.append(_trial(cand, f_stat, dof, dof_den, inflation))
        return trials

    def rescored_under_alternative(self, trials: list[Trial], threshold: float) -> list[Trial]:
        """Library trials whose evidence the correlation inflation took away, scored again with the inflation
        measured on the model WITH the term (the unrestricted model, as the F test's variance and as HAC-robust
        tests do): an effect not yet modelled leaves a slow signature in the current residuals that passes for
        correlated noise (a heading-locked accelerometer bias on a 300 s voyage scored p = 0.009 on the current
        model and is 18.6 sigma once fitted).  Under the null hypothesis the two inflations coincide.  The
        ``RESCORED`` strongest by their undeflated evidence, each at the cost of one fit."""
        hook = getattr(self.system, "residual_correlation", None)
        if hook is None:
            return trials
        lost = [t for t in trials if t.p_value >= threshold and t.raw is not None
                and stats.f.sf(t.raw[0], t.dof, t.raw[1]) < threshold]
        lost = sorted(lost, key=lambda t: -t.raw[0] * t.dof)[:RESCORED]
        if not lost:
            return trials
        self.progress(f"rescoring {len(lost)} terms with the correlation of the model that holds them")
        again = {}
        for t in lost:
            inflation = hook(self.system.fit(self.effects + (t.candidate,)))
            again[t.candidate] = _trial(t.candidate, t.raw[0], t.dof, t.raw[1], inflation)
        return sorted((again.get(t.candidate, t) for t in trials), key=lambda t: t.evidence_order)

    def inflation(self, fit: Fit) -> float:
        # residuals correlated in time (waves, vibration) hold fewer independent samples than rows: a system
        # that knows it gives the variance inflation 1 + 2 sum rho_k, and the F test uses the effective sizes
        hook = getattr(self.system, "residual_correlation", None)
        return hook(fit) if hook else 1.0

    def attempt(self, trial: Trial):
        """(fit, held-out, delta BIC) of the model with the candidate, or the :class:`Rejection` saying why not."""
        cand = trial.candidate
        new_effects = self.effects + (cand,)
        self.progress(f"refitting and cross-validating with {cand.key}")
        new_fit = self.system.fit(new_effects)
        new_held = _heldout(self.system, new_effects)
        delta_bic = new_fit.bic() - self.fit.bic()
        log.info("%s: F=%.3g p=%.3g dBIC=%.1f heldout %.4g -> %.4g", cand.key, trial.f_stat, trial.p_value,
                 delta_bic, self.held.rss, new_held.rss)
        measured = {"delta_bic": delta_bic, "heldout_rss_before": self.held.rss, "heldout_rss_after": new_held.rss}
        if delta_bic >= 0:
            return Rejection("bic", measured)
        # its own target must not get worse held-out beyond the sampling noise of the paired change (whitened, as
        # the score test and the graph's comparison; physical RMS where the rows do not pair)
        change = target_change(self.held, new_held, cand.label)
        if change is not None:
            measured["heldout_target_drop"], measured["heldout_target_sigma"] = change
            target_held = change[0] >= -TARGET_WORSE_SIGMAS * change[1]
        else:
            target_held = new_held.rms_by_label.get(cand.label, 0.0) <= self.held.rms_by_label.get(cand.label,
                                                                                                  np.inf)
        # a library term must pay for its parameters on held-out data too: fitted to noise, each of its q
        # parameters raises the expected held-out whitened RSS by about 1 (the predictive analogue of AIC), so a
        # real term lowers it by more than q; the catalog keeps the plain "lower" rule (its effects are physics
        # expected a priori, the library's are a search over many shapes)
        margin = float(trial.dof) if cand.term is not None else 0.0
        if not (new_held.rss < self.held.rss - margin and target_held):
            return Rejection("heldout", measured)
        try:
            estimate = self.system.estimate(new_fit, cand)[0]
        except DegenerateDataError as err:
            return Rejection("implausible", {**measured, "why": f"not determined by the data: {err}"})
        plausible = getattr(self.system, "plausible", None)
        why = plausible(cand, estimate) if plausible is not None else None
        if why:
            return Rejection("implausible", {**measured, "why": why})
        return new_fit, new_held, delta_bic

    def outdone_by_weaker_term(self, trials: list[Trial], n_tests: float) -> Candidate | None:
        """A catalog finding outdone by a term that could not be named on top of it (significant at the catalog's
        level over the library's effective number of tests but not at the library's, or significant but not
        paying held-out on top): a catalog effect must explain its target at least as well as the best generic
        term, and a term that cannot be named on top of the model may be the better model in the effect's place.

        The same test as :meth:`outdone_catalog_effect` (the swap lowers the BIC, the effect is no longer
        significant on top of the term), for the first ``TIE_ATTEMPTS`` such terms.  On a qc scan whose sphere
        radius changes with range (-10 mm/m, seed 2011 of 20) a range offset of 89 mm and a radius of -13 mm had been
        named, the linear term in range then raising the held-out RSS on top of them (3492 -> 3896); in the
        offset's place it is named, -10.2 +- 0.3 mm/m, beside a 2.1 mm radius.  Measured on qc scans hiding
        a range error growing with incidence (``a (i / 90 deg)^2``, a = 10 mm): a range offset of -16 +- 0.8 mm
        had been named on seeds 2000 and 2005 of 20 (first by the score test among the catalog's, F 414 against
        the radius's 379), the cubic in incidence on top of it at p = 4.5e-6 and 8.0e-6, above the library's
        level; swapped in, the cubic fits better and the offset is no longer significant on top of it (p 0.033,
        0.46).  On an IMU pair the accelerometer axis rotation's look-alike, a linear term in ``f_y``, adds
        nothing on top of it (p = 1.0): never tried."""
        weaker = [t for t in trials if t.p_value < self.alpha / n_tests and not self.nested_catalog(t.candidate)]
        for trial in weaker[:TIE_ATTEMPTS]:
            outdone = self.outdone_catalog_effect(trial)
            if outdone is not None:
                return outdone
        return None

    def nested_catalog(self, term: Candidate) -> list[Candidate]:
        """Catalog effects in the model that a library polynomial contains (its linear part in the same driver)."""
        same_as = getattr(self.system, "catalog_term", None)
        if term.term is None or same_as is None or term.term.form not in ("poly2", "poly3"):
            return []
        return [c for c in self.effects if c.term is None and c.sensor == term.sensor and c.target == term.target
                and same_as(c) == (term.term.driver, "poly1")]

    def outdone_catalog_effect(self, trial: Trial, among: list[Candidate] | None = None) -> Candidate | None:
        """The catalog finding a significant library term outdoes on the same residual, rejected as such.

        The term is significant on top of the whole model (the trial).  Swapped in for a catalog effect on the
        same residual, it must fit better by the BIC, and the effect must lose its significance on top of it: the
        term encompasses the effect (Davidson & MacKinnon's comparison of non-nested models).  The held-out
        check is the addition's (a time-driven term fitted on one half of a run cannot predict the other: the
        swap would fail for the wrong reason).
        """
        term = trial.candidate
        rivals = among if among is not None else [c for c in self.effects if c.term is None and c.sensor == term.sensor
                                                  and c.target == term.target]
        for cand in [c for c in rivals if c not in self.base_fit.effects]:
            swapped = tuple(c for c in self.effects if c != cand) + (term,)
            swapped_fit = self.system.fit(swapped)
            delta_bic = swapped_fit.bic() - self.fit.bic()
            if delta_bic >= 0:
                continue
            on_top = self.score(cand, swapped_fit)
            if on_top.p_value < self.alpha / max(len(self.system.candidates()), 1):
                continue
            finding = next(f for f in self.findings if f["effect"] == cand.effect and f["target"] == cand.label)
            self.reject(Trial(cand, finding["evidence"]["statistic"], finding["evidence"]["p_value"], 0),
                        Rejection("outdone", {
                            "delta_bic_swapped": delta_bic, "p_value_on_top_of_term": on_top.p_value,
                            "outdone_by": {"driver": term.term.driver, "form": term.term.form,
                                           "meaning": term.meaning}}))
            return cand
        return None

    def redundant_finding(self) -> Candidate | None:
        """A finding the final model no longer needs, rejected as ``outdone`` by the later findings.

        Accepted one at a time, an effect found first may only have stood in for one found after it (a radius
        error taking part of a range offset; a cubic in the heading, p = 4.3e-12, taking the place of the heading's
        second harmonic, p = 7.4e-12, that was then found on top of it): refitted without it, the final model's
        other effects leave it insignificant at its own level (a catalog effect's, or a library term's over the
        library's effective number of tests).  A catalog finding: the search starts again without it; a library
        term: dropped where it stands, the search going on (:meth:`drop`).  Backward elimination.
        """
        found = [c for c in self.effects if c not in self.base_fit.effects]
        catalog_level = self.alpha / max(len(self.system.candidates()), 1)
        library_level = None
        for cand in found[:-1]:
            if cand.term is not None and library_level is None:
                library_level = self.library_alpha / self.library_tests(self.generic_candidates())
            others = self.system.fit(tuple(c for c in self.effects if c != cand))
            on_top = self.score(cand, others)
            if on_top.p_value < (catalog_level if cand.term is None else library_level):
                continue
            finding = self.findings[found.index(cand)]  # findings are appended as effects are
            later = [c.key if c.term is not None else f"{c.effect}@{c.label}" for c in found[found.index(cand) + 1:]]
            self.reject(Trial(cand, finding["evidence"]["statistic"], finding["evidence"]["p_value"], 0),
                        Rejection("outdone", {"p_value_on_top_of_the_rest": on_top.p_value,
                                              "outdone_by": {"findings": later}}))
            return cand
        return None

    def needless_degree(self) -> Candidate | None:
        """A ``poly2``/``poly3`` finding whose top degree the final model does not need, rejected as ``outdone`` by
        the next lower degree of its driver (backward elimination of nested polynomials: the highest order goes
        first).  The lower degree is fitted in its place; the finding's own score test on top of that (the top
        coefficient's, rank gain 1) must pass the search's level over the polynomial findings tested.  Dropped, the
        search goes on and the lower degree enters by its own evidence.  Measured at 5f4c69b: a scan radius growing
        linearly with range was named as a cubic on seed 2018 (cubic beside the quadratic p = 0.10, quadratic beside
        the linear 0.58).
        The tie rule keeps a higher degree from entering by held-out noise; this one from staying by an ordering of
        the score tests' evidence (18.5 more explained for 2 dof on scan 2018, at the step it entered)."""
        found = [c for c in self.effects if c not in self.base_fit.effects]
        polynomials = [c for c in found if c.term is not None and c.term.second is None
                       and c.term.form in ("poly2", "poly3")]
        if not polynomials:
            return None
        generic = self.generic_candidates()
        # one nested test per polynomial finding, not a search over the library: its top coefficient stays where it
        # is significant at the search's own level (the library's, 1e-5 over hundreds of terms, had a quadratic
        # range error in qc incidence stepped down to a linear term on 10 of 22 seeds, its curvature then reported
        # as structure that remains at p 2e-8 to 9e-5)
        level = self.alpha / len(polynomials)
        for cand in polynomials:
            lower_form = "poly1" if cand.term.form == "poly2" else "poly2"
            lower = next((c for c in generic if c.term.form == lower_form and c.term.driver == cand.term.driver
                          and c.term.second is None and c.sensor == cand.sensor and c.target == cand.target), None)
            if lower is None:
                continue
            try:
                with_lower = self.system.fit(tuple(c for c in self.effects if c != cand) + (lower,))
                on_top = self.score(cand, with_lower)
            except DegenerateDataError:  # the lower degree adds no direction (an encoder's base gain holds the
                continue  # linear part of a response in signal): the finding's degree is its lowest
            if on_top.p_value < level or not self._accepted_in_place(cand, lower):
                continue
            finding = self.findings[found.index(cand)]
            self.reject(Trial(cand, finding["evidence"]["statistic"], finding["evidence"]["p_value"], 0),
                        Rejection("outdone", {"p_value_on_top_of_lower_degree": on_top.p_value,
                                              "outdone_by": {"driver": lower.term.driver, "form": lower_form,
                                                             "meaning": lower.meaning}}))
            return cand
        return None

    def _accepted_in_place(self, cand: Candidate, other: Candidate) -> bool:
        """Whether ``other`` passes :meth:`attempt` on the model without ``cand`` (the state is left as it was).
        A degree stepped down must be named in its place: on an encoder (seed 3003) the quadratic in signal failed
        the held-out margin where the cubic had passed it, and stepping down had left nothing named."""
        saved = self.effects, self.fit, self.held
        self.effects = tuple(c for c in self.effects if c != cand)
        self.fit = self.system.fit(self.effects)
        self.held = _heldout(self.system, self.effects)
        try:
            return not isinstance(self.attempt(self.score(other, self.fit)), Rejection)
        finally:
            self.effects, self.fit, self.held = saved

    def reject(self, trial: Trial, rejection: Rejection) -> None:
        cand = trial.candidate
        entry = {"effect": cand.effect, "target": cand.label, "reason": rejection.reason,
                 "evidence": {"statistic": trial.f_stat, "p_value": trial.p_value}, **rejection.measured}
        if cand.term is not None:
            entry.update(driver=cand.term.driver, form=cand.term.form, meaning=cand.meaning)
        self.rejected[cand.key] = entry

    def accept(self, trial: Trial, new_fit: Fit, new_held: Heldout, delta_bic: float, trials, threshold) -> None:
        cand = trial.candidate
        estimate, std = self.system.estimate(new_fit, cand)
        before, after = self.fit.family(cand.target, cand.sensor), new_fit.family(cand.target, cand.sensor)
        finding = {
            "effect": cand.effect, "sensor": cand.sensor, "estimate": estimate, "std": std,
            "evidence": {"diagnostic": f"score test: {cand.label} residual vs {cand.coordinate}",
                         "statistic": trial.f_stat, "p_value": trial.p_value},
            "gain": {"unit": before.unit if before else None,
                     "rms_before": before.rms if before else None, "rms_after": after.rms if after else None,
                     "delta_bic": delta_bic, "heldout_rms_before": self.held.rms_by_label.get(cand.label),
                     "heldout_rms_after": new_held.rms_by_label.get(cand.label)},
            "meaning": cand.meaning, "target": cand.label,
        }
        if cand.term is not None:
            finding.update(driver=cand.term.driver, form=cand.term.form)
            if cand.term.second:
                finding["second_driver"] = cand.term.second
        same_as = getattr(self.system, "catalog_term", lambda c: None)(cand)
        if same_as:
            finding["same_as"] = {"effect": UNLISTED, "driver": same_as[0], "form": same_as[1],
                                  "note": "the catalog name is used for this library term"}
        rivals = _ambiguous_rivals(self.system, new_fit, trials, cand, new_fit.bic(), self.fit, threshold)
        if rivals:
            finding["ambiguous_with"] = rivals
        self.findings.append(finding)
        self.rejected.pop(cand.key, None)
        self.effects = self.effects + (cand,)
        self.fit, self.held = new_fit, new_held
        self.fits.append(new_fit)

    # --- the library ---------------------------------------------------------------------------------------

    def generic_candidates(self, fit: Fit | None = None) -> list[Candidate]:
        """Library terms for every target the system takes terms on, minus those a catalog effect already is."""
        fit = fit or self.fit
        drivers = self.system.term_coordinates(fit)
        covered = set()
        for c in list(self.system.candidates()) + list(self.effects):
            same = getattr(self.system, "catalog_term", lambda c: None)(c) if c.term is None else None
            if same:
                covered.add((c.sensor, c.target, *same))
        out = []
        for (sensor, target), coordinates in drivers.items():
            usable = []
            for c in coordinates:
                why = c.usable
                if why:
                    note = f"{sensor}/{target}: {why}: skipped"
                    if note not in self.notes:
                        self.notes.append(note)
                else:
                    usable.append(c)
            fam = fit.family(target, sensor)
            time = next((c for c in usable if c.kind == "time"), None)
            residual = fam.whitened if fam is not None and time is not None and len(fam.whitened) == len(
                time.values) else None
            for term in library.terms_for(usable, residual, time.values if time is not None else None):
                if (sensor, target, term.driver, term.form) in covered:
                    continue
                unit = next((c.unit for c in usable if c.name == term.driver), "")
                cand = generic_candidate(term, sensor, target, unit)
                if cand not in self.effects:
                    out.append(cand)
        return out

    def _first_columns(self, candidates: list[Candidate]) -> list[np.ndarray]:
        """Each candidate's basis columns at its target's driver values, for the effective number of tests.

        Targets are different residuals, so their tests are independent: each target gets its own block of rows
        (its columns are zero on the others').  Every basis column of a term counts (a quadratic tests a
        direction its linear part does not)."""
        drivers = self.system.term_coordinates(self.fit)
        blocks = {key: {c.name: np.asarray(c.values, dtype=float) for c in coordinates}
                  for key, coordinates in drivers.items()}
        sizes = {key: len(next(iter(v.values()))) if v else 0 for key, v in blocks.items()}
        offsets, total = {}, 0
        for key, size in sizes.items():
            offsets[key], total = total, total + size
        columns = []
        for c in candidates:
            key = (c.sensor, c.target)
            basis = c.term.columns(blocks[key])
            for j in range(basis.shape[1]):
                col = np.zeros(total)
                col[offsets[key]:offsets[key] + sizes[key]] = basis[:, j]
                columns.append(col)
        return columns

    def strongest_terms(self) -> dict[str, dict]:
        """Per target family: the library term with the most evidence on top of the final model (the graph's
        score test), its p-value adjusted over the effective number of library tests."""
        generic = self.generic_candidates()
        if not generic:
            return {}
        m_eff = self.library_tests(generic)
        out = {}
        for trial in sorted(self.score_many(generic, self.fit), key=lambda t: t.evidence_order):
            label = trial.candidate.label
            if label not in out:
                term = trial.candidate.term
                out[label] = {"driver": term.driver, "form": term.form, "p_value": min(1.0, trial.p_value * m_eff),
                              "meaning": trial.candidate.meaning, "test": "score test on the graph",
                              **({"second_driver": term.second} if term.second else {})}
        return out

    # --- the result ----------------------------------------------------------------------------------------

    def result(self) -> AuditResult:
        self.progress("testing what remains in the final model's residuals")
        strongest = self.strongest_terms() if self.offers_terms else {}
        remaining = remaining_structure(self.fit, self.alpha, self.inflation(self.fit), strongest)
        return AuditResult(self.system.name, self.system.base_model, self.findings, self.effects, self.base_fit,
                           self.fit, self.history, self.fits, list(self.rejected.values()), remaining, self.notes)


def _same_polynomial(a: Trial, b: Trial) -> bool:
    """Both polynomials (``poly1``..``poly3``) of the same single driver on the same family: nested shapes."""
    ta, tb = a.candidate.term, b.candidate.term
    return (ta is not None and tb is not None and ta.form.startswith("poly") and tb.form.startswith("poly")
            and ta.second is None and tb.second is None and ta.driver == tb.driver
            and a.candidate.label == b.candidate.label)


def _adds_nothing_over_lower_degree(trial: Trial, trials: list[Trial]) -> bool:
    """A ``poly2``/``poly3`` whose rank gain over the model is no larger than the next lower degree's in the same
    driver and target: its extra columns are directions the model already has, so it says what the lower
    polynomial says, and only rounding decides which of the two scores higher (measured on a scan: a cubic in
    range with a rank gain of 1 at p = 2.1e-77 against the linear term's 2.3e-77; the cubic's estimate, three
    coefficients for one direction, was meaningless)."""
    term = trial.candidate.term
    if term is None or term.form not in ("poly2", "poly3"):
        return False
    lower = "poly1" if term.form == "poly2" else "poly2"
    # a lower degree the model already holds whole (rank gain 0) is reported with dof 1 and F = 0 (the tests'
    # max(gain, 1)): it adds no direction, so the higher degree's one is new (an encoder's diode response, whose
    # linear part the base gain holds: the quadratic in signal was left out as adding nothing)
    return any(t.candidate.term is not None and t.candidate.term.form == lower
               and t.candidate.term.driver == term.driver and t.candidate.term.second is None
               and t.candidate.label == trial.candidate.label and t.dof >= trial.dof and t.f_stat > 0.0
               for t in trials)


def _ambiguous_rivals(system, accepted_fit, trials, accepted, accepted_bic, previous_fit, threshold) -> list[dict]:
    """Other significant candidates that fit about as well alone and lose their evidence next to the accepted."""
    rivals = []
    significant = [t for t in trials if t.candidate != accepted and t.p_value < threshold]
    for trial, p_on_top in zip(significant, _p_values_on_top(system, accepted_fit, [t.candidate for t in significant])):
        if p_on_top < threshold:
            continue  # still significant on top of the accepted effect: a separate effect, not a rival
        alternative = system.fit(previous_fit.effects + (trial.candidate,))
        # in the sigmas the residuals show, and over the independent samples they hold (the score test's deflation
        # for residuals correlated in time: waves; a ship's 2 % gyro scale and the lever arm it resembles scored
        # F = 15.7 and 16.7 but their raw fits differed by ~30)
        hook = getattr(system, "residual_correlation", None)
        inflation = hook(accepted_fit) if hook else 1.0
        delta_chi2 = (alternative.rss - accepted_fit.rss) / variance_factor(accepted_fit) / inflation
        if alternative.bic() - accepted_bic < AMBIGUITY_BIC or delta_chi2 < AMBIGUITY_CHI2:
            rival = {"effect": trial.candidate.effect, "target": trial.candidate.label,
                     "delta_bic_vs_accepted": alternative.bic() - accepted_bic, "delta_chi2_vs_accepted": delta_chi2}
            term = trial.candidate.term
            if term is not None:  # which term: "unlisted" alone names none (a scan's time and range, 0.8 correlated)
                rival.update(driver=term.driver, form=term.form, meaning=trial.candidate.meaning)
                if term.second:
                    rival["second_driver"] = term.second
            rivals.append(rival)
    return rivals


def _p_values_on_top(system, fit: Fit, candidates: list[Candidate]) -> list[float]:
    """p-value of each candidate's score test on top of ``fit`` (no deflation: the rival test's own statistic).

    Library terms from one graph holding them all where the system builds one (a step after a strong effect
    leaves hundreds significant: one dense test each took 19 min on a real stationing file, the batch seconds)."""
    one, many = scorers(system)
    batched = [c for c in candidates if c.term is not None] if hasattr(system, "extend_all") else []
    p = {}
    if batched:
        graph, values, groups = system.extend_all(fit, batched)
        for cand, (f_stat, dof, dof_den) in zip(batched, many(graph, values, groups)):
            p[cand] = stats.f.sf(f_stat, dof, dof_den)
    for cand in candidates:
        if cand not in p:
            f_stat, dof, dof_den = one(*extend_one(system, fit, cand))
            p[cand] = stats.f.sf(f_stat, dof, dof_den)
    return [p[c] for c in candidates]


# --- what remains ------------------------------------------------------------------------------------------------

def driver_name(coordinate: str) -> str:
    """The plain name of a coordinate as a driver (``time_s`` -> ``time``)."""
    return "time" if coordinate in ("time_s", "t_s") else coordinate


def family_coordinates(family: ResidualFamily) -> list[Coordinate]:
    """The coordinates a family carries, as library drivers (time, channels, angles, state quantities)."""
    n = family.physical.shape[0]
    out = []
    for name, values in family.coordinates.items():
        values = np.asarray(values, dtype=float)
        if values.shape != (n,):
            continue
        kind = ("time" if driver_name(name) == "time" else "channel" if name in family.channels
                else "angle" if name in family.angles else "state")
        out.append(Coordinate(driver_name(name), values, kind=kind))
    return out


def remaining_structure(fit: Fit, alpha: float = FAMILY_ALPHA, inflation: float = 1.0,
                        strongest: dict | None = None) -> dict:
    """Per residual family of the final model: is what is left white noise, or does structure remain?

    Whiteness: Ljung-Box on each time-ordered whitened component (the smallest p, Bonferroni over components).
    Strongest remaining term: given in ``strongest`` (label -> the graph's score test of the library, where the
    system fits terms), else every library term of the family's coordinates regressed on each component's
    whitened residual (:func:`selfcal.audit.terms.residual_score`, a lower bound of the graph's score test),
    F deflated by the residuals' correlation inflation, p Bonferroni-adjusted over the effective number of
    terms and the components.  ``structure_remains`` when either is below ``alpha``; for residuals the
    system knows to be correlated (inflation > 1) the whiteness test is reported but does not decide.
    """
    strongest = strongest or {}
    from selfcal.audit.diagnostics import ljung_box
    out = {}
    for fam in fit.families:
        w = np.asarray(fam.whitened, dtype=float)
        w = w[:, None] if w.ndim == 1 else w
        coordinates = family_coordinates(fam)
        time = next((c for c in coordinates if c.kind == "time"), None)
        order = np.argsort(time.values, kind="stable") if time is not None else np.arange(len(w))
        k = w.shape[1]
        lb = [ljung_box(w[order, j])[2] for j in range(k)]
        lb = [p for p in lb if np.isfinite(p)]
        whiteness_p = float(min(1.0, min(lb) * len(lb))) if lb else None
        usable = [c for c in coordinates if c.usable is None]
        best = strongest.get(fam.label)
        candidates = [] if best else library.terms_for(usable, w[order] if time is not None else None,
                                                       time.values[order] if time is not None else None)
        if candidates:
            columns = {t: t.columns({c.name: c.values for c in usable}) for t in candidates}
            m_eff = max(library.effective_number([col[:, 0] for col in columns.values()]), 1.0) * k
            for j in range(k):
                for term, col in columns.items():
                    f_stat, dof, dof_den = library.residual_score(w[:, j], col)
                    f_stat, dof_den = f_stat / inflation, max(int(dof_den / inflation), 1)
                    p = min(1.0, term.search_corrected(library.f_pvalue(f_stat, dof, dof_den)) * m_eff)
                    if best is None or p < best["p_value"]:
                        best = {"driver": term.driver, "form": term.form, "component": j, "p_value": p,
                                "test": "regression on the residual",
                                **({"second_driver": term.second} if term.second else {})}
        structure = (best is not None and best["p_value"] < alpha) or (
            inflation <= 1.0 and whiteness_p is not None and whiteness_p < alpha)
        out[fam.label] = {"verdict": "structure_remains" if structure else "noise_floor",
                          "whiteness_p": whiteness_p, "strongest": best, "n": int(len(w))}
    return out
