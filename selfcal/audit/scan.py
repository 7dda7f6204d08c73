"""The mobile scan (``--system scan``, patent 001) for the audit.

Base model (``error15``): the patent's 15 INS error terms, sphere centres free, the nominal sphere radius and
the calibrated camera-IMU extrinsic and clock; the clock poses are the corrected INS poses
(:func:`selfcal.graphs.scan.build_collapsed`: the INS jitter marginalised into each clock's covariance, which
keeps the score tests to tens of variables).

Catalog (each one extra variable block of :mod:`selfcal.graphs.scan`):

=====================  ==================================================================  ==================
effect                 signature in the sphere residuals                                   estimate (units)
=====================  ==================================================================  ==================
``time_offset``        profiles shifted by the motion over dt: a sphere sheared by the     ``dt_s`` (s)
                       vehicle's sway/roll rate (t_ins = t_cam + dt)
``extrinsic_rotation`` profiles turned about the sensor: shear along track; separable from  ``angles`` (rad)
                       the INS attitude error only where the attitude varies
``sphere_radius``      a radial offset common to every point of every sphere               ``dR_m`` (m)
``accel_scale``        velocity error proportional to the speed change: spheres stretched   ``scale`` (1)
                       along track unlike a bias would
``gyro_scale``         attitude error proportional to the rotation so far                  ``scale`` (1)
=====================  ==================================================================  ==================

Residual family: ``scan0/sphere`` (m), one radial residual per point of set B, coordinates: time, speed, angular
rate.  Folds interleave the spheres (even / odd in the order the scan reaches them): a held-out sphere is
predicted with the error terms (and effect) fitted on the others, its centre re-fitted at the known radius;
contiguous halves would make every fold an extrapolation of the inertial drift over half the scan.
"""
from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from selfcal.audit.engine import Candidate, Fit, ResidualFamily, variance_factor
from selfcal.graphs import scan as gs
from selfcal.core.solve import dense_marginals, optimize
from selfcal.models import scan as ms
from selfcal.core.sphere import SphereNotFoundError, fit_sphere

MEANINGS = {
    "time_offset": "the camera clock and the INS clock are offset: a profile stamped t was taken at INS time t + dt",
    "extrinsic_rotation": "the stereo sensor is rotated relative to the IMU beyond its calibration: "
                          "R_IV,true = R_IV Exp(angles)",
    "sphere_radius": "the spheres' true radius differs from the nominal one by dR",
    "accel_scale": "the INS accelerometer scale factors are off: f~ = (I + diag(scale)) f + b_a",
    "gyro_scale": "the INS gyro scale factors are off: w~ = (I + diag(scale)) w + b_g",
}
COORDINATE = {"time_offset": "angular rate", "extrinsic_rotation": "time", "sphere_radius": "point",
              "accel_scale": "speed", "gyro_scale": "angular rate"}


class ScanAudit:
    name = "scan"
    base_model = "error15"
    base_effects: tuple = ()
    folds = 2

    def __init__(self, problem: gs.ScanProblem, sensor: str = "scan0"):
        self.problem = problem
        self.sensor = sensor
        spheres = sorted({o.sphere for o in problem.observations},
                         key=lambda j: min(o.clock for o in problem.observations if o.sphere == j))
        self._order = {j: i for i, j in enumerate(spheres)}

    def candidates(self) -> list[Candidate]:
        return [Candidate(e, self.sensor, MEANINGS[e], "sphere", COORDINATE[e]) for e in MEANINGS]

    def _part(self, fold, heldout: bool = False) -> gs.ScanProblem:
        if fold is None:
            return self.problem
        keep = [o for o in self.problem.observations if (self._order[o.sphere] % 2 == fold) == heldout]
        return replace(self.problem, observations=keep)

    @staticmethod
    def _model(effects) -> gs.ScanModel:
        return gs.ScanModel(tuple(c.effect for c in effects))

    def fit(self, effects, fold=None) -> Fit:
        model = self._model(effects)
        problem = self._part(fold)
        graph, values = gs.build_collapsed(problem, model)
        values = optimize(graph, values, max_iterations=50)
        families = [self._family(problem, self._residuals(problem, graph, values))]
        return Fit(tuple(effects), graph, values, families, {"model": model, "fold": fold, "problem": problem})

    @staticmethod
    def _residuals(problem, graph, values) -> list[np.ndarray]:
        """Sphere residuals (m) per observation: the collapsed graph holds the priors first, then one
        sphere factor per observation in order."""
        n_prior = graph.size() - len(problem.observations)
        return [graph.at(n_prior + i).unwhitenedError(values) for i in range(len(problem.observations))]

    def _family(self, problem, residuals) -> ResidualFamily:
        e = np.concatenate(residuals)
        sig = np.concatenate([o.sigmas_m for o in problem.observations])
        t = np.concatenate([np.full(len(o.sigmas_m), problem.clock_t_s[o.clock]) for o in problem.observations])
        speed = np.linalg.norm(np.column_stack([np.interp(t, problem.ins_t_s, problem.ins_v[:, j])
                                                for j in range(3)]), axis=1)
        rate = np.linalg.norm(np.column_stack([np.interp(t, problem.ins_t_s, problem.ins_gyro[:, j])
                                               for j in range(3)]), axis=1)
        return ResidualFamily(self.sensor, "sphere", "m", (e / sig)[:, None], e[:, None],
                              {"time_s": t, "speed": speed, "angular rate": rate, "point": np.arange(len(e), dtype=float)})

    def extend(self, fit: Fit, candidate: Candidate):
        model = self._model(fit.effects + (candidate,))
        graph, _ = gs.build_collapsed(fit.context["problem"], model)
        values = gtsam.Values(fit.values)
        key, dim = gs.EXT_KEYS[candidate.effect], gs.EXT_DIM[candidate.effect]
        values.insert(key, np.zeros(dim))
        return graph, values, [(key, np.arange(dim))]

    def _solution(self, fit: Fit) -> gs.ScanSolution:
        values, model = fit.values, fit.context["model"]
        ext = {n: (values.atVector(gs.EXT_KEYS[n]) * gs.EXTENSION_SCALE[n], None) for n in model.extensions}
        return gs.ScanSolution(values.atVector(gs.THETA) * self.problem.prior_sigmas, None, None, None, ext)

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        """Held-out spheres: clock poses from the fitted error terms (no tie freedom), centre re-fitted."""
        problem = self._part(fold, heldout=True)
        sol = self._solution(fit)
        clocks = problem.b_clocks()
        R, r = gs.corrected_clock_poses(problem, sol, clocks)
        row = {m: i for i, m in enumerate(clocks)}
        R_IV = problem.imu_R_vision
        if "extrinsic_rotation" in sol.extensions:
            R_IV = R_IV @ ms.so3.exp(sol.extensions["extrinsic_rotation"][0])
        radius = problem.radius_m + (sol.extensions["sphere_radius"][0][0] if "sphere_radius" in sol.extensions else 0.0)
        residuals, kept = [], []
        for j in sorted({o.sphere for o in problem.observations}):
            obs = [o for o in problem.observations if o.sphere == j]
            pts = [ms.world_points(R[row[o.clock]], r[row[o.clock]], R_IV, problem.imu_t_vision, o.vision_p)
                   for o in obs]
            try:
                c = fit_sphere(np.concatenate(pts), radius_m=radius).center_m
            except SphereNotFoundError:
                continue
            residuals += [np.linalg.norm(p - c, axis=1) - radius for p in pts]
            kept += obs
        return [self._family(replace(problem, observations=kept), residuals)] if residuals else []

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        """Value and 1-sigma; the covariance scaled by the a-posteriori variance factor when it exceeds 1."""
        key = gs.EXT_KEYS[candidate.effect]
        cov = dense_marginals(fit.graph, fit.values, [key], candidate.effect)[key]
        s = gs.EXTENSION_SCALE[candidate.effect] * np.sqrt(max(1.0, variance_factor(fit)))
        value = fit.values.atVector(key) * gs.EXTENSION_SCALE[candidate.effect]
        sigma = np.sqrt(np.diag(cov)) * s
        name = {"time_offset": "dt_s", "sphere_radius": "dR_m", "extrinsic_rotation": "angles"}.get(
            candidate.effect, "scale")
        if value.size == 1:
            return {name: float(value[0])}, {name: float(sigma[0])}
        return {name: value.tolist()}, {name: sigma.tolist()}
