"""Finding the artefact's features for ``selfcal qc``: planes and sphere candidates on a downsampled cloud.

Detection works on a voxel-downsampled copy of the scan with normals (KD-tree): the largest planes by RANSAC
(open3d ``segment_plane``) are removed, the rest is clustered (DBSCAN), and each cluster is searched for
spheres by robust RANSAC (:func:`selfcal.core.sphere.ransac_sphere`, radius within bounds).  A candidate is
kept if its points' normals point radially.  The figures themselves are measured afterwards on the
full-resolution points (:mod:`selfcal.pipelines.qc.checks`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from selfcal.core.sphere import SphereFit, SphereNotFoundError, ransac_sphere
from selfcal.io.pointcloud import points_of
from selfcal.pipelines.qc.spec import DetectionSpec, PlaneSpec, QCSpec

__all__ = ["SphereCandidate", "detection_cloud", "find_planes", "detect_spheres", "radial_normal_fraction"]

#: a point's normal counts as radial within this angle of the direction from the sphere's centre
RADIAL_NORMAL_MAX_DEG = 30.0


@dataclass
class SphereCandidate:
    """A sphere found on the (downsampled) detection cloud."""

    fit: SphereFit
    n_inliers: int
    normal_consistency: float


def detection_cloud(cloud: o3d.geometry.PointCloud, spec: DetectionSpec) -> o3d.geometry.PointCloud:
    """The cloud features are detected on: voxel-downsampled (``voxel_m``, none if 0), with normals estimated
    within ``normal_radius_m``.  Normals are added to a copy, never to the caller's cloud."""
    det = cloud.voxel_down_sample(spec.voxel_m) if spec.voxel_m > 0 else cloud
    det = o3d.geometry.PointCloud(det)
    det.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=spec.normal_radius_m, max_nn=30))
    return det


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


def radial_normal_fraction(points_m: np.ndarray, normals: np.ndarray, center_m: np.ndarray) -> float:
    """Fraction of points whose normal is within ``RADIAL_NORMAL_MAX_DEG`` of the radial direction (either
    sign: estimated normals are unoriented).  Near 1 on a sphere; low on a curved wall or a corner, which
    RANSAC can fit with a sphere of plausible radius too."""
    u = (points_m - center_m) / np.linalg.norm(points_m - center_m, axis=1)[:, None]
    return float(np.mean(np.abs(np.einsum("ij,ij->i", u, normals)) >= np.cos(np.radians(RADIAL_NORMAL_MAX_DEG))))


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
            consistency = radial_normal_fraction(q[inl], normals[idx][inl], fit.center_m)
            if consistency >= sph.min_normal_consistency:
                candidates.append(SphereCandidate(fit, int(inl.sum()), consistency))
            else:
                warnings.append(f"sphere candidate r={fit.radius_m:.4g} m at {np.round(fit.center_m, 3).tolist()} "
                                f"rejected: only {consistency:.0%} of its points have radial normals")
            idx = idx[~inl]
    return _expected_count(candidates, sph.count, warnings)


def _expected_count(candidates: list[SphereCandidate], count: int | None,
                    warnings: list[str]) -> list[SphereCandidate]:
    """The candidates with the most inliers first, cut to the ``count`` the spec expects (the rest warned of)."""
    candidates.sort(key=lambda c: -c.n_inliers)
    if count is not None and len(candidates) > count:
        for c in candidates[count:]:
            warnings.append(f"extra sphere candidate r={c.fit.radius_m:.4g} m at "
                            f"{np.round(c.fit.center_m, 3).tolist()} ({c.n_inliers} points) ignored: spec expects "
                            f"{count}")
        candidates = candidates[:count]
    return candidates
