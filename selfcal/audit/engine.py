"""The audit engine: find what a fitted model gets wrong, name the cause, extend the model, measure the gain.

Any system plugs in through :class:`AuditSystem`: it fits a factor graph for a set of effects (on all data or
on the training half of a fold), returns whitened residual families with their coordinates, and offers a
catalog of candidate effects.  The engine is the same for every system:

1. Evidence for each candidate is a score (Lagrange-multiplier) test on the linearised graph: the drop in
   whitened residual sum of squares that one Gauss–Newton step with the candidate's extra variables would
   give, as an F statistic against the residual variance.  It needs no refit, so every candidate is ranked.
2. Candidates significant at ``alpha / m`` (Bonferroni over the m candidates still open) are refitted in
   order of evidence; one is accepted only if it lowers the BIC AND the held-out residual (cross-validated
   over contiguous blocks in time: all families whitened, and its own target family in physical units), so
   an effect must predict data it was not fitted to.
3. Repeat until nothing significant is left.  No finding is a valid answer.
4. When another candidate explains the data about as well as the accepted one (BIC within 6, "strong
   evidence" on Kass & Raftery's scale) and loses its own evidence once the accepted one is in, the finding
   records the ambiguity instead of hiding it.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Protocol

import gtsam
import numpy as np
from scipy import stats

from selfcal.core.solve import dense_jacobian

log = logging.getLogger(__name__)

FAMILY_ALPHA = 1e-3  # family-wise false-finding probability per search step: a false finding sends a user
# recalibrating for nothing, so it is kept rare (about 2 % of 20 null recordings may show one)
AMBIGUITY_BIC = 6.0


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

    @property
    def key(self) -> str:
        return f"{self.effect}@{self.sensor}:{self.target}"


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
        :func:`score_test`."""

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        """Residual families of the held-out part of ``fold``, predicted with ``fit`` (trained on the rest)."""

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        """The candidate's estimate and 1-sigma in the contract's keys and units."""


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

    def to_json(self) -> dict:
        """The audit contract of ARCHITECTURE.md (extra keys are additions, never changes)."""
        final = [self.base_model] + [c.effect for c in self.final_effects if c not in self.base_fit.effects]
        return {"system": self.system, "base_model": self.base_model, "findings": self.findings,
                "final_model": final,
                "residual_rms": {f.label: f.rms for f in self.final_fit.families}}


def _heldout(system: AuditSystem, effects) -> tuple[float, dict[str, float]]:
    """Held-out whitened RSS over all families and physical RMS per family label, summed over folds."""
    rss, sq, count = 0.0, {}, {}
    for fold in range(system.folds):
        fit = system.fit(effects, fold)
        for fam in system.heldout(fit, fold):
            rss += float(np.sum(fam.whitened**2))
            sq[fam.label] = sq.get(fam.label, 0.0) + float(np.sum(fam.physical**2))
            count[fam.label] = count.get(fam.label, 0) + fam.physical.size
    return rss, {label: np.sqrt(sq[label] / count[label]) for label in sq}


def run_audit(system: AuditSystem, max_findings: int = 8, alpha: float = FAMILY_ALPHA, progress=None) -> AuditResult:
    """Search the catalog for effects the data show, one accepted extension at a time."""
    effects = tuple(system.base_effects)
    fit = system.fit(effects)
    base_fit = fit
    fits = [fit]
    heldout_rss, heldout_rms = _heldout(system, effects)
    findings, history = [], []
    for step in range(max_findings):
        open_candidates = [c for c in system.candidates() if c not in effects]
        if not open_candidates:
            break
        trials = []
        # residuals correlated in time (waves, vibration) hold fewer independent samples than rows: a system
        # that knows it gives the variance inflation 1 + 2 sum rho_k, and the F test uses the effective sizes
        inflation = system.residual_correlation(fit) if hasattr(system, "residual_correlation") else 1.0
        for cand in open_candidates:
            f_stat, dof, dof_den = score_test(*system.extend(fit, cand))
            f_stat, dof_den = f_stat / inflation, max(int(dof_den / inflation), 1)
            trials.append(Trial(cand, f_stat, float(stats.f.sf(f_stat, dof, dof_den)), dof))
        trials.sort(key=lambda t: t.p_value)
        threshold = alpha / len(open_candidates)
        if progress:
            progress(f"step {step + 1}: {len(trials)} candidates, best {trials[0].candidate.key} p={trials[0].p_value:.3g}")
        accepted = None
        tried = []
        for trial in (t for t in trials if t.p_value < threshold):
            new_effects = effects + (trial.candidate,)
            new_fit = system.fit(new_effects)
            new_heldout_rss, new_heldout_rms = _heldout(system, new_effects)
            delta_bic = new_fit.bic() - fit.bic()
            tried.append((trial, new_fit, delta_bic))
            log.info("%s: F=%.3g p=%.3g dBIC=%.1f heldout %.4g -> %.4g", trial.candidate.key, trial.f_stat,
                     trial.p_value, delta_bic, heldout_rss, new_heldout_rss)
            label = f"{trial.candidate.sensor}/{trial.candidate.target}"
            target_held = new_heldout_rms.get(label, 0.0) <= heldout_rms.get(label, np.inf)
            if delta_bic < 0 and new_heldout_rss < heldout_rss and target_held:
                accepted = (trial, new_fit, delta_bic, new_heldout_rss, new_heldout_rms)
                break
        history.append({"step": step + 1, "threshold": threshold,
                        "trials": [{"candidate": t.candidate.key, "F": t.f_stat, "p_value": t.p_value} for t in trials],
                        "accepted": accepted[0].candidate.key if accepted else None})
        if accepted is None:
            break
        trial, new_fit, delta_bic, new_heldout_rss, new_heldout_rms = accepted
        cand = trial.candidate
        estimate, std = system.estimate(new_fit, cand)
        target_before = fit.family(cand.target, cand.sensor)
        target_after = new_fit.family(cand.target, cand.sensor)
        label = f"{cand.sensor}/{cand.target}"
        finding = {
            "effect": cand.effect, "sensor": cand.sensor, "estimate": estimate, "std": std,
            "evidence": {"diagnostic": f"score test: {label} residual vs {cand.coordinate}",
                         "statistic": trial.f_stat, "p_value": trial.p_value},
            "gain": {"rms_before": target_before.rms if target_before else None,
                     "rms_after": target_after.rms if target_after else None,
                     "delta_bic": delta_bic,
                     "heldout_rms_before": heldout_rms.get(label), "heldout_rms_after": new_heldout_rms.get(label)},
            "meaning": cand.meaning, "target": label,
        }
        rivals = _ambiguous_rivals(system, new_fit, trials, cand, new_fit.bic(), fit, threshold)
        if rivals:
            finding["ambiguous_with"] = rivals
        findings.append(finding)
        effects = effects + (cand,)
        fit, heldout_rss, heldout_rms = new_fit, new_heldout_rss, new_heldout_rms
        fits.append(fit)
    # estimates and sigmas come from the final model: an effect accepted later changes the earlier ones
    # (gains stay as measured at the step each effect was accepted)
    for finding, cand in zip(findings, [c for c in effects if c not in base_fit.effects]):
        finding["estimate"], finding["std"] = system.estimate(fit, cand)
    return AuditResult(system.name, system.base_model, findings, effects, base_fit, fit, history, fits)


def _ambiguous_rivals(system, accepted_fit, trials, accepted, accepted_bic, previous_fit, threshold) -> list[dict]:
    """Other significant candidates that fit about as well alone and lose their evidence next to the accepted."""
    rivals = []
    for trial in trials:
        if trial.candidate == accepted or trial.p_value >= threshold:
            continue
        f_stat, dof, dof_den = score_test(*system.extend(accepted_fit, trial.candidate))
        if stats.f.sf(f_stat, dof, dof_den) < threshold:
            continue  # still significant on top of the accepted effect: a separate effect, not a rival
        alternative = system.fit(previous_fit.effects + (trial.candidate,))
        if alternative.bic() - accepted_bic < AMBIGUITY_BIC:
            rivals.append({"effect": trial.candidate.effect, "target": f"{trial.candidate.sensor}/{trial.candidate.target}",
                           "delta_bic_vs_accepted": alternative.bic() - accepted_bic})
    return rivals
