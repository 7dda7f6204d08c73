"""The VDI/VDE 2634-2 figures of ``selfcal qc``, measured on the full-resolution scan.

Features found on the detection cloud (:mod:`selfcal.pipelines.qc.detect`) are refitted on the scan's own
points near them::

    probing error of form   PF = range of the radial residuals of a best-fit sphere (free radius)
    probing error of size   PS = D_measured - D_calibrated          (diameters, as the guideline states)
    flatness                F  = range of the signed distances from a best-fit plane (total least squares)
    deviation               d  = signed distance of each scan point from the reference mesh (+: outside)

PF and F leave out the ``form_exclude_fraction`` of points with the largest residuals (:func:`trimmed_range`,
0.3 % in the guideline).  Judging the figures against the tolerances is :mod:`selfcal.pipelines.qc.checks`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from selfcal.core.sphere import SphereFit, SphereNotFoundError, fit_sphere, sphere_residuals_m
from selfcal.pipelines.qc.detect import SphereCandidate, detect_spheres
from selfcal.pipelines.qc.spec import PlaneSpec, QCSpec, ReferenceSpec, SphereSpec

__all__ = ["SphereResult", "PlaneResult", "DeviationResult", "trimmed_range", "evaluate_sphere", "evaluate_plane",
           "signed_distances_to_mesh", "evaluate_deviation", "measure_spheres", "measure_planes",
           "measure_deviation"]


# ------------------------------------------------------------------------------------------------ results

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


# ------------------------------------------------------------------------------------------ sphere and plane

def trimmed_range(residuals_m: np.ndarray, exclude_fraction: float) -> float:
    """Range (max - min) of residuals after leaving out the ``exclude_fraction`` with the largest |e|."""
    e = np.asarray(residuals_m, dtype=float)
    n_drop = int(np.floor(exclude_fraction * len(e)))
    if n_drop:
        # the n_drop largest |e| by a partial sort (O(N): planes hold millions of points)
        keep = np.argpartition(np.abs(e), len(e) - n_drop - 1)[:len(e) - n_drop]
        e = e[keep]
    return float(e.max() - e.min())


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


# ------------------------------------------------------------------------------------------- the run's steps

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


def measure_spheres(points_m: np.ndarray, det: o3d.geometry.PointCloud, on_plane: np.ndarray, spec: QCSpec,
                    warnings: list[str]) -> list[SphereResult]:
    """The probing spheres: detected on the detection cloud (planes removed), refitted on the full-resolution
    points (:func:`evaluate_sphere`: PF, PS, centre), named after the spec's targets, sorted by name."""
    spheres: list[SphereResult] = []
    try:
        candidates = detect_spheres(det, spec, warnings, on_plane)
    except SphereNotFoundError as err:
        candidates = []
        warnings.append(f"sphere detection failed: {err}")
    for k, cand in enumerate(candidates):
        try:
            spheres.append(evaluate_sphere(points_m, cand, spec.spheres, f"S{k + 1}"))
        except SphereNotFoundError as err:
            warnings.append(f"sphere S{k + 1}: {err}")
    _match_targets(spheres, spec.spheres, warnings)
    spheres.sort(key=lambda sp: sp.name)
    return spheres


def measure_planes(points_m: np.ndarray, plane_models: list[np.ndarray], spec: PlaneSpec,
                   warnings: list[str]) -> list[PlaneResult]:
    """The ``evaluate`` largest planes refitted on the full-resolution points (:func:`evaluate_plane`); a plane
    left with too few points is a warning."""
    planes: list[PlaneResult] = []
    if spec.evaluate <= 0:
        return planes
    for k, model in enumerate(plane_models[:spec.evaluate]):
        try:
            planes.append(evaluate_plane(points_m, model, spec, f"P{k + 1}"))
        except DegeneratePlaneError as err:
            warnings.append(str(err))
    return planes


def measure_deviation(points_m: np.ndarray, reference: o3d.geometry.TriangleMesh | None, spec: QCSpec,
                      warnings: list[str]) -> DeviationResult | None:
    """Signed distances of the scan from the reference mesh (:func:`evaluate_deviation`); None without a
    reference.  No scan point near the reference at all is warned of: the scan or the mesh is in another frame."""
    if reference is None:
        return None
    deviation = evaluate_deviation(points_m, reference, spec.reference, np.random.default_rng(spec.seed))
    if deviation.n_evaluated == 0:
        warnings.append(f"no scan point within {spec.reference.max_distance_m} m of the reference mesh: "
                        "wrong frame or wrong mesh?")
    return deviation
