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

Pipeline: non-finite points dropped (counted) -> voxel downsampling -> normals (KD-tree) -> the largest
planes by RANSAC (open3d ``segment_plane``), removed -> DBSCAN clusters of the rest -> per cluster robust
sphere RANSAC (:func:`selfcal.core.sphere.ransac_sphere`, radius within bounds), candidates kept if their
points' normals point radially -> each sphere refitted on the full-resolution points near it
(:func:`fit_sphere`) -> planes refitted on the full-resolution points near them (total least squares:
smallest eigenvector of their covariance) -> distances to the reference mesh by open3d ``RaycastingScene`` closest points.

The spec format is documented in ``docs/qc.md`` (:mod:`selfcal.pipelines.qc.spec`).
"""
from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
import numpy as np
import open3d as o3d

from selfcal.io.pointcloud import LoadedCloud, PointCloudError, points_of
from selfcal.core.sphere import (SphereFit, SphereNotFoundError, fit_sphere, ransac_sphere,
                                   sphere_residuals_m)
from selfcal.pipelines.qc.spec import PlaneSpec, QCSpec, QCSpecError, ReferenceSpec, SphereSpec

__all__ = ["QCSpec", "QCSpecError", "Check", "QCResult", "run_qc", "detect_spheres", "evaluate_sphere",
           "evaluate_plane", "signed_distances_to_mesh", "trimmed_range"]

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
class SphereResult:
    """A detected sphere: its full-resolution fit and the VDI/VDE 2634-2 figures."""

    name: str
    fit: SphereFit
    centre_fit: SphereFit
    n_detection_inliers: int
    normal_consistency: float
    form_error_m: float
    size_error_m: float | None
    one_sided: bool
    target_distance_m: float | None = None


@dataclass
class PlaneResult:
    """A plane found in the scan and its flatness."""

    name: str
    normal: np.ndarray
    offset_m: float
    n_points: int
    flatness_m: float
    rms_m: float


@dataclass
class DeviationResult:
    """Signed distances of the scan from the reference mesh."""

    n_evaluated: int
    n_off_reference: int
    rms_m: float
    mean_m: float
    p95_abs_m: float
    max_abs_m: float
    distances_m: np.ndarray = field(repr=False)
    points_m: np.ndarray = field(repr=False)


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

    @property
    def verdict(self) -> str:
        """``fail`` if any check failed; ``incomplete`` if none failed but a toleranced check could not run;
        ``reported`` if the spec gives no tolerance at all (figures only); ``pass`` otherwise."""
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
                "deviation": dev, "warnings": self.warnings, "seconds": self.seconds}


def _check(name, value, tolerance, note="", absolute=True, unit="m") -> Check:
    if value is None or not np.isfinite(value):
        return Check(name, None, tolerance, None, unit, note)
    passed = None if tolerance is None else bool((abs(value) if absolute else value) <= tolerance)
    return Check(name, float(value), tolerance, passed, unit, note)


# ---------------------------------------------------------------------------------------------- detection

@dataclass
class SphereCandidate:
    """A sphere found on the (downsampled) detection cloud."""

    fit: SphereFit
    n_inliers: int
    normal_consistency: float


def trimmed_range(residuals_m: np.ndarray, exclude_fraction: float) -> float:
    """Range (max - min) of residuals after leaving out the ``exclude_fraction`` with the largest |e|."""
    e = np.asarray(residuals_m, dtype=float)
    n_drop = int(np.floor(exclude_fraction * len(e)))
    if n_drop:
        # the n_drop largest |e| by a partial sort (O(N): planes hold millions of points)
        keep = np.argpartition(np.abs(e), len(e) - n_drop - 1)[:len(e) - n_drop]
        e = e[keep]
    return float(e.max() - e.min())


def find_planes(cloud: o3d.geometry.PointCloud, spec: PlaneSpec, count: int,
                seed: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
    """Up to ``count`` planes, largest first, by RANSAC (open3d ``segment_plane``).

    Returns the plane models ``(a, b, c, d)`` (``a x + b y + c z + d = 0``, unit normal) and, per point, the
    index of the plane it lies on (-1: none).
    """
    o3d.utility.random.seed(seed)
    on_plane = np.full(len(cloud.points), -1, dtype=int)
    models = []
    remaining = np.arange(len(cloud.points))
    rest = cloud
    for _ in range(count):
        if len(remaining) < max(spec.min_points, 3):
            break
        model, idx = rest.segment_plane(spec.threshold_m, 3, 1000)
        if len(idx) < spec.min_points:
            break
        model = np.asarray(model, dtype=float)
        models.append(model / np.linalg.norm(model[:3]))
        on_plane[remaining[idx]] = len(models) - 1
        rest = rest.select_by_index(idx, invert=True)
        remaining = np.delete(remaining, idx)
    return models, on_plane


def detect_spheres(cloud: o3d.geometry.PointCloud, spec: QCSpec, warnings: list[str] | None = None,
                   on_plane: np.ndarray | None = None) -> list[SphereCandidate]:
    """Sphere candidates in a cloud: planes removed, DBSCAN clusters, RANSAC per cluster, normal check.

    Parameters
    ----------
    cloud : open3d.geometry.PointCloud
        The detection cloud (already downsampled); normals are estimated here if it has none.
    spec : QCSpec
        ``detection``, ``planes`` (how many to remove) and ``spheres`` (radius bounds, threshold, count).
    warnings : list of str, optional
        Receives one line per rejected candidate.
    on_plane : np.ndarray of bool, optional
        Points already found on planes (:func:`find_planes`); found here when not given.

    Returns
    -------
    list of SphereCandidate
        Best first (most inliers); at most ``spheres.count`` when the spec gives it.
    """
    warnings = warnings if warnings is not None else []
    det, sph = spec.detection, spec.spheres
    if not cloud.has_normals():
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=det.normal_radius_m, max_nn=30))
    if on_plane is None:
        _, plane_index = find_planes(cloud, spec.planes, spec.planes.remove_for_detection, spec.seed)
        on_plane = plane_index >= 0
    keep = np.flatnonzero(~on_plane)
    rest = cloud.select_by_index(keep.tolist())
    if len(rest.points) < sph.min_points:
        return []
    labels = np.asarray(rest.cluster_dbscan(det.dbscan_eps_m, det.dbscan_min_points))
    pts, normals = points_of(rest), np.asarray(rest.normals)
    lo, hi = sph.bounds()
    rng = np.random.default_rng(spec.seed)
    candidates = []
    for label in range(labels.max() + 1 if len(labels) else 0):
        idx = np.flatnonzero(labels == label)
        for _ in range(det.max_spheres_per_cluster):
            if len(idx) < sph.min_points:
                break
            q = pts[idx]
            # a cluster much larger than a sphere is tried too (a sphere on a curved wall), but it must hold
            # a sphere's worth of points
            try:
                fit, inl = ransac_sphere(q, radius_m=None, threshold_m=sph.ransac_threshold_m, rng=rng,
                                         min_inliers=sph.min_points, radius_bounds_m=(lo, hi))
            except SphereNotFoundError:
                break
            u = (q[inl] - fit.center_m) / np.linalg.norm(q[inl] - fit.center_m, axis=1)[:, None]
            consistency = float(np.mean(np.abs(np.einsum("ij,ij->i", u, normals[idx][inl])) >= np.cos(np.radians(30))))
            if consistency >= sph.min_normal_consistency:
                candidates.append(SphereCandidate(fit, int(inl.sum()), consistency))
            else:
                warnings.append(f"sphere candidate r={fit.radius_m:.4g} m at {np.round(fit.center_m, 3).tolist()} "
                                f"rejected: only {consistency:.0%} of its points have radial normals")
            idx = idx[~inl]
    candidates.sort(key=lambda c: -c.n_inliers)
    if sph.count is not None and len(candidates) > sph.count:
        for c in candidates[sph.count:]:
            warnings.append(f"extra sphere candidate r={c.fit.radius_m:.4g} m at "
                            f"{np.round(c.fit.center_m, 3).tolist()} ({c.n_inliers} points) ignored: spec expects "
                            f"{sph.count}")
        candidates = candidates[:sph.count]
    return candidates


def _in_box(points_m: np.ndarray, centre_m: np.ndarray, half_m: float) -> np.ndarray:
    """Points within a cube about a centre: one coordinate at a time, each on the survivors of the last
    (three full-size temporaries of 10 M points would cost more than the sphere fit)."""
    idx = np.flatnonzero(np.abs(points_m[:, 0] - centre_m[0]) <= half_m)
    for k in (1, 2):
        idx = idx[np.abs(points_m[idx, k] - centre_m[k]) <= half_m]
    return points_m[idx]


def evaluate_sphere(points_m: np.ndarray, candidate: SphereCandidate, spec: SphereSpec, name: str) -> SphereResult:
    """Refit a detected sphere on the full-resolution points within the evaluation gate; PF, PS, centre.

    The free-radius fit gives PF and PS.  When the sphere is seen from one side only (cap narrower than
    ``min_cap_deg``) its radius and its centre along the view axis are not separable: PS is not evaluated
    and, with a nominal radius, the centre comes from the known-radius fit.
    """
    gate = spec.gate()
    c, r = candidate.fit.center_m, candidate.fit.radius_m
    near = _in_box(points_m, c, r + gate)
    for _ in range(2):  # re-select once around the refined sphere
        sel = np.abs(sphere_residuals_m(near, c, r)) <= gate
        if np.count_nonzero(sel) < 5:
            raise SphereNotFoundError(f"{name}: only {np.count_nonzero(sel)} points near the detected sphere")
        fit = fit_sphere(near[sel])
        c, r = fit.center_m, fit.radius_m
    e = sphere_residuals_m(near[sel], c, r)
    one_sided = fit.coverage.one_sided(spec.min_cap_deg)
    centre_fit = fit
    size = None
    if spec.nominal_radius_m is not None:
        if one_sided:
            centre_fit = fit_sphere(near[sel], radius_m=spec.nominal_radius_m)
        else:
            size = 2.0 * (fit.radius_m - spec.nominal_radius_m)
    return SphereResult(name=name, fit=fit, centre_fit=centre_fit, n_detection_inliers=candidate.n_inliers,
                        normal_consistency=candidate.normal_consistency,
                        form_error_m=trimmed_range(e, spec.form_exclude_fraction), size_error_m=size,
                        one_sided=one_sided)


def evaluate_plane(points_m: np.ndarray, model: np.ndarray, spec: PlaneSpec, name: str) -> PlaneResult:
    """Refit a RANSAC plane on the full-resolution points within the gate (total least squares: the normal is
    the eigenvector of the smallest eigenvalue of the points' covariance); flatness = trimmed range of the
    distances.  Distances are taken about the RANSAC plane, so the covariance needs one pass and no copy
    of the (millions of) plane points."""
    # einsum, not BLAS: a threaded matrix-vector product over 10 M points stalls on a shared machine
    d = np.einsum("ij,j->i", points_m, model[:3]) + model[3]
    sel = np.flatnonzero(np.abs(d) <= spec.gate())
    if len(sel) < 3:
        raise DegeneratePlaneError(f"{name}: fewer than 3 points near the plane")
    q = points_m[sel]
    mean = q.mean(axis=0)
    q -= mean  # q is a copy (fancy indexing): centred in place
    w, v = np.linalg.eigh(np.einsum("ni,nj->ij", q, q) / len(q))
    normal = v[:, 0] * (1.0 if v[:, 0] @ model[:3] >= 0 else -1.0)
    dist = np.einsum("ij,j->i", q, normal)
    return PlaneResult(name=name, normal=normal, offset_m=float(-normal @ mean), n_points=len(sel),
                       flatness_m=trimmed_range(dist, spec.form_exclude_fraction),
                       rms_m=float(np.sqrt(np.mean(dist**2))))


class DegeneratePlaneError(ValueError):
    """A detected plane left too few points at full resolution (internal; reported as a warning)."""


# ------------------------------------------------------------------------------------------------ deviation

def signed_distances_to_mesh(points_m: np.ndarray, mesh: o3d.geometry.TriangleMesh) -> np.ndarray:
    """Signed distance of each point from a triangle mesh (m; + on the side the face normal points to).

    open3d ``RaycastingScene.compute_closest_points`` gives the nearest surface point and its triangle's
    normal; the magnitude is the Euclidean distance and the sign that of ``(p - q) . n``.  Unlike
    ``compute_signed_distance`` (ray parity) this holds for open meshes (a tunnel section, a wall).
    Coordinates are shifted to the mesh centroid first: the scene works in float32, which would lose
    millimetres at survey coordinates.
    """
    vertices = np.asarray(mesh.vertices)
    origin = vertices.mean(axis=0)
    shifted = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices - origin), mesh.triangles)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(shifted))
    q = np.ascontiguousarray(points_m - origin, dtype=np.float32)
    out = scene.compute_closest_points(o3d.core.Tensor(q))
    diff = q - out["points"].numpy()
    dist = np.linalg.norm(diff, axis=1)
    sign = np.sign(np.einsum("ij,ij->i", diff, out["primitive_normals"].numpy()))
    return np.where(sign < 0, -dist, dist).astype(np.float64)


def evaluate_deviation(points_m: np.ndarray, mesh: o3d.geometry.TriangleMesh, spec: ReferenceSpec,
                       rng: np.random.Generator) -> DeviationResult:
    """Deviation statistics of the scan from the reference; points farther than ``max_distance_m`` are
    not on the reference (clutter, mounts) and are counted, not evaluated."""
    pts = points_m
    if spec.max_points and len(pts) > spec.max_points:
        pts = pts[np.sort(rng.choice(len(pts), spec.max_points, replace=False))]
    d = signed_distances_to_mesh(pts, mesh)
    on = np.abs(d) <= spec.max_distance_m
    if not on.any():
        return DeviationResult(0, len(d), np.nan, np.nan, np.nan, np.nan, d[:0], pts[:0])
    a = np.abs(d[on])
    return DeviationResult(n_evaluated=int(on.sum()), n_off_reference=int((~on).sum()),
                           rms_m=float(np.sqrt(np.mean(d[on] ** 2))), mean_m=float(d[on].mean()),
                           p95_abs_m=float(np.percentile(a, 95)), max_abs_m=float(a.max()),
                           distances_m=d[on], points_m=pts[on])


# --------------------------------------------------------------------------------------------------- the run

def _match_targets(results: list[SphereResult], spec: SphereSpec, warnings: list[str]) -> None:
    """Name detected spheres after the nearest target within ``match_radius_m`` (greedy, closest first)."""
    if not spec.targets:
        return
    gate = spec.match_radius_m if spec.match_radius_m is not None else 2.0 * (spec.nominal_radius_m or np.inf)
    pairs = sorted((float(np.linalg.norm(s.centre_fit.center_m - t.centre_m)), i, j)
                   for i, s in enumerate(results) for j, t in enumerate(spec.targets))
    used_s, used_t = set(), set()
    for dist, i, j in pairs:
        if i in used_s or j in used_t or dist > gate:
            continue
        used_s.add(i)
        used_t.add(j)
        results[i].name = spec.targets[j].name
        results[i].target_distance_m = dist
    for j, t in enumerate(spec.targets):
        if j not in used_t:
            warnings.append(f"sphere {t.name}: not found within {gate:.3g} m of its nominal centre "
                            f"{np.round(t.centre_m, 4).tolist()}")


def run_qc(loaded: LoadedCloud, spec: QCSpec, reference: o3d.geometry.TriangleMesh | None = None,
           reference_name: str | None = None, progress=log.info) -> QCResult:
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
        Receives one line per stage.

    Returns
    -------
    QCResult
    """
    timings: dict[str, float] = {}
    warnings: list[str] = []
    checks: list[Check] = []
    tol = spec.tolerances
    t0 = time.perf_counter()
    points = points_of(loaded.cloud)
    if len(points) == 0:
        raise PointCloudError(f"{loaded.path}: no finite points to check")
    if loaded.n_nonfinite:
        warnings.append(f"{loaded.n_nonfinite} of {loaded.n_read} points were non-finite (NaN/inf) and were "
                        "left out")

    t = time.perf_counter()
    det = loaded.cloud.voxel_down_sample(spec.detection.voxel_m) if spec.detection.voxel_m > 0 else loaded.cloud
    det = o3d.geometry.PointCloud(det)  # normals are added to a copy, never to the caller's cloud
    det.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=spec.detection.normal_radius_m, max_nn=30))
    timings["downsample_normals"] = time.perf_counter() - t
    progress(f"detection cloud: {len(det.points)} of {len(points)} points (voxel {spec.detection.voxel_m} m)")

    # planes: found once, on the detection cloud; removed before sphere clustering, evaluated for flatness
    t = time.perf_counter()
    plane_models, plane_index = find_planes(det, spec.planes, max(spec.planes.remove_for_detection,
                                                                  spec.planes.evaluate), spec.seed)
    on_plane = (plane_index >= 0) & (plane_index < spec.planes.remove_for_detection)
    timings["plane_detection"] = time.perf_counter() - t

    # spheres
    t = time.perf_counter()
    spheres: list[SphereResult] = []
    try:
        candidates = detect_spheres(det, spec, warnings, on_plane)
    except SphereNotFoundError as err:
        candidates = []
        warnings.append(f"sphere detection failed: {err}")
    for k, cand in enumerate(candidates):
        try:
            spheres.append(evaluate_sphere(points, cand, spec.spheres, f"S{k + 1}"))
        except SphereNotFoundError as err:
            warnings.append(f"sphere S{k + 1}: {err}")
    _match_targets(spheres, spec.spheres, warnings)
    spheres.sort(key=lambda sp: sp.name)
    timings["spheres"] = time.perf_counter() - t
    progress(f"{len(spheres)} sphere(s) in {timings['spheres']:.1f} s")
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
        if s.one_sided:
            note = (f"seen from one side only (cap {cap:.0f} deg < {spec.spheres.min_cap_deg:.0f} deg): radius and "
                    "centre are not separable, size not evaluated"
                    + ("; centre from the nominal radius" if spec.spheres.nominal_radius_m else ""))
            warnings.append(f"sphere {s.name}: {note}")
            checks.append(_check(f"probing error of size PS {s.name}", None, tol.probing_size_m, note))
        elif s.size_error_m is None:
            checks.append(_check(f"probing error of size PS {s.name}", None, tol.probing_size_m,
                                 "no nominal radius in the spec"))
        else:
            checks.append(_check(f"probing error of size PS {s.name}", s.size_error_m, tol.probing_size_m,
                                 f"D = {2 * s.fit.radius_m:.5g} m vs {2 * spec.spheres.nominal_radius_m:.5g} m "
                                 f"(+-{2 * s.fit.radius_sigma_m:.2g})"))
    by_name = {s.name: s for s in spheres}
    for a, b, length in spec.spheres.pairs():
        if a in by_name and b in by_name:
            ca, cb = by_name[a].centre_fit, by_name[b].centre_fit
            diff = ca.center_m - cb.center_m
            g = diff / np.linalg.norm(diff)
            sigma = float(np.sqrt(g @ (ca.covariance[:3, :3] + cb.covariance[:3, :3]) @ g))
            checks.append(_check(f"sphere-spacing error SD {a}-{b}", float(np.linalg.norm(diff)) - length,
                                 tol.sphere_spacing_m, f"L = {length:.6g} m, 1-sigma {sigma:.2g} m"))
        else:
            missing = [n for n in (a, b) if n not in by_name]
            checks.append(_check(f"sphere-spacing error SD {a}-{b}", None, tol.sphere_spacing_m,
                                 f"sphere(s) {', '.join(missing)} not found"))

    # planes
    t = time.perf_counter()
    planes: list[PlaneResult] = []
    if spec.planes.evaluate > 0:
        for k, model in enumerate(plane_models[:spec.planes.evaluate]):
            try:
                planes.append(evaluate_plane(points, model, spec.planes, f"P{k + 1}"))
            except DegeneratePlaneError as err:
                warnings.append(str(err))
        if not planes:
            note = f"no plane of at least {spec.planes.min_points} points (within {spec.planes.threshold_m} m)"
            checks.append(_check("flatness F", None, tol.flatness_m, note))
        for p in planes:
            checks.append(_check(f"flatness F {p.name}", p.flatness_m, tol.flatness_m,
                                 f"{p.n_points} points, RMS {p.rms_m:.3g} m", absolute=False))
    timings["planes"] = time.perf_counter() - t

    # deviation from the reference
    t = time.perf_counter()
    deviation = None
    if reference is None:
        for name, limit in (("deviation RMS", tol.deviation_rms_m), ("deviation |d| p95", tol.deviation_p95_m),
                            ("deviation |d| max", tol.deviation_max_m)):
            if limit is not None:
                checks.append(_check(name, None, limit, "no reference mesh given"))
    else:
        deviation = evaluate_deviation(points, reference, spec.reference, np.random.default_rng(spec.seed))
        n_all = deviation.n_evaluated + deviation.n_off_reference
        cover = deviation.n_evaluated / n_all
        note = f"{deviation.n_evaluated} points within {spec.reference.max_distance_m} m of the reference"
        if deviation.n_evaluated == 0:
            warnings.append(f"no scan point within {spec.reference.max_distance_m} m of the reference mesh: "
                            "wrong frame or wrong mesh?")
        checks.append(_check("deviation RMS", deviation.rms_m, tol.deviation_rms_m, note, absolute=False))
        checks.append(_check("deviation |d| p95", deviation.p95_abs_m, tol.deviation_p95_m, absolute=False))
        checks.append(_check("deviation |d| max", deviation.max_abs_m, tol.deviation_max_m, absolute=False))
        checks.append(Check("points on the reference", cover, tol.reference_coverage,
                            None if tol.reference_coverage is None else bool(cover >= tol.reference_coverage),
                            unit="fraction", note=f"{deviation.n_off_reference} points farther than "
                                                  f"{spec.reference.max_distance_m} m (clutter, mounts, or errors)"))
    timings["deviation"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0
    return QCResult(scan=str(loaded.path), reference=reference_name, n_points=len(points),
                    n_nonfinite=loaded.n_nonfinite, spheres=spheres, planes=planes, deviation=deviation,
                    checks=checks, warnings=warnings, seconds=timings, spec=spec)
