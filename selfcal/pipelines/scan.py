"""Use case ``selfcal smooth scan``: a mobile-scan recording in, the corrected point cloud and the INS errors out.

Steps (patent 001, steps 202-207):

1. read the per-clock point sets (set A, vision frame) and the INS solution; place set A in the world with the
   INS poses (the inertial-only scan);
2. isolate sphere candidates with open3d (voxel downsampling, DBSCAN clustering, KD-tree neighbourhoods) and
   fit each with RANSAC + least squares at the known radius (:func:`selfcal.core.sphere.ransac_sphere`):
   the inliers, split by clock, are set B;
3. per-point radial sigmas from the stereo geometry (:func:`selfcal.models.scan.stereo_point_covariance`);
4. the factor graph (:mod:`selfcal.graphs.scan`): batch LM, or iSAM2 sphere by sphere with ``online=True``;
5. the estimated error terms correct every clock: the corrected point set A.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from selfcal.core.progress import quiet
from selfcal.core import so3
from selfcal.core.sanity import imu_problems
from selfcal.core.solve import DegenerateDataError
from selfcal.graphs import scan as gs
from selfcal.io.camera import read_camera
from selfcal.io.recording import Recording, RecordingError
from selfcal.models import scan as ms
from selfcal.core.sphere import SphereNotFoundError, ransac_sphere

log = logging.getLogger(__name__)


@dataclass
class Camera:
    K: np.ndarray
    dist: np.ndarray
    vision_R_cam: np.ndarray
    vision_t_cam: np.ndarray


@dataclass
class ScanData:
    """A recording's scan: per-clock points (vision frame) and the INS solution, as arrays."""

    clock_t_s: np.ndarray  # (M,) s, on the INS time base (stamps relative to the INS's first sample)
    points_V: list  # M arrays (k, 3)
    ins_t_s: np.ndarray
    ins_R: np.ndarray
    ins_r: np.ndarray
    ins_v: np.ndarray
    ins_gyro: np.ndarray
    ins_accel: np.ndarray
    imu_R_vision: np.ndarray
    imu_t_vision: np.ndarray
    cameras: tuple
    pixel_sigma: float
    radius_m: float
    prior_sigmas: np.ndarray
    jitter_sigmas: np.ndarray

    def world_points(self, R, r) -> tuple[np.ndarray, np.ndarray]:
        """All points in the world for clock poses R (M, 3, 3), r (M, 3); and the clock of each point.

        ``p_W = R (R_IV p_V + t_IV) + r = (R R_IV) p_V + (R t_IV + r)``: one 3x3 product per clock, written
        into one preallocated array (10 M points: a list of per-clock results and a concatenation cost twice
        the memory and seconds).  Each output column is three multiply-adds over the clock's points: 3-4x faster
        than ``@`` or einsum per clock (measured: 0.3 s against 1.1 s for 10 M points), and no threaded BLAS,
        which stalls on (N, 3) x (3, 3) products on a shared machine.
        """
        R, r = np.asarray(R, float), np.asarray(r, float)
        counts = np.array([len(p) for p in self.points_V], dtype=np.int64)
        offsets = np.r_[0, np.cumsum(counts)]
        out = np.empty((int(offsets[-1]), 3))
        A = np.einsum("mij,jk->mik", R, self.imu_R_vision)  # world_R_vision per clock
        b = np.einsum("mij,j->mi", R, self.imu_t_vision) + r
        for m, p in enumerate(self.points_V):
            seg, a = out[offsets[m]:offsets[m + 1]], A[m]
            for k in range(3):
                col = seg[:, k]
                np.multiply(p[:, 0], a[k, 0], out=col)
                col += p[:, 1] * a[k, 1]
                col += p[:, 2] * a[k, 2]
                col += b[m, k]
        clock = np.repeat(np.arange(len(counts)), counts)
        return out, clock


def read_scan(recording: Recording, scan_name: str = "scan0", ins_name: str = "ins0") -> ScanData:
    """The scan and INS sensors of a recording (columns in docs/scan.md); RecordingError on bad input."""
    where = recording.path if recording.path is not None else "<recording>"
    for name in (scan_name, ins_name):
        if name not in recording.sensors:
            raise RecordingError(f"{where}: no sensor {name!r} (a mobile scan needs {scan_name}/ and {ins_name}/)")
    scan, ins = recording.sensors[scan_name], recording.sensors[ins_name]
    meta = scan.meta
    for key in ("imu_R_vision", "imu_t_vision", "cameras", "sphere_radius_m"):
        if key not in meta:
            raise RecordingError(f"{where}/{scan_name}/sensor.yaml: missing {key!r}")
    need = [c for c in ("p_WI_x", "q_WI_w", "v_WI_x", "w_RS_S_x", "a_RS_S_x") if c not in ins.values]
    if need:
        raise RecordingError(f"{where}/{ins_name}/data.csv: missing columns {', '.join(need)}")
    check_ins(f"{where}/{ins_name}", ins, scan.t_ns)
    folder = scan.folder
    pattern = meta.get("file_pattern", "{timestamp}.npy")
    points = []
    for ts in scan.t_ns:
        file = Path(folder) / pattern.format(timestamp=int(ts)) if folder is not None else None
        if file is None or not file.is_file():
            raise RecordingError(f"{where}/{scan_name}: missing point file {pattern.format(timestamp=int(ts))}")
        try:
            p = np.load(file, allow_pickle=False).astype(float)
        except (ValueError, OSError, EOFError) as err:  # a truncated or foreign file
            raise RecordingError(f"{file}: not a readable numpy array ({' '.join(str(err).split())})") from None
        if p.ndim != 2 or p.shape[1] != 3:
            raise RecordingError(f"{file}: expected an (k, 3) array of points, got shape {p.shape}")
        bad = ~np.isfinite(p).all(axis=1)
        if bad.any():
            log.warning("%s: dropped %d non-finite points", file, int(bad.sum()))
            p = p[~bad]
        points.append(p)
    v = ins.values
    q = np.column_stack([v["q_WI_x"], v["q_WI_y"], v["q_WI_z"], v["q_WI_w"]])
    t0 = ins.t_ns[0]
    cams = []
    for side in ("left", "right"):
        c = meta["cameras"][side]
        intrinsics = read_camera(c, f"{where}/{scan_name}/sensor.yaml cameras.{side}")
        cams.append(Camera(intrinsics.K, intrinsics.dist, np.array(c["vision_R_cam"], float),
                           np.array(c["vision_t_cam"], float)))
    cams = tuple(cams)
    prior = np.array(ins.meta.get("error_term_sigmas", ms.DEFAULT_PRIOR_SIGMAS), float)
    jitter = np.r_[np.full(3, float(ins.meta.get("pose_jitter_rad", 1e-5))),
                   np.full(3, float(ins.meta.get("pose_jitter_m", 5e-5)))]
    return ScanData((scan.t_ns - t0) * 1e-9, points, (ins.t_ns - t0) * 1e-9, Rotation.from_quat(q).as_matrix(),
                    np.column_stack([v["p_WI_x"], v["p_WI_y"], v["p_WI_z"]]),
                    np.column_stack([v["v_WI_x"], v["v_WI_y"], v["v_WI_z"]]),
                    np.column_stack([v[f"w_RS_S_{a}"] for a in "xyz"]), np.column_stack([v[f"a_RS_S_{a}"] for a in "xyz"]),
                    np.array(meta["imu_R_vision"], float), np.array(meta["imu_t_vision"], float), cams,
                    float(meta.get("pixel_sigma", 0.1)), float(meta["sphere_radius_m"]), prior, jitter)


def check_ins(where: str, ins, scan_t_ns: np.ndarray) -> None:
    """Refuse an INS that cannot place the scan: frames outside its record (INS stamps in us read as ns, a 2-row
    INS: every point was "corrected" with an extrapolated pose), or its inertial data failing the IMU's physical
    checks (a gap, a unit, a dead channel: :func:`selfcal.core.sanity.imu_problems`)."""
    outside = (scan_t_ns < ins.t_ns[0]) | (scan_t_ns > ins.t_ns[-1])
    if outside.any():
        raise RecordingError(f"{where}: {int(outside.sum())} of {scan_t_ns.size} scan frames lie outside the INS "
                             f"record ({(ins.t_ns[-1] - ins.t_ns[0]) * 1e-9:.6g} s long): no pose to place them with; "
                             "INS timestamps in ns?")
    v = ins.values
    problems = imu_problems((ins.t_ns - ins.t_ns[0]) * 1e-9, np.column_stack([v[f"w_RS_S_{a}"] for a in "xyz"]),
                            np.column_stack([v[f"a_RS_S_{a}"] for a in "xyz"]))
    if problems:
        raise RecordingError(f"{where}: {problems[0]}")


@dataclass
class DetectionOptions:
    voxel_m: float = 0.03
    dbscan_eps_m: float = 0.07
    dbscan_min_points: int = 5
    threshold_sigmas: float = 5.0  # RANSAC inlier threshold, in radial point sigmas (at least 3 mm)
    min_points: int = 60
    min_clocks: int = 4  # profiles through a sphere: one circle leaves its centre ambiguous along the track
    max_incidence_deg: float = 75.0  # points seen more obliquely (the limb) are left out of set B


def detect_set_b(data: ScanData, R, r, options: DetectionOptions = DetectionOptions(), seed: int = 0):
    """Sphere candidates in the scan placed with poses (R, r): set B as per-clock observations.

    Returns
    -------
    observations : list of SphereObservation (sigmas filled in)
    centers : (S, 3) fitted centres (world, with the given poses)
    """
    P, clock = data.world_points(R, r)
    if len(P) == 0:
        raise DegenerateDataError("the scan holds no points")
    R_s = data.radius_m
    # candidates on the voxel-downsampled cloud; the full-resolution points near them are fitted below
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    down = cloud.voxel_down_sample(options.voxel_m)
    labels = np.asarray(down.cluster_dbscan(options.dbscan_eps_m, options.dbscan_min_points))
    D = np.asarray(down.points)
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(labels.max() + 2 if len(labels) else 1))
    seeds = []
    for label in range(len(starts) - 1):
        q = D[order[starts[label]:starts[label + 1]]]
        extent = q.max(axis=0) - q.min(axis=0)
        if extent.max() > 4 * R_s or extent.max() < 0.5 * R_s:
            continue  # a wall, or a speck
        seeds.append(q.mean(axis=0))
    # a KD-tree over only the full-resolution points in grid cells near a candidate: the same neighbourhoods as a
    # tree over all points, without building one over 10 M points
    near, tree = _points_near(P, np.array(seeds).reshape(-1, 3), 2.5 * R_s, cloud.get_min_bound(),
                              cloud.get_max_bound())
    del cloud
    taken = np.zeros(len(P), dtype=bool)
    rng = np.random.default_rng(seed)
    centers, members = [], []
    sigma_guess = 0.002
    for c in seeds:
        _, idx, _ = tree.search_radius_vector_3d(c, 2.5 * R_s)
        idx = near[np.sort(np.asarray(idx, dtype=np.int64))]
        idx = idx[~taken[idx]]
        try:
            fit, inl = ransac_sphere(P[idx], radius_m=R_s, threshold_m=max(0.003, options.threshold_sigmas * sigma_guess),
                                     rng=rng, min_inliers=options.min_points)
        except SphereNotFoundError as err:
            log.info("candidate at %s: %s", np.round(q.mean(axis=0), 2), err)
            continue
        sel = idx[inl]
        if len(np.unique(clock[sel])) < options.min_clocks:
            log.info("sphere at %s seen by %d profiles only: not used", np.round(fit.center_m, 2),
                     len(np.unique(clock[sel])))
            continue
        taken[sel] = True
        centers.append(fit.center_m)
        members.append(sel)
    if not centers:
        raise DegenerateDataError(f"no sphere of radius {R_s} m found in the scan: set B is empty, nothing constrains "
                                  "the inertial drift")
    # order spheres by when the scan reaches them
    order = np.argsort([clock[m].min() for m in members])
    centers = np.array(centers)[order]
    members = [members[i] for i in order]
    offsets = np.r_[0, np.cumsum([len(p) for p in data.points_V])]
    observations = []
    for j, sel in enumerate(members):
        for m in np.unique(clock[sel]):
            idx = sel[clock[sel] == m] - offsets[m]
            p_V = data.points_V[m][idx]
            p_W = ms.world_points(R[m], r[m], data.imu_R_vision, data.imu_t_vision, p_V)
            # grazing points (the sphere's limb as the camera sees it) are dropped: the first-order radial sigma
            # vanishes there while curvature and limb matching do not (they showed up as 20-sigma residuals)
            u_W = (p_W - centers[j]) / np.linalg.norm(p_W - centers[j], axis=1, keepdims=True)
            ray_W = (p_V / np.linalg.norm(p_V, axis=1, keepdims=True)) @ (R[m] @ data.imu_R_vision).T
            keep = np.abs(np.einsum("ij,ij->i", u_W, ray_W)) >= np.cos(np.radians(options.max_incidence_deg))
            if keep.sum() < 2:
                continue
            p_V, p_W = p_V[keep], p_W[keep]
            cov = ms.stereo_point_covariance(p_V, data.cameras, data.pixel_sigma)
            sig = ms.radial_sigmas(p_V, data.imu_R_vision, R[m], centers[j], p_W, cov)
            observations.append(gs.SphereObservation(int(m), j, p_V, np.maximum(sig, 1e-5)))
    log.info("set B: %d spheres, %d clocks, %d points", len(centers), len({o.clock for o in observations}),
             sum(len(o.vision_p) for o in observations))
    return observations, centers


def _points_near(points: np.ndarray, seeds: np.ndarray, radius_m: float, min_bound, max_bound):
    """Indices of the points in the grid cells (size ``radius_m``) touching balls of ``radius_m`` about the seeds,
    and an open3d KD-tree over those points (its indices refer to the returned index array).

    ``min_bound``, ``max_bound``: the points' bounding box (open3d's, cheaper than numpy's strided reductions).
    """
    if len(seeds) == 0:
        return np.zeros(0, dtype=np.int64), o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud())
    origin = np.asarray(min_bound, float)
    inv = 1.0 / radius_m
    dims = ((np.asarray(max_bound, float) - origin) * inv).astype(np.int64) + 3  # a margin for the seeds' +-1
    key = np.zeros(len(points), dtype=np.int64)
    for k in range(3):  # one coordinate at a time: no (N, 3) temporaries
        key *= dims[k]
        key += ((points[:, k] - origin[k]) * inv).astype(np.int64)  # >= 0: truncation is floor
    seed_cell = ((seeds - origin) * inv).astype(np.int64)  # the points' rounding
    offsets = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T
    around = (seed_cell[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
    wanted = np.unique((around[:, 0] * dims[1] + around[:, 1]) * dims[2] + around[:, 2])
    if np.prod(dims) <= 64_000_000:  # a lookup table over the grid (bytes): one gather per point
        table = np.zeros(int(np.prod(dims)), dtype=bool)
        table[wanted] = True
        near = np.flatnonzero(table[key])
    else:
        pos = np.minimum(np.searchsorted(wanted, key), len(wanted) - 1)
        near = np.flatnonzero(wanted[pos] == key)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[near]))
    return near, o3d.geometry.KDTreeFlann(cloud)


@dataclass(frozen=True)
class RegistrationOptions:
    every_clocks: int = 3  # profile pairs (m, m + every_clocks), chained: 3 clocks = 3 cm of track at 0.5 m/s.
    # The in-plane normals take the surface as extruded across the scan plane; the vehicle's yaw and pitch tilt
    # the plane by milliradians against the tunnel's axis, an error of (gap x tilt) in every pair (measured
    # registration NEES / dof at the true poses, 10 m scans: 1.5 with 10 clocks, 2.0 with 0.3 deg of pitch;
    # 1.1-1.2 with 3 clocks)
    max_correspondence_m: float = 0.3  # profiles of a push-broom scanner do not overlap: the next profile is
    # every_clocks * speed / clock_hz away along the track, and every neighbour is at least that far
    tangent_half_window: int = 3  # points either side for a profile's tangent (its in-plane normal)
    max_tangent_gap_m: float = 0.05  # neighbours further apart than this along the profile: an edge, no normal
    sphere_clearance_radii: float = 2.5  # points this close to a detected sphere (in radii) are left out
    relative_floor: float = 1e-2  # information eigen-directions below this fraction of the largest: unseen


def _profile_normals(p_I: np.ndarray, plane_normal_I: np.ndarray, half: int, max_gap_m: float):
    """In-plane unit normals of one profile (points in pixel order): the surface taken as extruded across the
    scan plane (a tunnel's vault and floor), the normal is perpendicular to the profile's tangent and to the
    plane's normal.  Returns (normals (N, 3), valid (N,)): no normal across a gap (an edge, an occlusion)."""
    n = len(p_I)
    valid = np.zeros(n, dtype=bool)
    normals = np.zeros((n, 3))
    if n < 2 * half + 1:
        return normals, valid
    ahead, behind = p_I[2 * half:], p_I[:-2 * half]
    step = np.linalg.norm(np.diff(p_I, axis=0), axis=1)
    gaps = np.convolve(step > max_gap_m, np.ones(2 * half, dtype=int), mode="valid") > 0
    tangent = ahead - behind
    normal = np.cross(tangent, plane_normal_I)
    length = np.linalg.norm(normal, axis=1)
    ok = ~gaps & (length > 0)
    normals[half:n - half][ok] = normal[ok] / length[ok, None]
    valid[half:n - half] = ok
    return normals, valid


def _point_to_plane_icp(source, target, source_cov, target_cov, init, options: RegistrationOptions,
                        iterations: int = 20):
    """Weighted point-to-plane ICP moving only along the directions the correspondences see: ``(a_T_b, L)``.

    ``open3d.pipelines.registration.registration_icp`` solves all six directions every iteration; between two
    profiles of an extruded surface three of them (along the track, and the two tilts out of the scan plane)
    have no information, its solve wanders there (measured: 70 mrad of yaw, 30 cm along the track) and the
    wandering spoils the correspondences of the seen directions.  Here each Gauss-Newton step is the
    weighted least-squares step restricted to the eigen-directions of ``J^T W J`` above ``relative_floor`` (the
    null directions stay at the INS's relative pose); correspondences from scipy's KD-tree.  Each residual is
    weighted by its own variance ``n^T (R C_b R^T + C_a) n`` (the stereo covariances of both points: range noise
    grows with the square of the range, and the far points carry the rotation); the information is divided by
    the a-posteriori variance factor ``sum (e/s)^2 / (N - r)``.  Returns None when too few points match.
    """
    from scipy.spatial import cKDTree
    P, Q, N = (np.asarray(source.points), np.asarray(target.points), np.asarray(target.normals))
    tree = cKDTree(Q)
    Z = np.array(init, dtype=float)
    for it in range(iterations + 1):
        moved = P @ Z[:3, :3].T + Z[:3, 3]
        _, match = tree.query(moved, distance_upper_bound=options.max_correspondence_m)
        ok = match < len(Q)  # scipy marks "none within the bound" with len(Q)
        if ok.sum() < 50:
            return None
        src, q, n = P[ok], Q[match[ok]], N[match[ok]]
        n_b = n @ Z[:3, :3]  # the normal in the source frame
        sigma = np.sqrt(np.einsum("ni,nij,nj->n", n_b, source_cov[ok], n_b)
                        + np.einsum("ni,nij,nj->n", n, target_cov[match[ok]], n))
        e = np.einsum("ij,ij->i", n, moved[ok] - q)
        info = ms.point_to_plane_information(src, n, Z, sigma)
        L = ms.observable_square_root(info, options.relative_floor)
        if it == iterations:
            break
        G = np.concatenate([np.cross(src, n_b), n_b], axis=1) / sigma[:, None]
        # step within the seen subspace: xi = V c, min |G V c + e / sigma|  (V: the rows of L, normalised)
        V = (L / np.linalg.norm(L, axis=1, keepdims=True)).T
        xi = V @ np.linalg.lstsq(G @ V, -e / sigma, rcond=None)[0]
        step = np.eye(4)
        step[:3, :3] = so3.exp(xi[:3])
        step[:3, 3] = xi[3:]  # first order in xi: the steps are micro-radians and millimetres
        Z = Z @ step
        if np.linalg.norm(xi) < 1e-9:
            iterations = it + 1  # one more pass: the correspondences and the information at the final Z
    variance_factor = np.sum((e / sigma) ** 2) / (len(e) - len(L))
    return Z, ms.observable_square_root(info / variance_factor, options.relative_floor)


def register_frames(data: ScanData, problem: gs.ScanProblem,
                    options: RegistrationOptions = RegistrationOptions()) -> list:
    """Profiles of the scan registered pairwise by point-to-plane ICP (open3d): ``FrameRegistration`` list.

    A line scanner's frame is one profile; a frame placed by the INS over several clocks would carry the INS's
    own velocity error into the measurement (measured: registration NEES growing with the drift to ~10^3), so
    each frame is a single clock, rigid by construction.  Profile ``b = a + every_clocks`` is registered onto
    profile ``a`` from the INS's relative pose, with the target's in-plane normals
    (:func:`_profile_normals`: the scene taken as extruded across the scan plane, as a tunnel is).  The
    information (:func:`selfcal.models.scan.point_to_plane_information`) weighs each residual by the stereo
    covariances of its two points (:func:`selfcal.models.scan.stereo_point_covariance`) and is divided by the
    a-posteriori variance factor of the converged residuals (whatever of the surface the model does not fit);
    it is kept on its seen directions only.  The spheres are cut out.
    """
    R, r = ms.interpolate_poses(data.clock_t_s, data.ins_t_s, data.ins_R, data.ins_r)
    plane_normal_I = data.imu_R_vision[:, 1]  # the scan plane is y_V = 0
    out = []
    for a in range(0, len(data.clock_t_s) - options.every_clocks, options.every_clocks):
        b = a + options.every_clocks
        clouds = []
        for m in (a, b):
            p_I = data.points_V[m] @ data.imu_R_vision.T + data.imu_t_vision
            p_W = p_I @ R[m].T + r[m]
            far = np.ones(len(p_I), dtype=bool)
            for c in problem.centers0:
                far &= np.einsum("ij,ij->i", p_W - c, p_W - c) > (options.sphere_clearance_radii * data.radius_m) ** 2
            normals, valid = _profile_normals(p_I, plane_normal_I, options.tangent_half_window,
                                              options.max_tangent_gap_m)
            keep = far & valid
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p_I[keep]))
            cloud.normals = o3d.utility.Vector3dVector(normals[keep])
            cov_V = ms.stereo_point_covariance(data.points_V[m][keep], data.cameras, data.pixel_sigma)
            clouds.append((cloud, data.imu_R_vision @ cov_V @ data.imu_R_vision.T))
        (target, target_cov), (source, source_cov) = clouds
        if len(target.points) < 50 or len(source.points) < 50:
            continue
        init = np.eye(4)
        init[:3, :3] = R[a].T @ R[b]
        init[:3, 3] = R[a].T @ (r[b] - r[a])
        fit = _point_to_plane_icp(source, target, source_cov, target_cov, init, options)
        if fit is None:
            continue
        Z, sqrt_information = fit
        out.append(gs.FrameRegistration(a, b, Z, sqrt_information))
    log.info("registration: %d profile pairs", len(out))
    return out


def scan_problem(data: ScanData, detection: DetectionOptions = DetectionOptions()) -> gs.ScanProblem:
    """Set B detected in the inertial-only scan, with the INS error sensitivity: the graph's input."""
    sens = ms.error_sensitivity(data.ins_t_s, data.ins_R, data.ins_accel, data.ins_gyro)
    R, r = ms.interpolate_poses(data.clock_t_s, data.ins_t_s, data.ins_R, data.ins_r)
    observations, centers = detect_set_b(data, R, r, detection)
    return gs.ScanProblem(data.ins_t_s, data.ins_R, data.ins_r, data.ins_v, data.ins_gyro, sens, data.clock_t_s,
                          observations, centers, data.radius_m, data.imu_R_vision, data.imu_t_vision,
                          data.prior_sigmas, data.jitter_sigmas)


@dataclass
class ScanEstimate:
    """The corrected scan and what was estimated, each with its 1-sigma."""

    points_W: np.ndarray  # (N, 3) corrected set A, world, m
    clock_of_point: np.ndarray  # (N,)
    theta: np.ndarray  # (15,)
    theta_sigma: np.ndarray
    centers: np.ndarray  # (S, 3)
    centers_cov: np.ndarray  # (S, 3, 3)
    sphere_rms_m: float  # RMS of the sphere residuals after the fit
    n_b_points: int
    n_b_clocks: int
    seconds: float
    online: bool
    extensions: dict = field(default_factory=dict)
    problem: gs.ScanProblem | None = None
    solution: gs.ScanSolution | None = None
    stages_s: dict = field(default_factory=dict)  # stage -> (wall s, CPU s of the process)
    #: predicted 1-sigma of every corrected point along its worst direction, m (:func:`predicted_point_sigmas`)
    point_sigma_m: np.ndarray | None = None
    #: every pair of found spheres: (i, j, distance m, predicted 1-sigma m) (:func:`sphere_distances`)
    distances: list = field(default_factory=list)

    def summary(self) -> str:
        s = [f"{len(self.points_W)} points, {len(self.centers)} spheres ({self.n_b_points} points on "
             f"{self.n_b_clocks} clocks), sphere residual RMS {self.sphere_rms_m * 1e3:.3f} mm, "
             f"{self.seconds:.1f} s ({'iSAM2 online' if self.online else 'batch LM'})"]
        for name, v, sg, unit in zip(ms.ERROR_TERMS, self.theta, self.theta_sigma, ms.ERROR_UNITS):
            s.append(f"  {name:14s} {v: .4e} +- {sg:.2e} {unit}")
        return "\n".join(s)

    def to_dict(self) -> dict:
        return {"error_terms": {n: {"value": float(v), "sigma": float(s), "unit": u}
                                for n, v, s, u in zip(ms.ERROR_TERMS, self.theta, self.theta_sigma, ms.ERROR_UNITS)},
                "spheres": [{"center_m": c.tolist(), "center_sigma_m": np.sqrt(np.diag(C)).tolist()}
                            for c, C in zip(self.centers, self.centers_cov)],
                "sphere_residual_rms_m": self.sphere_rms_m, "points": int(len(self.points_W)),
                "set_b_points": self.n_b_points, "set_b_clocks": self.n_b_clocks, "seconds": self.seconds,
                "mode": "online" if self.online else "batch", **self._predicted()}

    def _predicted(self) -> dict:
        out = {"sphere_distances": [{"between": [int(i), int(j)], "distance_m": float(d), "sigma_m": float(s)}
                                    for i, j, d, s in self.distances]}
        if self.point_sigma_m is not None and len(self.point_sigma_m):
            q = np.percentile(self.point_sigma_m, [50, 95, 100])
            out["point_sigma_m"] = {"median": float(q[0]), "p95": float(q[1]), "max": float(q[2])}
        return out


def solve_scan(data: ScanData, problem: gs.ScanProblem, model: gs.ScanModel = gs.ScanModel(), online: bool = False,
               iterations: int | None = None):
    """Solve for the error terms, re-mechanising the INS between passes when ``iterations`` > 1 (default 1).

    The error model is linear in the terms; products of errors (attitude error x velocity error, ...) are left
    out.  With ``iterations`` > 1 the estimated terms are removed from the INS *through the strapdown*
    (:func:`selfcal.models.scan.remechanized`, exact) and the graph is solved again for what is left, with the
    prior shifted accordingly.  Measured on a 24 m scan drifting by 0.8 m: no change of the sphere spacing (1.501
    vs 1.501 mm) or the NEES, so one pass is the default; the option stays for INS far worse than tactical grade.

    Returns
    -------
    (problem of the last pass, its ScanSolution, total error terms (15,))
    """
    iterations = 1 if online else (iterations or 1)
    total = np.zeros(ms.N_TERMS)
    for it in range(iterations):
        solution = (gs.solve_online if online else gs.solve_batch)(problem, model)
        if it == iterations - 1:
            break
        total = total + solution.theta
        gyro, accel = data.ins_gyro - total[9:12], data.ins_accel - total[12:15]
        R, v, r = ms.remechanized(data.ins_t_s, data.ins_R, data.ins_v, data.ins_r, data.ins_gyro, data.ins_accel,
                                  total)
        problem = replace(problem, ins_R=R, ins_v=v, ins_r=r, ins_gyro=gyro,
                          sensitivity=ms.error_sensitivity(data.ins_t_s, R, accel, gyro), prior_mean=-total,
                          centers0=np.where(np.isfinite(solution.centers), solution.centers, problem.centers0))
    return problem, solution, total + solution.theta


def smooth_scan(recording: Recording, online: bool = False, model: gs.ScanModel = gs.ScanModel(),
                scan_name: str = "scan0", ins_name: str = "ins0", iterations: int | None = None,
                progress=quiet) -> ScanEstimate:
    """Correct a mobile scan: sphere constraints -> INS error terms -> every clock's pose -> set A.
    ``progress(stage)`` is told each stage as it starts (:mod:`selfcal.core.progress`)."""
    start = time.perf_counter()
    stages = {}
    clock_ = [time.perf_counter(), time.process_time()]

    def lap(name):
        now = [time.perf_counter(), time.process_time()]
        stages[name] = (now[0] - clock_[0], now[1] - clock_[1])
        clock_[:] = now

    progress("read points")
    data = read_scan(recording, scan_name, ins_name)
    if sum(len(p) for p in data.points_V) == 0:
        raise DegenerateDataError(f"{recording.path}: the scan holds no points")
    lap("read points")
    progress("sphere detection (set B)")
    problem = scan_problem(data)
    lap("sphere detection (set B)")
    if model.registration and not online:  # the iSAM2 path takes the spheres only
        progress("frame registration")
        problem = replace(problem, registrations=register_frames(data, problem))
        lap("frame registration")
    progress("factor graph" + (" (iSAM2)" if online else ""))
    problem, solution, theta = solve_scan(data, problem, model, online, iterations)
    lap("factor graph")
    progress("correction of all points")
    R, r = gs.corrected_clock_poses(problem, solution)
    P, clock = data.world_points(R, r)
    res = np.concatenate(gs.sphere_residuals(problem, solution.values, model))
    lap("correction of all points")
    progress("predicted accuracy")
    sigma = predicted_point_sigmas(problem, solution, R, r, P, clock)
    lap("predicted accuracy")
    return ScanEstimate(P, clock, theta, np.sqrt(np.diag(solution.theta_cov)), solution.centers,
                        solution.centers_cov, float(np.sqrt(np.mean(res**2))),
                        sum(len(o.vision_p) for o in problem.observations), len(problem.b_clocks()),
                        time.perf_counter() - start, online, solution.extensions, problem, solution, stages,
                        sigma, sphere_distances(solution))


def predicted_point_sigmas(problem: gs.ScanProblem, solution: gs.ScanSolution, R, r, points_W, clock) -> np.ndarray:
    """Predicted 1-sigma (N,) of every corrected point (m, worst direction) relative to the scan as a rigid
    whole: the error terms' posterior without its rigid part (the INS's initial position and heading, which no
    sphere of unknown position sees: :func:`selfcal.models.scan.shape_covariance`) and the INS jitter, through
    each clock's correction (:func:`selfcal.models.scan.point_error_sigmas`).

    The point's own triangulation noise is not in it (white, per point: every fit averages it), nor the
    uncertainty of estimated extensions (scale factors, clock offset): the base model's 15 terms only.
    """
    clocks = np.arange(len(problem.clock_t_s))
    R_ins, r_ins, Phi, _ = gs.clock_inputs(problem, clocks)
    _, _, J = ms.corrected_pose(R_ins, r_ins, Phi[:, :, :ms.N_TERMS], solution.theta, with_jacobian=True)
    shape = ms.shape_covariance(solution.theta_cov, ms.rigid_gauge(problem.ins_v[0]))
    pose_cov = ms.corrected_pose_covariance(J, shape, problem.jitter_sigmas)
    return ms.point_error_sigmas(R, r, pose_cov, points_W, clock)


def sphere_distances(solution: gs.ScanSolution) -> list[tuple[int, int, float, float]]:
    """Every pair of estimated sphere centres: ``(i, j, distance m, predicted 1-sigma m)`` from the joint
    posterior of the centres (:func:`selfcal.models.scan.distance_sigmas`)."""
    if solution.terms_centers_cov is None:
        return []
    found = np.flatnonzero(np.isfinite(solution.centers).all(axis=1))
    pairs = np.array([(i, j) for k, i in enumerate(found) for j in found[k + 1:]], dtype=int).reshape(-1, 2)
    if not len(pairs):
        return []
    d, sigma = ms.distance_sigmas(solution.centers, solution.terms_centers_cov[ms.N_TERMS:, ms.N_TERMS:], pairs)
    return [(int(i), int(j), float(a), float(b)) for (i, j), a, b in zip(pairs, d, sigma)]


def inertial_only_points(recording: Recording) -> np.ndarray:
    """Set A placed with the uncorrected INS poses (the scan the patent sets out to improve)."""
    data = read_scan(recording)
    R, r = ms.interpolate_poses(data.clock_t_s, data.ins_t_s, data.ins_R, data.ins_r)
    return data.world_points(R, r)[0]


def audit_system(recording: Recording, base: str = "error15", sensors: list[str] | None = None):
    """The audit's view of a scan recording: the 15 INS error terms and sphere centres as the base model."""
    from selfcal.audit.scan import ScanAudit
    return ScanAudit(scan_problem(read_scan(recording)))


# ------------------------------------------------------------------------------------------------ planning

@dataclass
class ScanPlanCase:
    """The predicted accuracy of one sphere layout (linear covariance analysis, no measurement)."""

    n_spheres: int
    spacing_m: float
    distance_sigmas_m: np.ndarray  # every pair of spheres, m
    predicted_rms_m: float  # sqrt(mean sigma^2) over the pairs: the sphere-spacing RMS to expect
    worst_sigma_m: float
    bound_m: float  # worst_sigma x the two-sided normal quantile of the confidence
    meets: bool


@dataclass
class ScanPlan:
    """``selfcal plan scan``: the largest sphere spacing whose predicted distance errors meet the tolerance."""

    length_m: float
    speed_m_s: float
    tolerance_m: float
    confidence: float
    cases: list[ScanPlanCase]

    @property
    def chosen(self) -> ScanPlanCase | None:
        """The layout with the fewest spheres (largest spacing) found to meet the tolerance; None if none."""
        return next((c for c in self.cases if c.meets), None)

    def to_dict(self) -> dict:
        case = self.chosen
        return {"length_m": self.length_m, "speed_m_s": self.speed_m_s, "tolerance_m": self.tolerance_m,
                "confidence": self.confidence, "feasible": case is not None,
                "largest_spacing_m": None if case is None else case.spacing_m,
                "spheres": None if case is None else case.n_spheres,
                "cases": [{"spheres": c.n_spheres, "spacing_m": c.spacing_m, "predicted_rms_m": c.predicted_rms_m,
                           "worst_sigma_m": c.worst_sigma_m, "bound_m": c.bound_m, "meets": c.meets}
                          for c in self.cases]}


def planned_problem(scenario, prior_sigmas, jitter_sigmas, seed: int = 0,
                    detection: DetectionOptions = DetectionOptions()) -> gs.ScanProblem:
    """The graph's input for a scan not yet made: the noise-free sphere profiles of the simulated sensor along
    the nominal path (:func:`selfcal.sim.scan.simulate_scan` with ``spheres_only``), an error-free INS on it,
    and the radial sigmas the stereo geometry gives each point, as :func:`detect_set_b` would assign them."""
    from selfcal.sim.scan import simulate_scan
    # zero sigmas rather than fixed zero terms: the random draws happen as in a simulated scan of the same seed,
    # so the spheres stand where that scan has them
    exact = replace(scenario, pixel_sigma=0.0, ins_jitter_m=0.0, ins_jitter_rad=0.0, error_terms=None,
                    error_sigmas=np.zeros(ms.N_TERMS))
    sim = simulate_scan(exact, seed=seed, spheres_only=True)
    t = sim.ins_t_s
    R_c, r_c = sim.true_R, sim.true_r
    observations = []
    cos_max = np.cos(np.radians(detection.max_incidence_deg))
    for m, (p_V, label) in enumerate(zip(sim.points_V, sim.sphere_label)):
        for j in np.unique(label[label >= 0]):
            q = p_V[label == j]
            p_W = ms.world_points(R_c[m], r_c[m], sim.imu_R_vision, sim.imu_t_vision, q)
            u = (p_W - sim.sphere_centers[j]) / np.linalg.norm(p_W - sim.sphere_centers[j], axis=1, keepdims=True)
            ray = (q / np.linalg.norm(q, axis=1, keepdims=True)) @ (R_c[m] @ sim.imu_R_vision).T
            keep = np.abs(np.einsum("ij,ij->i", u, ray)) >= cos_max
            if keep.sum() < 2:
                continue
            cov = ms.stereo_point_covariance(q[keep], (sim.left, sim.right), scenario.pixel_sigma)
            sig = ms.radial_sigmas(q[keep], sim.imu_R_vision, R_c[m], sim.sphere_centers[j], p_W[keep], cov)
            observations.append(gs.SphereObservation(m, int(j), q[keep], np.maximum(sig, 1e-5)))
    sens = ms.error_sensitivity(t, sim.ins_R, sim.ins_accel, sim.ins_gyro)
    return gs.ScanProblem(t, sim.ins_R, sim.ins_r, sim.ins_v, sim.ins_gyro, sens, sim.clock_stamp_s - t[0],
                          observations, sim.sphere_centers, scenario.sphere_radius_m, sim.imu_R_vision,
                          sim.imu_t_vision, np.asarray(prior_sigmas, float), np.asarray(jitter_sigmas, float))


def predicted_layout(problem: gs.ScanProblem) -> tuple[np.ndarray, np.ndarray]:
    """Linear covariance analysis of a planned scan: the graph linearised at the truth (error terms zero,
    centres true), its joint covariance of the centres, every pair's distance sigma.  Returns (pairs, sigmas)."""
    import gtsam
    values = gtsam.Values()
    values.insert(gs.THETA, np.zeros(ms.N_TERMS))
    keys = [gs.THETA] + [gs.O_KEY(j) for j in range(len(problem.centers0))]
    for j, c in enumerate(problem.centers0):
        values.insert(gs.O_KEY(j), np.asarray(c, float))
    joint = gs.covariance_at(problem, gs.ScanModel(), values, keys)
    pairs = np.array(np.triu_indices(len(problem.centers0), 1)).T
    _, sigma = ms.distance_sigmas(problem.centers0, joint[ms.N_TERMS:, ms.N_TERMS:], pairs)
    return pairs, sigma


def plan_scan(length_m: float, speed_m_s: float, tolerance_m: float, prior_sigmas=None, jitter_sigmas=None,
              confidence: float = 0.95, seed: int = 0, max_spheres: int | None = None, progress=quiet) -> ScanPlan:
    """The largest sphere spacing along a straight scan of ``length_m`` at ``speed_m_s`` whose every sphere
    distance has a predicted error bound (``confidence``, two-sided normal) within ``tolerance_m``.

    Layouts as the simulator places them (spheres from 1.5 m after the start to 1.5 m before the end, evenly, at
    random heights and ranges in the field of view, ``seed``); the number of spheres is doubled from 2 until a
    layout meets the tolerance, then bisected (more spheres: shorter spacing, more information; a layout's random
    placement makes this only nearly monotone, so the answer is the largest spacing found to meet it).
    ``prior_sigmas`` (15) and ``jitter_sigmas`` (6: rad x3, m x3) describe the INS (default: the simulator's).
    No measurement and no Monte Carlo: the covariance of the graph linearised at the planned truth
    (:func:`predicted_layout`).
    """
    from scipy import stats

    from selfcal.sim.scan import ScanScenario
    if length_m <= 3.5 or speed_m_s <= 0 or tolerance_m <= 0 or not 0 < confidence < 1:
        raise DegenerateDataError("plan: need a length over 3.5 m (spheres stand 1.5 m inside each end), a positive "
                                  "speed and tolerance, a confidence between 0 and 1")
    prior = ms.DEFAULT_PRIOR_SIGMAS if prior_sigmas is None else np.asarray(prior_sigmas, float)
    base = ScanScenario(length_m=length_m, speed_m_s=speed_m_s, speed_change_m_s=0.5 * speed_m_s)
    jitter = (np.r_[np.full(3, base.ins_jitter_rad), np.full(3, base.ins_jitter_m)] if jitter_sigmas is None
              else np.asarray(jitter_sigmas, float))
    z = float(stats.norm.ppf(0.5 + confidence / 2))
    n_max = max_spheres or int((length_m - 3.0) / (4 * base.sphere_radius_m)) + 1  # spheres 2 diameters apart
    cases: dict[int, ScanPlanCase] = {}

    def case(n: int) -> ScanPlanCase:
        if n not in cases:
            progress(f"{n} spheres")
            problem = planned_problem(replace(base, n_spheres=n, error_sigmas=prior), prior, jitter, seed)
            _, sigma = predicted_layout(problem)
            worst = float(sigma.max())
            cases[n] = ScanPlanCase(n, (length_m - 3.0) / (n - 1), sigma, float(np.sqrt(np.mean(sigma**2))), worst,
                                    z * worst, z * worst <= tolerance_m)
        return cases[n]

    lo, hi = 1, 2
    while not case(hi).meets and hi < n_max:
        lo, hi = hi, min(2 * hi, n_max)
    if case(hi).meets:
        while hi - lo > 1:  # lo fails (or is 1), hi meets
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if case(mid).meets else (mid, hi)
    return ScanPlan(length_m, speed_m_s, tolerance_m, confidence, [cases[n] for n in sorted(cases)])
