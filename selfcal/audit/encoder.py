"""The optical angle encoder (``--system encoder``) for the audit.

Base model (``ml``): the patent's image model as calibrated by :mod:`selfcal.graphs.encoder.calibration` -- edges,
positions, ``p, q``, aperture, dark level, a smooth illumination profile per frame (so light intensity drift
from frame to frame is already in the base).  Catalog (only effects the data can identify are offered):

``prnu``               per-diode gain: ``a_j = a0 + (1 + g_j) I T``; ``g`` orthogonal to the illumination basis
                       (a gain shaped like the light profile is the light profile).  Estimate: ``rms`` of g.
``temperature_scale``  ``p`` linear in the ``temperature`` channel: ``p (1 + k (T - T_mean))``; offered when the
                       temperature varies.  Estimate: ``k_per_degC``.
``eccentricity``       code centre off the axis ``(eps_x, eps_y)`` (code radii); offered only when
                       :func:`selfcal.graphs.encoder.calibration.eccentricity_observability` finds it separable from the
                       edges -- with free edges it is a once-per-revolution graduation error and is reported
                       in ``diagnostics`` as unobservable instead.

Not in the catalog: disk wobble (2/rev: a graduation-error pattern again), array tilt (in the base as ``q``),
light intensity drift (in the base).  Generic terms (:mod:`selfcal.audit.terms`): a signal offset ``k phi(x)``
per diode sample inside each frame factor, in the drivers ``signal`` (counts: the base fit's predicted signal, a
diode response that is not linear), ``diode`` (index), ``position`` (disk angle, rad: harmonics offered; the free
edges absorb what is a graduation error) and ``temperature`` where there is one.  Residual family: ``signal`` (counts) of each array, one row per diode
sample; coordinates: diode index, position, temperature.  Folds interleave the positions (even/odd), so each
half still covers the whole disk; a held-out frame is fitted for its own position and light profile with the
trained parameters held fixed.
"""
from __future__ import annotations

import math

import gtsam
import numpy as np

from selfcal.audit import terms as library
from selfcal.audit.engine import Candidate, Fit, ResidualFamily, variance_factor
from selfcal.audit.terms import Coordinate
from selfcal.core.solve import joint_covariance
from selfcal.graphs.encoder import calibration as ge

MAX_ROWS = 60_000  # diode samples the audit fits: above it, every k-th position (each fit and score test is
# linear in the rows; the positions left still cover the disk)

MEANINGS = {
    "prnu": "per-diode gain non-uniformity of the array (photo-response non-uniformity)",
    "temperature_scale": "image scale p changes with temperature (thermal expansion of the optics / housing)",
    "eccentricity": "code centre offset from the rotation axis (once-per-revolution angle error)",
}


class EncoderAudit:
    name = "encoder"
    folds = 2
    base_model = "ml"
    # tens of thousands of diode samples: score tests from the normal equations, not the dense Jacobian (the
    # gauge edge is a constant and every edge has a prior, so the base graph is full rank)
    information_form = True

    def __init__(self, problem: ge.Problem, start: dict | None = None, max_rows: int | None = None):
        self.problem = problem
        self.start = start or {}
        self.base_effects = ()
        used = problem.used_positions()
        n = problem.arrays[0].n
        step = max(1, math.ceil(used.size * n * len(problem.arrays) / (max_rows or MAX_ROWS)))
        self.positions = used[::step]
        base = self._solve(self._frames(None), ge.EncoderModel(), None)
        self.base_values = base[0]
        self.edges = base[1]
        self.diagnostics = {}
        est = ge._estimate(problem, ge.EncoderModel(), base[2], base[3], base[0], base[1], covariance=False)
        obs = ge.eccentricity_observability(problem, est)
        self.eccentricity_observable = obs.observable
        self.diagnostics["eccentricity"] = {"observable": obs.observable, "information_fraction":
                                            obs.information_fraction, "meaning": obs.reason}
        temps = [a.temperature_degC for a in problem.arrays if a.temperature_degC is not None]
        self.temperature_varies = bool(temps) and float(np.ptp(np.concatenate(temps))) > 0.5
        self._drivers, self._rows = self._driver_values(base[2], base[3], base[0])
        self._keys_of = library.TermKeys("u")

    # -- the generic term library ----------------------------------------------------------------------------
    def _driver_values(self, graph, layout, values):
        """Per array, every driver over its rows (frames of the whole run in order, n diodes each), and each
        frame's rows.  ``signal`` is what the base fit predicts (the measured one carries the noise)."""
        res = ge.residuals(graph, values, len(layout.frames))
        drivers, rows, count = {}, {}, {}
        for i, (k, J) in enumerate(layout.frames):
            arr = self.problem.arrays[k]
            d = drivers.setdefault(k, {"signal": [], "diode": [], "position": [], "temperature": []})
            d["signal"].append(res[i] + arr.frames[J])
            d["diode"].append(np.arange(arr.n, dtype=float))
            d["position"].append(np.full(arr.n, self.problem.beta0[J]))
            if arr.temperature_degC is not None:
                d["temperature"].append(np.full(arr.n, arr.temperature_degC[J]))
            start = count.get(k, 0)
            rows[(k, J)] = slice(start, start + arr.n)
            count[k] = start + arr.n
        return ({k: {n: np.concatenate(v) for n, v in d.items() if v} for k, d in drivers.items()}, rows)

    def term_coordinates(self, fit: Fit | None = None) -> dict[tuple[str, str], list[Coordinate]]:
        units = {"signal": "counts", "diode": "", "position": "rad", "temperature": "degC"}
        # the signal is a "level": its gain drifting with temperature is the per-frame illumination of the base, so
        # a product signal x temperature would only be a dark-level drift (a0 (T - T0)) in a misleading unit
        kinds = {"signal": "level", "diode": "state", "position": "angle", "temperature": "channel"}
        return {(self.problem.arrays[k].name, "signal"): [Coordinate(n, v, units[n], kinds[n]) for n, v in d.items()]
                for k, d in self._drivers.items()}

    def catalog_term(self, candidate: Candidate) -> None:
        return None  # no catalog effect of the encoder is a signal offset in one driver

    def _array(self, candidate: Candidate) -> int:
        return [a.name for a in self.problem.arrays].index(candidate.sensor)

    def _term_columns(self, effects) -> dict[tuple[int, int], list[tuple[int, np.ndarray]]]:
        out: dict[tuple[int, int], list] = {}
        for c in effects:
            if c.term is None:
                continue
            k = self._array(c)
            columns = c.term.columns(self._drivers[k])
            for (kk, J), rows in self._rows.items():
                if kk == k:
                    out.setdefault((k, J), []).extend(zip(self._keys_of(c.term), columns[rows].T))
        return out

    # -- candidates and models -------------------------------------------------------------------------------
    def candidates(self) -> list[Candidate]:
        out = []
        for k, arr in enumerate(self.problem.arrays):
            out.append(Candidate("prnu", arr.name, MEANINGS["prnu"], "signal", "diode"))
            if self.temperature_varies:
                out.append(Candidate("temperature_scale", arr.name, MEANINGS["temperature_scale"], "signal",
                                     "temperature"))
        if self.eccentricity_observable:
            out.append(Candidate("eccentricity", self.problem.arrays[0].name, MEANINGS["eccentricity"], "signal",
                                 "position"))
        return out

    def _model(self, effects) -> ge.EncoderModel:
        names = {c.effect for c in effects}
        return ge.EncoderModel(eccentricity="eccentricity" in names, temperature_scale="temperature_scale" in names,
                               prnu="prnu" in names)

    def _frames(self, fold):
        keep = self.positions if fold is None else self.positions[(np.arange(self.positions.size) % 2) != fold]
        return [(k, int(J)) for k in range(len(self.problem.arrays)) for J in keep if self.problem.decoded[k][J].ok]

    def _initial(self, model, frames):
        values = ge.initial_values(self.problem, model, self.start.get("edges"), self.start.get("beta"),
                                   self.start.get("geometry"))
        if hasattr(self, "base_values"):
            for key in self.base_values.keys():
                if values.exists(key):
                    values.update(key, self.base_values.atVector(key))
                else:
                    values.insert(key, self.base_values.atVector(key))
        keep = {J for _, J in frames}
        for key in list(values.keys()):
            sym = gtsam.Symbol(key)
            if sym.chr() == ord("b") and sym.index() not in keep:
                values.erase(key)
            elif sym.chr() == ord("c") and sym.index() % ge.ILLUMINATION_STRIDE not in keep:
                values.erase(key)
        return values

    def _solve(self, frames, model, fold, effects=()):
        edges = np.asarray(getattr(self, "edges", self.start.get("edges", self.problem.code.nominal_edge_angles())))
        values = self._initial(model, frames)
        columns = self._term_columns(effects) if effects else {}
        for key in {key for group in columns.values() for key, _ in group}:
            values.insert(key, np.zeros(1))
        graph, layout = ge.build_graph(self.problem, model, values, edges, frames, term_columns=columns)
        ge.insert_edges(values, layout.edge_vars, edges)
        for key in list(values.keys()):
            sym = gtsam.Symbol(key)
            if sym.chr() == ord("e") and sym.index() not in layout.edge_vars:
                values.erase(key)
        values, _ = ge.optimize(graph, values)
        return values, ge.edge_angles(values, self.problem.code, edges), graph, layout

    def fit(self, effects, fold=None) -> Fit:
        model = self._model(effects)
        frames = self._frames(fold)
        values, edges, graph, layout = self._solve(frames, model, fold, effects)
        return Fit(tuple(effects), graph, values, self._families(graph, layout, values),
                   {"model": model, "fold": fold, "frames": frames, "edges": edges, "layout": layout})

    def extend_all(self, fit: Fit, candidates):
        """One graph holding every candidate (new variables at zero): (graph, values, new columns each)."""
        effects = fit.effects + tuple(candidates)
        model = self._model(effects)
        values = gtsam.Values(fit.values)
        groups = []
        for cand in candidates:
            keys = [self._key(cand)] if cand.term is None else [(k, 1) for k in self._keys_of(cand.term)]
            for key, dim in keys:
                values.insert(key, np.zeros(dim))
            groups.append([(key, np.arange(dim)) for key, dim in keys])
        graph, layout = ge.build_graph(self.problem, model, values, fit.context["edges"], fit.context["frames"],
                                       term_columns=self._term_columns(effects))
        # an edge at the end of an image may come into view at the solution: a variable at its current angle
        ge.insert_edges(values, layout.edge_vars, fit.context["edges"])
        return graph, values, groups

    def _key(self, candidate):
        k = [a.name for a in self.problem.arrays].index(candidate.sensor)
        if candidate.effect == "prnu":
            return ge.GAIN(k), self.problem.arrays[k].n
        if candidate.effect == "temperature_scale":
            return ge.TEMPERATURE(k), 1
        return ge.ECCENTRICITY, 2

    # -- residuals -------------------------------------------------------------------------------------------
    def _families(self, graph, layout, values) -> list[ResidualFamily]:
        out = []
        res = ge.residuals(graph, values, len(layout.frames))
        for k, arr in enumerate(self.problem.arrays):
            rows = [(i, J) for i, (kk, J) in enumerate(layout.frames) if kk == k]
            if not rows:
                continue
            r = np.concatenate([res[i] for i, _ in rows])[:, None]
            diode = np.tile(np.arange(arr.n, dtype=float), len(rows))
            J = np.repeat([J for _, J in rows], arr.n)
            coords = {"diode": diode, "position": self.problem.beta0[J]}
            if arr.temperature_degC is not None:
                coords["temperature"] = arr.temperature_degC[J]
            out.append(ResidualFamily(arr.name, "signal", "counts", r / arr.noise_sigma, r, coords))
        return out

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        """Held-out frames: each one's position and light profile fitted with the trained parameters fixed."""
        held = self.positions[(np.arange(self.positions.size) % 2) == fold]
        frames = [(k, int(J)) for k in range(len(self.problem.arrays)) for J in held if self.problem.decoded[k][J].ok]
        model = fit.context["model"]
        values = gtsam.Values(fit.values)
        for k, J in frames:
            if not values.exists(ge.B(J)):
                values.insert(ge.B(J), np.array([self.problem.beta0[J]]))
            if not values.exists(ge.ILLUMINATION(k, J)):
                values.insert(ge.ILLUMINATION(k, J), self.base_values.atVector(ge.ILLUMINATION(k, J))
                              if self.base_values.exists(ge.ILLUMINATION(k, J)) else
                              ge._start_illumination(self.problem.arrays[k].frames[J], 0.0, 2))
        fixed = ge.EncoderModel(model.geometry_free, model.eccentricity, model.temperature_scale, model.prnu,
                                edges_fixed=True)
        graph, layout = ge.build_graph(self.problem, fixed, values, fit.context["edges"], frames,
                                       term_columns=self._term_columns(fit.effects))
        # only the per-frame unknowns move: pin every trained variable with a tight prior
        for key in fit.values.keys():
            v = fit.values.atVector(key)
            graph.add(gtsam.PriorFactorVector(key, v, gtsam.noiseModel.Isotropic.Sigma(v.size, 1e-9 * max(1.0, float(np.max(np.abs(v)))))))
        for key in list(values.keys()):
            sym = gtsam.Symbol(key)
            if sym.chr() == ord("e") and not fit.values.exists(key):
                values.erase(key)
        values, _ = ge.optimize(graph, values)
        return self._families(graph, layout, values)

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        if candidate.term is not None:
            keys = self._keys_of(candidate.term)
            joint = joint_covariance(fit.graph, fit.values, keys, "the audited term") * variance_factor(fit)
            units = {"signal": "counts", "diode": "", "position": "rad", "temperature": "degC"}
            estimate, std = library.describe(candidate.term, np.array([fit.values.atVector(k) for k in keys]), joint,
                                             self._drivers[self._array(candidate)], "counts",
                                             units[candidate.term.driver])
            estimate["target"] = f"{candidate.sensor}/signal"
            return estimate, std
        key, dim = self._key(candidate)
        scale = math.sqrt(variance_factor(fit))
        marginals = gtsam.Marginals(fit.graph, fit.values)
        value = fit.values.atVector(key)
        cov = marginals.marginalCovariance(key) * scale**2
        sigma = np.sqrt(np.diag(cov))
        if candidate.effect == "temperature_scale":
            return {"k_per_degC": float(value[0])}, {"k_per_degC": float(sigma[0])}
        if candidate.effect == "eccentricity":
            return {"eps": value.tolist()}, {"eps": sigma.tolist()}
        # size of the gain pattern: bias-corrected RMS, its sigma by the delta method
        ms = float(np.mean(value**2) - np.mean(np.diag(cov)))
        var_ms = float(4 * value @ cov @ value + 2 * np.sum(cov**2)) / value.size**2
        rms = math.sqrt(max(ms, 0.0))
        return ({"rms": rms, "gain": value.tolist()},
                {"rms": math.sqrt(var_ms) / (2 * max(rms, 1e-12)), "gain": sigma.tolist()})
