"""Use case ``selfcal qc``: quality control of a (corrected) scan in the manner of VDI/VDE 2634 part 2.

A scan (point cloud) and, optionally, a reference mesh of the object go in; out come the acceptance figures of
VDI/VDE 2634-2 that the scene supports, a deviation map, and pass/fail against the tolerances of a QC spec::

    probing error of form   PF = range of the radial residuals of a best-fit sphere (free radius)
    probing error of size   PS = D_measured - D_calibrated          (diameters, as the guideline states)
    sphere-spacing error    SD = |c_i - c_j| - L_ij                 (L_ij: calibrated centre distance)
    flatness                F  = range of the signed distances from a best-fit plane
    deviation               d  = signed distance of each scan point from the reference mesh (+: outside)

The guideline allows the 0.3 % of points with the largest residuals to be left out of PF and F
(``form_exclude_fraction``).  Each figure is a :class:`Check`; a figure the data cannot give (no sphere,
a sphere seen from one side only for PS, no plane, no reference) is reported as not checked, with the
reason, and everything else is still checked.

Pipeline (:func:`run_qc`, one named step each): non-finite points dropped (counted) -> detection on a
downsampled copy (:mod:`selfcal.pipelines.qc.detect`: normals, the largest planes by RANSAC, removed, DBSCAN
clusters of the rest, sphere RANSAC per cluster with a radial-normal check) -> the figures measured on the
full-resolution points (:mod:`selfcal.pipelines.qc.figures`: each sphere refitted near it for PF, PS and its
centre, planes refitted near them for F, distances to the reference mesh) -> one :class:`Check` per figure
(SD from the sphere centres here) -> the verdict (:attr:`QCResult.verdict`).

The spec format is documented in ``docs/qc.md`` (:mod:`selfcal.pipelines.qc.spec`).
"""
from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass

import numpy as np
import open3d as o3d

from selfcal.core.progress import quiet
from selfcal.io.pointcloud import LoadedCloud, PointCloudError, points_of
from selfcal.pipelines.qc.detect import detection_cloud, find_planes
from selfcal.pipelines.qc.figures import (DeviationResult, PlaneResult, SphereResult, measure_deviation,
                                          measure_planes, measure_spheres)
from selfcal.pipelines.qc.spec import QCSpec, QCSpecError, SphereSpec, Tolerances

__all__ = ["QCSpec", "QCSpecError", "Check", "QCResult", "PredictionResult", "prediction_check", "run_qc",
           "scan_points", "detection_planes", "sphere_checks", "sphere_spacing_checks", "flatness_checks",
           "deviation_checks"]

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------------ results

@dataclass
class Check:
    """One acceptance figure: its value, the tolerance, and pass (True), fail (False) or not checked (None)."""

    name: str
    value: float | None
    tolerance: float | None
    passed: bool | None
    unit: str = "m"
    note: str = ""

    @property
    def status(self) -> str:
        """``pass``, ``FAIL``, ``no tolerance`` (measured, not judged) or ``not checked`` (not measurable)."""
        if self.passed is not None:
            return "pass" if self.passed else "FAIL"
        return "not checked" if self.value is None else "no tolerance"


@dataclass
class PredictionResult:
    """The predicted accuracy map a corrected scan carries (per-point 1-sigma, PLY property ``sigma_m``), judged
    against ``tolerances.point_error_m`` at ``prediction.confidence``."""

    points_m: np.ndarray  # (N, 3) the scan's points (for the map)
    sigma_m: np.ndarray  # (N,) per point, m
    z: float  # bound = z sigma (two-sided normal quantile of the confidence)
    confidence: float
    tolerance_m: float | None
    fraction_unvouched: float | None  # points whose bound exceeds the tolerance (None without a tolerance)

    def to_json(self) -> dict:
        q = np.percentile(self.sigma_m, [50, 95, 100])
        return {"sigma_median_m": float(q[0]), "sigma_p95_m": float(q[1]), "sigma_max_m": float(q[2]),
                "confidence": self.confidence, "bound_factor": self.z, "tolerance_m": self.tolerance_m,
                "fraction_unvouched": self.fraction_unvouched}


@dataclass
class QCResult:
    """Everything ``selfcal qc`` measured; ``verdict`` is pass / fail / incomplete."""

    scan: str
    reference: str | None
    n_points: int
    n_nonfinite: int
    spheres: list[SphereResult]
    planes: list[PlaneResult]
    deviation: DeviationResult | None
    checks: list[Check]
    warnings: list[str]
    seconds: dict[str, float]
    spec: QCSpec
    prediction: PredictionResult | None = None

    @property
    def verdict(self) -> str:
        """``cannot be vouched for`` if the scan's own predicted accuracy does not meet the point tolerance
        (whatever the measured figures say: they are not to be trusted); else ``fail`` if any check failed;
        ``incomplete`` if none failed but a toleranced check could not run; ``reported`` if the spec gives no
        tolerance at all (figures only); ``pass`` otherwise."""
        if any(c.passed is False and c.name == VOUCH_CHECK for c in self.checks):
            return "cannot be vouched for"
        if any(c.passed is False for c in self.checks):
            return "fail"
        if any(c.passed is None and c.tolerance is not None for c in self.checks):
            return "incomplete"
        if not any(c.tolerance is not None for c in self.checks):
            return "reported"
        return "pass"

    def to_json(self) -> dict:
        def sphere(s: SphereResult) -> dict:
            return {"name": s.name, "centre_m": s.centre_fit.center_m.tolist(),
                    "centre_sigma_m": s.centre_fit.center_sigma_m.tolist(),
                    "radius_m": s.fit.radius_m, "radius_sigma_m": s.fit.radius_sigma_m,
                    "form_error_m": s.form_error_m, "size_error_m": s.size_error_m, "rms_m": s.fit.rms_m,
                    "n_points": s.fit.n_points, "cap_half_angle_deg": s.fit.coverage.cap_half_angle_deg,
                    "solid_angle_fraction": s.fit.coverage.solid_angle_fraction, "one_sided": s.one_sided,
                    "normal_consistency": s.normal_consistency, "target_distance_m": s.target_distance_m}
        dev = None
        if self.deviation is not None:
            d = self.deviation
            dev = {"n_evaluated": d.n_evaluated, "n_off_reference": d.n_off_reference, "rms_m": d.rms_m,
                   "mean_m": d.mean_m, "p95_abs_m": d.p95_abs_m, "max_abs_m": d.max_abs_m}
        return {"scan": self.scan, "reference": self.reference, "verdict": self.verdict,
                "n_points": self.n_points, "n_nonfinite": self.n_nonfinite,
                "checks": [asdict(c) for c in self.checks],
                "spheres": [sphere(s) for s in self.spheres],
                "planes": [{"name": p.name, "normal": p.normal.tolist(), "offset_m": p.offset_m,
                            "n_points": p.n_points, "flatness_m": p.flatness_m, "rms_m": p.rms_m}
                           for p in self.planes],
                "deviation": dev, "prediction": None if self.prediction is None else self.prediction.to_json(),
                "warnings": self.warnings, "seconds": self.seconds}


def _check(name, value, tolerance, note="", absolute=True, unit="m") -> Check:
    if value is None or not np.isfinite(value):
        return Check(name, None, tolerance, None, unit, note)
    passed = None if tolerance is None else bool((abs(value) if absolute else value) <= tolerance)
    return Check(name, float(value), tolerance, passed, unit, note)


# --------------------------------------------------------------------------------------------------- the run
# run_qc is a sequence of the steps below and of the measuring steps of figures.py; the checks come out in
# the order of the report (PF and PS per sphere, SD per pair, F per plane, deviation).

@contextmanager
def _timed(seconds: dict[str, float], stage: str, progress):
    """Announces the block as a stage (``progress``) and records its wall time as ``seconds[stage]``."""
    progress(stage.replace("_", " "))
    start = time.perf_counter()
    yield
    seconds[stage] = time.perf_counter() - start


def scan_points(loaded: LoadedCloud, warnings: list[str]) -> np.ndarray:
    """The scan's finite points (N, 3), m; points the reader dropped as non-finite are reported, not checked."""
    points = points_of(loaded.cloud)
    if len(points) == 0:
        raise PointCloudError(f"{loaded.path}: no finite points to check")
    if loaded.n_nonfinite:
        warnings.append(f"{loaded.n_nonfinite} of {loaded.n_read} points were non-finite (NaN/inf) and were "
                        "left out")
    return points


def detection_planes(det: o3d.geometry.PointCloud, spec: QCSpec) -> tuple[list[np.ndarray], np.ndarray]:
    """Planes found once, on the detection cloud, for two uses: the ``remove_for_detection`` largest are taken
    out before sphere clustering, the ``evaluate`` largest are measured for flatness.

    Returns the plane models (:func:`find_planes`) and the mask of detection points on a removed plane.
    """
    plane_models, plane_index = find_planes(det, spec.planes, max(spec.planes.remove_for_detection,
                                                                  spec.planes.evaluate), spec.seed)
    on_plane = (plane_index >= 0) & (plane_index < spec.planes.remove_for_detection)
    return plane_models, on_plane


def _size_check(s: SphereResult, spec: SphereSpec, tol: Tolerances, warnings: list[str]) -> Check:
    """Probing error of size PS = D_measured - D_calibrated of one sphere, where its size is measurable: not
    for a sphere seen from one side only (radius and centre inseparable), nor without a nominal radius."""
    name = f"probing error of size PS {s.name}"
    if s.one_sided:
        cap = s.fit.coverage.cap_half_angle_deg
        note = (f"seen from one side only (cap {cap:.0f} deg < {spec.min_cap_deg:.0f} deg): radius and "
                "centre are not separable, size not evaluated"
                + ("; centre from the nominal radius" if spec.nominal_radius_m else ""))
        warnings.append(f"sphere {s.name}: {note}")
        return _check(name, None, tol.probing_size_m, note)
    if s.size_error_m is None:
        return _check(name, None, tol.probing_size_m, "no nominal radius in the spec")
    return _check(name, s.size_error_m, tol.probing_size_m,
                  f"D = {2 * s.fit.radius_m:.5g} m vs {2 * spec.nominal_radius_m:.5g} m "
                  f"(+-{2 * s.fit.radius_sigma_m:.2g})")


def sphere_checks(spheres: list[SphereResult], spec: QCSpec, warnings: list[str]) -> list[Check]:
    """Probing error of form PF (range of the radial residuals, free radius) and of size PS per sphere; both
    reported as not checked, with the reason, when no sphere was found."""
    tol = spec.tolerances
    checks: list[Check] = []
    if not spheres:
        reason = ("no sphere found (radius bounds " + ", ".join(f"{b:.4g}" for b in spec.spheres.bounds())
                  + f" m, at least {spec.spheres.min_points} points)")
        warnings.append(reason)
        checks.append(_check("probing error of form PF", None, tol.probing_form_m, reason))
        checks.append(_check("probing error of size PS", None, tol.probing_size_m, reason))
    if spec.spheres.count is not None and 0 < len(spheres) < spec.spheres.count:
        warnings.append(f"{len(spheres)} of {spec.spheres.count} expected spheres found")
    for s in spheres:
        cap = s.fit.coverage.cap_half_angle_deg
        checks.append(_check(f"probing error of form PF {s.name}", s.form_error_m, tol.probing_form_m,
                             f"{s.fit.n_points} points, cap {cap:.0f} deg", absolute=False))
        checks.append(_size_check(s, spec.spheres, tol, warnings))
    return checks


def sphere_spacing_checks(spheres: list[SphereResult], spec: QCSpec) -> list[Check]:
    """Sphere-spacing error SD = |c_a - c_b| - L_ab for each calibrated pair of the spec.

    The note gives its 1-sigma from the two centres' covariances along the line between them,
    ``g^T (C_a + C_b) g`` with ``g = (c_a - c_b) / |c_a - c_b|`` (the centres are fitted independently).
    """
    by_name = {s.name: s for s in spheres}
    checks: list[Check] = []
    for a, b, length in spec.spheres.pairs():
        if a in by_name and b in by_name:
            ca, cb = by_name[a].centre_fit, by_name[b].centre_fit
            diff = ca.center_m - cb.center_m
            g = diff / np.linalg.norm(diff)
            sigma = float(np.sqrt(g @ (ca.covariance[:3, :3] + cb.covariance[:3, :3]) @ g))
            checks.append(_check(f"sphere-spacing error SD {a}-{b}", float(np.linalg.norm(diff)) - length,
                                 spec.tolerances.sphere_spacing_m, f"L = {length:.6g} m, 1-sigma {sigma:.2g} m"))
        else:
            missing = [n for n in (a, b) if n not in by_name]
            checks.append(_check(f"sphere-spacing error SD {a}-{b}", None, spec.tolerances.sphere_spacing_m,
                                 f"sphere(s) {', '.join(missing)} not found"))
    return checks


def flatness_checks(planes: list[PlaneResult], spec: QCSpec) -> list[Check]:
    """Flatness F (range of the distances from the best-fit plane) per plane; not checked when the spec asks
    for planes and none was found.  No check at all when the spec evaluates no plane."""
    if spec.planes.evaluate <= 0:
        return []
    tol = spec.tolerances
    checks: list[Check] = []
    if not planes:
        note = f"no plane of at least {spec.planes.min_points} points (within {spec.planes.threshold_m} m)"
        checks.append(_check("flatness F", None, tol.flatness_m, note))
    for p in planes:
        checks.append(_check(f"flatness F {p.name}", p.flatness_m, tol.flatness_m,
                             f"{p.n_points} points, RMS {p.rms_m:.3g} m", absolute=False))
    return checks


def deviation_checks(deviation: DeviationResult | None, spec: QCSpec) -> list[Check]:
    """RMS, 95th percentile and maximum of |d| over the points on the reference, and the fraction of points on
    it; without a reference, the toleranced deviation figures are reported as not checked."""
    tol = spec.tolerances
    if deviation is None:
        limits = (("deviation RMS", tol.deviation_rms_m), ("deviation |d| p95", tol.deviation_p95_m),
                  ("deviation |d| max", tol.deviation_max_m))
        return [_check(name, None, limit, "no reference mesh given") for name, limit in limits if limit is not None]
    max_distance_m = spec.reference.max_distance_m
    cover = deviation.n_evaluated / (deviation.n_evaluated + deviation.n_off_reference)
    note = f"{deviation.n_evaluated} points within {max_distance_m} m of the reference"
    return [_check("deviation RMS", deviation.rms_m, tol.deviation_rms_m, note, absolute=False),
            _check("deviation |d| p95", deviation.p95_abs_m, tol.deviation_p95_m, absolute=False),
            _check("deviation |d| max", deviation.max_abs_m, tol.deviation_max_m, absolute=False),
            Check("points on the reference", cover, tol.reference_coverage,
                  None if tol.reference_coverage is None else bool(cover >= tol.reference_coverage),
                  unit="fraction", note=f"{deviation.n_off_reference} points farther than "
                                        f"{max_distance_m} m (clutter, mounts, or errors)")]


VOUCH_CHECK = "points vouched for by the predicted accuracy"


def prediction_check(points_m: np.ndarray, sigma_m: np.ndarray | None,
                     spec: QCSpec) -> tuple[PredictionResult | None, list[Check]]:
    """The fraction of points whose predicted bound ``z sigma`` exceeds ``tolerances.point_error_m``, checked
    against ``prediction.max_fraction_unvouched`` (first of all checks: a scan that cannot be vouched for is
    not judged by its measured figures).  No sigma map: not checked when the spec has a point tolerance."""
    from scipy import stats
    tol = spec.tolerances.point_error_m
    if sigma_m is None:
        note = "the scan carries no predicted accuracy (PLY property sigma_m, written by 'selfcal smooth scan')"
        return None, ([] if tol is None else [Check(VOUCH_CHECK, None, spec.prediction.max_fraction_unvouched,
                                                    None, "fraction", note)])
    conf = spec.prediction.confidence
    z = float(stats.norm.ppf(0.5 + conf / 2))
    fraction = None if tol is None else float(np.mean(z * sigma_m > tol))
    result = PredictionResult(points_m, np.asarray(sigma_m, float), z, conf, tol, fraction)
    median, worst = np.median(sigma_m), np.max(sigma_m)
    if tol is None:
        return result, [Check("predicted point 1-sigma (max)", float(worst), None, None,
                              note=f"median {median * 1e3:.3g} mm; no tolerances.point_error_m to judge it")]
    note = (f"fraction of points whose {conf:.0%} bound ({z:.3g} sigma) exceeds {tol * 1e3:.4g} mm; "
            f"sigma median {median * 1e3:.3g} mm, max {worst * 1e3:.3g} mm")
    return result, [Check(VOUCH_CHECK, fraction, spec.prediction.max_fraction_unvouched,
                          fraction <= spec.prediction.max_fraction_unvouched, "fraction", note)]


def run_qc(loaded: LoadedCloud, spec: QCSpec, reference: o3d.geometry.TriangleMesh | None = None,
           reference_name: str | None = None, progress=quiet, point_sigma_m: np.ndarray | None = None) -> QCResult:
    """Quality control of a scan: every figure the scene supports, checked against the spec's tolerances.

    Parameters
    ----------
    loaded : LoadedCloud
        The scan (:func:`selfcal.io.pointcloud.read_point_cloud` with ``drop_nonfinite=True``).
    spec : QCSpec
        Detection settings and tolerances.
    reference : open3d.geometry.TriangleMesh, optional
        Reference mesh of the object, in the scan's frame.
    reference_name : str, optional
        For the report.
    progress : callable
        ``progress(stage)`` as each stage starts (:mod:`selfcal.core.progress`).
    point_sigma_m : (N,) array, optional
        The scan's predicted 1-sigma per point (:func:`selfcal.io.pointcloud.read_point_attribute`, ``sigma_m``),
        judged first (:func:`prediction_check`).

    Returns
    -------
    QCResult
        The figures, the checks and the warnings; ``verdict`` judges the checks.
    """
    seconds: dict[str, float] = {}
    warnings: list[str] = []
    start = time.perf_counter()
    points = scan_points(loaded, warnings)
    if point_sigma_m is not None and len(point_sigma_m) != len(points):
        raise PointCloudError(f"{loaded.path}: {len(point_sigma_m)} sigma_m values for {len(points)} points")
    prediction, checks = prediction_check(points, point_sigma_m, spec)
    if prediction is not None and prediction.fraction_unvouched:
        warnings.append(f"{prediction.fraction_unvouched:.1%} of the points cannot be vouched for: their predicted "
                        f"{prediction.confidence:.0%} bound exceeds {prediction.tolerance_m * 1e3:.4g} mm")
    with _timed(seconds, "downsample_normals", progress):
        det = detection_cloud(loaded.cloud, spec.detection)
    log.info(f"detection cloud: {len(det.points)} of {len(points)} points (voxel {spec.detection.voxel_m} m)")
    with _timed(seconds, "plane_detection", progress):
        plane_models, on_plane = detection_planes(det, spec)
    with _timed(seconds, "spheres", progress):
        spheres = measure_spheres(points, det, on_plane, spec, warnings)
    log.info(f"{len(spheres)} sphere(s) in {seconds['spheres']:.1f} s")
    checks += sphere_checks(spheres, spec, warnings) + sphere_spacing_checks(spheres, spec)
    with _timed(seconds, "planes", progress):
        planes = measure_planes(points, plane_models, spec.planes, warnings)
        checks += flatness_checks(planes, spec)
    with _timed(seconds, "deviation", progress):
        deviation = measure_deviation(points, reference, spec, warnings)
        checks += deviation_checks(deviation, spec)
    seconds["total"] = time.perf_counter() - start
    return QCResult(scan=str(loaded.path), reference=reference_name, n_points=len(points),
                    n_nonfinite=loaded.n_nonfinite, spheres=spheres, planes=planes, deviation=deviation,
                    checks=checks, warnings=warnings, seconds=seconds, spec=spec, prediction=prediction)
