"""Graph of sphere scans: one sphere target seen in several scenes (ranges) by one ranging sensor.

Variables: per scene its sphere centre ``c_s`` (``Vector3``, sensor frame); per scene a radius deviation ``r_s``
with a prior ``N(0, tau^2)`` (the target's own shape and the scene's view of it: an inflatable ball is no
reference sphere, and two scenes see different caps); as the model asks, a common radius error ``dR`` and a range
offset ``b``; the audit's generic terms as radius coefficients.  Each scene's returns are one factor
(:func:`selfcal.factors.qc.sphere_returns_factor`).

``tau`` is the scatter of the scenes' free-fit radii beyond their own noise about a line in range (the
DerSimonian-Laird moment estimator of a meta-regression): as Mallows' Cp takes sigma from the richest model,
the level comes from the model that already holds a range trend, so a trend does not hide in its own noise
level.  With ``tau = 0`` (scenes that agree within their noise) the ``r_s`` are left out.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from selfcal.core.errors import SelfcalError
from selfcal.core.solve import gaussian
from selfcal.core.sphere import SphereNotFoundError, fit_sphere
from selfcal.factors.qc import sphere_returns_factor
from selfcal.models.qc import MAX_INCIDENCE_RAD, incidence_angle_rad, range_residuals

RADIUS, RANGE_OFFSET = gtsam.symbol("R", 0), gtsam.symbol("b", 0)


def center_key(scene: int) -> int:
    return gtsam.symbol("c", scene)


def scene_radius_key(scene: int) -> int:
    return gtsam.symbol("r", scene)


class DegenerateScansError(SelfcalError):
    """Scans that cannot carry the audit (too few scenes, a scene without a fittable sphere)."""


@dataclass(frozen=True)
class SphereScene:
    """The returns of one scene on the sphere, with what the scene's own free fit says of them."""

    points_S_m: np.ndarray  # (N, 3) returns on the sphere (gated), sensor frame
    t_s: float  # when the scene was scanned (s from the first)
    sigmas_m: np.ndarray  # (N,) range noise of each return
    center0_m: np.ndarray  # free fit's centre (start value)
    radius_m: float  # free fit's radius
    radius_sigma_m: float
    channels: dict[str, float] = field(default_factory=dict)  # auxiliary columns of the scene's row

    @property
    def range_m(self) -> float:
        return float(np.linalg.norm(self.center0_m))


@dataclass(frozen=True)
class SphereScans:
    sensor: str
    scenes: tuple[SphereScene, ...]
    nominal_radius_m: float
    scene_sigma_m: float  # tau (see the module docstring)
    channel_units: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class SphereModel:
    radius: bool = False  # common radius error dR
    range_offset: bool = False  # range zero-point offset b


def scene_of(points_S_m, t_s: float = 0.0, channels: dict | None = None) -> SphereScene:
    """A scene from its returns on the sphere (gated by the caller): the free fit gives the start values; returns
    the free fit sees beyond ``MAX_INCIDENCE_RAD`` are left out (the range model is singular at the rim); the
    noise level is the RMS range residual of a free fit of the rest, dof-corrected, the same for every return."""
    p = np.asarray(points_S_m, dtype=float)
    try:
        fit = fit_sphere(p)
        p = p[incidence_angle_rad(p, fit.center_m, fit.radius_m) <= MAX_INCIDENCE_RAD]
        fit = fit_sphere(p)
    except SphereNotFoundError as err:
        raise DegenerateScansError(f"scene at t = {t_s:g} s: {err}") from None
    e = range_residuals(p, fit.center_m, fit.radius_m)
    sigma = float(np.sqrt(np.sum(e**2) / max(len(p) - 4, 1)))
    return SphereScene(p, float(t_s), np.full(len(p), sigma), fit.center_m, fit.radius_m, fit.radius_sigma_m,
                       dict(channels or {}))


def scene_scatter_m(scenes) -> float:
    """tau: DerSimonian-Laird between-scene scatter of the free-fit radii about a weighted line in range."""
    r = np.array([s.radius_m for s in scenes])
    w = 1.0 / np.array([s.radius_sigma_m for s in scenes]) ** 2
    X = np.column_stack([np.ones(len(r)), [s.range_m for s in scenes]])
    if len(r) <= X.shape[1] + 1:
        X = X[:, :1]
    XtW = X.T * w
    info_inv = np.linalg.pinv(XtW @ X)
    beta = info_inv @ XtW @ r
    q = float(np.sum(w * (r - X @ beta) ** 2))
    denominator = float(np.sum(w) - np.trace(info_inv @ (XtW * w) @ X))
    return float(np.sqrt(max(0.0, (q - (len(r) - X.shape[1])) / max(denominator, 1e-300))))


def scans_of(sensor: str, scenes, nominal_radius_m: float, channel_units: dict | None = None) -> SphereScans:
    scenes = tuple(scenes)
    if len(scenes) < 3:
        raise DegenerateScansError(f"{sensor}: {len(scenes)} scene(s) with the sphere; the audit needs at least 3 "
                                   "(a radius error and its scatter between scenes)")
    return SphereScans(sensor, scenes, float(nominal_radius_m), scene_scatter_m(scenes), dict(channel_units or {}))


def build(scans: SphereScans, model: SphereModel, scene_ids, term_columns=()):
    """(graph, start values) over the scenes ``scene_ids``; ``term_columns`` ``(key, [phi over scene s's returns
    for s in scene_ids])`` adds radius terms ``k phi``."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    common = ([RADIUS] if model.radius else [])
    for key in common + ([RANGE_OFFSET] if model.range_offset else []) + [k for k, _ in term_columns]:
        values.insert(key, np.zeros(1))
    tau = scans.scene_sigma_m
    for row, s in enumerate(scene_ids):
        scene = scans.scenes[s]
        radius_keys = list(common)
        if tau > 0.0:
            radius_keys.append(scene_radius_key(s))
            values.insert(scene_radius_key(s), np.zeros(1))
            graph.add(gtsam.PriorFactorVector(scene_radius_key(s), np.zeros(1), gaussian([tau])))
        values.insert(center_key(s), np.asarray(scene.center0_m, dtype=float))
        graph.add(sphere_returns_factor(
            gaussian(scene.sigmas_m), scene.points_S_m, center_key(s),
            scans.nominal_radius_m, radius_keys, RANGE_OFFSET if model.range_offset else None,
            [(key, phis[row]) for key, phis in term_columns]))
    return graph, values
