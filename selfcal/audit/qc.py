"""Sphere scans for the audit (``--system qc``, base ``sphere``): one sphere target in several scenes.

Base model (``sphere``): per scene the sphere's centre, the nominal radius, a scene radius deviation with the
between-scene scatter ``tau`` as its prior (:mod:`selfcal.graphs.qc`).

Catalog:

==================  =================================================================  ==================
effect              signature in the radial residuals                                  estimate (units)
==================  =================================================================  ==================
``sphere_radius``   every scene's sphere bigger by the same dR: ranges short by dR/cos(i)  ``dR_m`` (m)
``range_offset``    every range read b too long: a constant the centres absorb but for    ``b_m`` (m)
                    the rays' spread; an apparent radius falling off as 1/range
==================  =================================================================  ==================

Residual family ``<sensor>/sphere`` (m), one range residual per return (:mod:`selfcal.models.qc`).  Drivers of the generic terms (radius
corrections ``k phi(x)``): ``range`` (m, of each return, as the scene's free fit predicts it), ``incidence`` (rad, from each scene's free fit),
``elevation`` and ``azimuth`` (rad, of each return), ``time`` (s, of the scene; skipped when the recording's
timestamps are only the scene order) and every auxiliary column of the scenes' rows.  Folds: scenes interleaved
in range order (both halves span the ranges); a held-out scene is predicted with the fitted radius model and its
centre re-fitted (its own deviation is unknown: zero).
"""
from __future__ import annotations

import gtsam
import numpy as np
from scipy.optimize import least_squares

from selfcal.audit import terms as library
from selfcal.audit.engine import Candidate, Fit, ResidualFamily, variance_factor
from selfcal.audit.terms import Coordinate
from selfcal.core.solve import joint_covariance, marginal_covariances, optimize
from selfcal.graphs import qc as gq
from selfcal.models import qc as mq

MEANINGS = {"sphere_radius": "the sphere's radius differs from its nominal value by dR",
            "range_offset": "the sensor reads every range b too long (range zero point offset)"}
KEYS = {"sphere_radius": (gq.RADIUS, "dR_m"), "range_offset": (gq.RANGE_OFFSET, "b_m")}
PLAUSIBLE = {"sphere_radius": 0.2, "range_offset": 0.5}  # |dR| / R0; |b| in m (beyond: another target, a wrong
# unit or another scanner, not an error of this one)
UNITS = {"range": "m", "incidence": "rad", "elevation": "rad", "azimuth": "rad", "time": "s"}


class SphereScansAudit:
    name = "qc"
    base_model = "sphere"
    base_effects: tuple = ()
    folds = 2

    def __init__(self, scans: gq.SphereScans, time_is_order: bool = False):
        self.scans = scans
        self.sensor = scans.sensor
        scenes = scans.scenes
        order = np.argsort([s.range_m for s in scenes])
        self._folds = [np.sort(order[0::2]), np.sort(order[1::2])]
        self._offsets = np.cumsum([0] + [len(s.points_S_m) for s in scenes])
        p = np.concatenate([s.points_S_m for s in scenes])
        # the range of a return as the free fit predicts it: the measured range carries the very noise the
        # residual does, and a term in it would fit that noise (F ~ 15 on null scans)
        predicted = [np.linalg.norm(s.points_S_m, axis=1) - mq.range_residuals(s.points_S_m, s.center0_m, s.radius_m)
                     for s in scenes]
        drivers = {"range": np.concatenate(predicted),
                   "incidence": np.concatenate([mq.incidence_angle_rad(s.points_S_m, s.center0_m, s.radius_m)
                                                for s in scenes]),
                   "elevation": np.arcsin(np.clip(p[:, 2] / np.linalg.norm(p, axis=1), -1, 1)),
                   "azimuth": np.arctan2(p[:, 1], p[:, 0])}
        self.notes = []
        if time_is_order:
            self.notes.append("time: the recording's timestamps only order the scenes; not offered as a driver")
        else:
            drivers["time"] = self._per_return([s.t_s for s in scenes])
        for name in sorted(set().union(*(s.channels for s in scenes))):
            drivers[name] = self._per_return([s.channels.get(name, np.nan) for s in scenes])
        self._drivers = drivers
        self._keys_of = library.TermKeys("k")

    def _per_return(self, per_scene) -> np.ndarray:
        return np.repeat(np.asarray(per_scene, dtype=float), np.diff(self._offsets))

    def _rows(self, scene_ids) -> np.ndarray:
        return np.concatenate([np.arange(self._offsets[s], self._offsets[s + 1]) for s in scene_ids])

    def candidates(self) -> list[Candidate]:
        return [Candidate(e, self.sensor, MEANINGS[e], "sphere", "range") for e in MEANINGS]

    # --- the generic term library -----------------------------------------------------------------------------

    def term_coordinates(self, fit: Fit | None = None) -> dict[tuple[str, str], list[Coordinate]]:
        angles = ("elevation", "azimuth")
        units = {**UNITS, **self.scans.channel_units}
        coordinates = [Coordinate(n, v, units.get(n, ""), "time" if n == "time" else
                                  "angle" if n in angles else "channel" if n in self.scans.channel_units else "state")
                       for n, v in self._drivers.items()]
        return {(self.sensor, "sphere"): coordinates}

    def catalog_term(self, candidate: Candidate) -> None:
        return None  # neither catalog effect is a single library term (dR is the constant the terms leave out)

    def _term_columns(self, effects, scene_ids) -> list[tuple[int, list[np.ndarray]]]:
        out = []
        for c in effects:
            if c.term is None:
                continue
            columns = c.term.columns(self._drivers)
            for key, column in zip(self._keys_of(c.term), columns.T):
                out.append((key, [column[self._offsets[s]:self._offsets[s + 1]] for s in scene_ids]))
        return out

    # --- fits -------------------------------------------------------------------------------------------------

    @staticmethod
    def _model(effects) -> gq.SphereModel:
        names = {c.effect for c in effects}
        return gq.SphereModel(radius="sphere_radius" in names, range_offset="range_offset" in names)

    def _scene_ids(self, fold) -> np.ndarray:
        return np.arange(len(self.scans.scenes)) if fold is None else self._folds[fold]

    def fit(self, effects, fold=None) -> Fit:
        scene_ids = self._scene_ids(fold)
        graph, values = gq.build(self.scans, self._model(effects), scene_ids, self._term_columns(effects, scene_ids))
        values = optimize(graph, values)
        return Fit(tuple(effects), graph, values, [self._family(graph, values, scene_ids)],
                   {"scene_ids": scene_ids})

    def _family(self, graph, values, scene_ids) -> ResidualFamily:
        factors = [graph.at(i) for i in range(graph.size()) if isinstance(graph.at(i), gtsam.CustomFactor)]
        physical = np.concatenate([f.unwhitenedError(values) for f in factors])
        sigma = np.concatenate([self.scans.scenes[s].sigmas_m for s in scene_ids])
        return self._residual_family(physical, sigma, scene_ids)

    def _residual_family(self, physical, sigma, scene_ids) -> ResidualFamily:
        rows = self._rows(scene_ids)
        coords = {n: v[rows] for n, v in self._drivers.items()}
        return ResidualFamily(self.sensor, "sphere", "m", (physical / sigma)[:, None], physical[:, None], coords,
                              tuple(self.scans.channel_units), ("elevation", "azimuth"))

    def extend_all(self, fit: Fit, candidates):
        """One graph holding every candidate (new variables at zero): (graph, values, new columns each)."""
        effects = fit.effects + tuple(candidates)
        scene_ids = fit.context["scene_ids"]
        graph, values = gq.build(self.scans, self._model(effects), scene_ids, self._term_columns(effects, scene_ids))
        for key in fit.values.keys():
            values.update(key, fit.values.atVector(key))
        groups = []
        for c in candidates:
            keys = [KEYS[c.effect][0]] if c.term is None else self._keys_of(c.term)
            groups.append([(key, np.arange(1)) for key in keys])
        return graph, values, groups

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        """Held-out scenes: radius from the fitted model (the scene's own deviation unknown: 0), centre re-fitted."""
        scene_ids = self._folds[1 - fold]
        values = fit.values
        radius = self.scans.nominal_radius_m + (values.atVector(gq.RADIUS)[0] if values.exists(gq.RADIUS) else 0.0)
        b = values.atVector(gq.RANGE_OFFSET)[0] if values.exists(gq.RANGE_OFFSET) else 0.0
        terms = self._term_columns(fit.effects, scene_ids)
        physical, sigma = [], []
        for row, s in enumerate(scene_ids):
            scene = self.scans.scenes[s]
            r = radius + sum((phis[row] * values.atVector(key)[0] for key, phis in terms), 0.0)

            def residuals(c, points=scene.points_S_m, r=r):
                return mq.range_residuals(points, c, r, b)

            def jacobian(c, points=scene.points_S_m, r=r):
                return mq.range_residuals(points, c, r, b, with_jacobians=True)[1]

            centre = least_squares(residuals, scene.center0_m, jac=jacobian, method="lm").x
            physical.append(residuals(centre))
            sigma.append(scene.sigmas_m)
        return [self._residual_family(np.concatenate(physical), np.concatenate(sigma), scene_ids)]

    # --- estimates --------------------------------------------------------------------------------------------

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        """Value and 1-sigma; the covariance scaled by the fit's variance factor (the returns' noise is the free
        fits' estimate, their form errors correlate neighbouring returns)."""
        vf = max(1.0, variance_factor(fit))
        if candidate.term is not None:
            keys = self._keys_of(candidate.term)
            joint = joint_covariance(fit.graph, fit.values, keys, "the audited term") * vf
            units = {**UNITS, **self.scans.channel_units}
            estimate, std = library.describe(candidate.term, np.array([fit.values.atVector(k) for k in keys]), joint,
                                             self._drivers, "m", units.get(candidate.term.driver, ""))
            estimate["target"] = f"{self.sensor}/sphere"
            return estimate, std
        key, name = KEYS[candidate.effect]
        cov = marginal_covariances(fit.graph, fit.values, [key], candidate.effect)[key] * vf
        return {name: float(fit.values.atVector(key)[0])}, {name: float(np.sqrt(cov[0, 0]))}

    def plausible(self, candidate: Candidate, estimate: dict) -> str | None:
        if candidate.term is not None:
            return None
        key, name = KEYS[candidate.effect]
        value = abs(estimate[name])
        limit = PLAUSIBLE[candidate.effect] * (self.scans.nominal_radius_m if name == "dR_m" else 1.0)
        if value > limit:
            return f"|{name}| = {value:.3g} m beyond the plausible {limit:.3g} m"
        return None
