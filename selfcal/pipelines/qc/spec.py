"""The QC spec of ``selfcal qc``: what to look for in a scan and the tolerances it must meet (YAML).

Sections ``spheres``, ``planes``, ``detection``, ``reference``, ``tolerances``, ``prediction`` and ``seed``;
every length in metres; every key optional (a missing tolerance means the figure is reported, not judged).  The format, with
an example, is documented in ``docs/qc.md``.  Unknown keys are refused (a misspelt tolerance must not
silently pass a scan).  This module needs neither open3d nor the estimators, so the CLI can import its
error class cheaply.
"""
from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
import yaml

from selfcal.core.errors import SelfcalError


class QCSpecError(SelfcalError):
    """A QC spec file that cannot be used (unknown key, wrong type, inconsistent values)."""


# ----------------------------------------------------------------------------------------------- the spec

@dataclass
class SphereTarget:
    """A named sphere of the artefact at its nominal position (for matching detected spheres)."""

    name: str
    centre_m: np.ndarray


# Without a nominal radius or bounds, a sphere is a scanner's sphere target: reference spheres are made from 12.7 mm
# (1/2 in) to 500 mm radius (VDI/VDE 2634-2 asks for spheres of 0.1-0.2 x the measuring volume's diagonal); a vault
# or a wall fitted as a sphere of 3 m or 800 m is no target (the unbounded default reported 40 "spheres" in a tunnel
# with 10).
TARGET_RADIUS_RANGE_M = (0.005, 0.5)


@dataclass
class SphereSpec:
    """Sphere detection and evaluation settings (``spheres:`` in the spec YAML)."""

    nominal_radius_m: float | None = None
    radius_bounds_m: tuple[float, float] | None = None
    count: int | None = None
    ransac_threshold_m: float = 0.005
    evaluation_gate_m: float | None = None
    min_points: int = 50
    min_cap_deg: float = 60.0
    form_exclude_fraction: float = 0.003
    min_normal_consistency: float = 0.5
    targets: list[SphereTarget] = field(default_factory=list)
    match_radius_m: float | None = None
    distances: list[tuple[str, str, float]] = field(default_factory=list)

    def bounds(self) -> tuple[float, float]:
        if self.radius_bounds_m is not None:
            return self.radius_bounds_m
        if self.nominal_radius_m is not None:
            return 0.8 * self.nominal_radius_m, 1.2 * self.nominal_radius_m
        return TARGET_RADIUS_RANGE_M

    def gate(self) -> float:
        return self.evaluation_gate_m if self.evaluation_gate_m is not None else 3.0 * self.ransac_threshold_m

    def pairs(self) -> list[tuple[str, str, float]]:
        """Calibrated centre distances: the listed ones, else every pair of targets."""
        if self.distances:
            return self.distances
        return [(a.name, b.name, float(np.linalg.norm(a.centre_m - b.centre_m)))
                for a, b in itertools.combinations(self.targets, 2)]


@dataclass
class PlaneSpec:
    """Plane detection (removed before sphere clustering) and flatness (``planes:``)."""

    threshold_m: float = 0.005
    min_points: int = 1000
    remove_for_detection: int = 3
    evaluate: int = 1
    evaluation_gate_m: float | None = None
    form_exclude_fraction: float = 0.003

    def gate(self) -> float:
        return self.evaluation_gate_m if self.evaluation_gate_m is not None else 2.0 * self.threshold_m


@dataclass
class DetectionSpec:
    """Point-set processing before the fits (``detection:``)."""

    voxel_m: float = 0.005
    normal_radius_m: float = 0.02
    dbscan_eps_m: float = 0.02
    dbscan_min_points: int = 10
    max_spheres_per_cluster: int = 3


@dataclass
class ReferenceSpec:
    """Deviation from the reference mesh (``reference:``)."""

    max_distance_m: float = 0.05
    max_points: int = 0


@dataclass
class Tolerances:
    """Acceptance limits, metres (``tolerances:``); a missing limit means the figure is reported only."""

    sphere_spacing_m: float | None = None
    probing_form_m: float | None = None
    probing_size_m: float | None = None
    flatness_m: float | None = None
    deviation_rms_m: float | None = None
    deviation_p95_m: float | None = None
    deviation_max_m: float | None = None
    reference_coverage: float | None = None
    point_error_m: float | None = None  # a point's error, bound at prediction.confidence (needs a sigma map)


@dataclass
class PredictionSpec:
    """How the predicted accuracy of a corrected scan (per-point 1-sigma, PLY property ``sigma_m``) is judged
    (``prediction:``): a point is vouched for when ``z sigma <= tolerances.point_error_m`` with ``z`` the
    two-sided normal quantile of ``confidence``; the scan when at most ``max_fraction_unvouched`` of its points
    are not."""

    confidence: float = 0.95
    max_fraction_unvouched: float = 0.0


@dataclass
class QCSpec:
    """A QC spec: what to look for and the tolerances (see docs/qc.md for the YAML)."""

    spheres: SphereSpec = field(default_factory=SphereSpec)
    planes: PlaneSpec = field(default_factory=PlaneSpec)
    detection: DetectionSpec = field(default_factory=DetectionSpec)
    reference: ReferenceSpec = field(default_factory=ReferenceSpec)
    tolerances: Tolerances = field(default_factory=Tolerances)
    prediction: PredictionSpec = field(default_factory=PredictionSpec)
    seed: int = 0

    @classmethod
    def from_dict(cls, data: dict | None, source: str = "spec") -> QCSpec:
        data = dict(data or {})
        sections = {"spheres": SphereSpec, "planes": PlaneSpec, "detection": DetectionSpec,
                    "reference": ReferenceSpec, "tolerances": Tolerances, "prediction": PredictionSpec}
        unknown = set(data) - set(sections) - {"seed"}
        if unknown:
            raise QCSpecError(f"{source}: unknown section(s) {sorted(unknown)}; known: {sorted(sections)}, seed")
        built = {}
        for key, kind in sections.items():
            section = data.get(key) or {}
            if not isinstance(section, dict):
                raise QCSpecError(f"{source}: '{key}' must be a mapping")
            section = dict(section)
            names = {f.name for f in fields(kind)}
            bad = set(section) - names
            if bad:
                raise QCSpecError(f"{source}: unknown key(s) {sorted(bad)} in '{key}'; known: {sorted(names)}")
            if kind is SphereSpec:
                section = _sphere_section(section, source)
            try:
                built[key] = kind(**{k: _number(v) for k, v in section.items()})
            except (TypeError, ValueError) as err:
                raise QCSpecError(f"{source}: '{key}': {err}") from err
        spec = cls(**built, seed=int(data.get("seed", 0)))
        spec._validate(source)
        return spec

    @classmethod
    def from_yaml(cls, path) -> QCSpec:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such QC spec file")
        try:
            data = yaml.safe_load(path.read_text())
        except yaml.YAMLError as err:
            raise QCSpecError(f"{path}: not valid YAML ({' '.join(str(err).split())})") from err
        if data is not None and not isinstance(data, dict):
            raise QCSpecError(f"{path}: the spec must be a mapping of sections")
        return cls.from_dict(data, str(path))

    def _validate(self, source: str) -> None:
        s = self.spheres
        lo, hi = s.bounds()
        if not 0 <= lo < hi:
            raise QCSpecError(f"{source}: spheres.radius_bounds_m must be [low, high] with 0 <= low < high")
        for name, value in (("spheres.ransac_threshold_m", s.ransac_threshold_m),
                            ("planes.threshold_m", self.planes.threshold_m),
                            ("detection.dbscan_eps_m", self.detection.dbscan_eps_m),
                            ("detection.normal_radius_m", self.detection.normal_radius_m)):
            if not value > 0:
                raise QCSpecError(f"{source}: {name} must be > 0")
        names = {t.name for t in s.targets}
        for a, b, _ in s.distances:
            if a not in names or b not in names:
                raise QCSpecError(f"{source}: spheres.distances names {a!r}, {b!r}: not among targets {sorted(names)}")
        for name, value in asdict(self.tolerances).items():
            if value is not None and not value > 0:
                raise QCSpecError(f"{source}: tolerances.{name} must be > 0")
        if not 0 < self.prediction.confidence < 1 or not 0 <= self.prediction.max_fraction_unvouched < 1:
            raise QCSpecError(f"{source}: prediction.confidence must be in (0, 1) and "
                              "prediction.max_fraction_unvouched in [0, 1)")


def _number(v):
    """YAML reads ``1e-3`` (no dot) as a string: accept it as the number it means."""
    if isinstance(v, str):
        try:
            return float(v)
        except ValueError:
            return v
    return v


def _sphere_section(section: dict, source: str) -> dict:
    try:
        targets = [SphereTarget(str(t["name"]), np.asarray(t["centre_m"], dtype=float).reshape(3))
                   for t in section.pop("targets", None) or []]
        distances = [(str(d["between"][0]), str(d["between"][1]), float(d["distance_m"]))
                     for d in section.pop("distances", None) or []]
    except (KeyError, TypeError, ValueError, IndexError) as err:
        raise QCSpecError(f"{source}: spheres.targets need {{name, centre_m: [x, y, z]}} and spheres.distances "
                          f"{{between: [A, B], distance_m}} ({err!r})") from err
    if "radius_bounds_m" in section and section["radius_bounds_m"] is not None:
        section["radius_bounds_m"] = tuple(float(x) for x in section["radius_bounds_m"])
    return dict(section, targets=targets, distances=distances)
