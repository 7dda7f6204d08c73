"""Simulated mobile 3D scan (patent 001): a line-scan stereo sensor and an INS moving through a tunnel with spheres.

The scene
---------
A tunnel section along world x: a circular vault of radius ``tunnel_radius_m`` about the x axis, cut by a flat
floor at ``floor_z_m`` (an open3d triangle mesh, also written as the reference mesh for QC).  Spheres of radius
``sphere_radius_m`` stand in the sensor's view at random positions (held by thin rods the sensor does not
resolve).  Surfaces are ray cast with open3d's ``RaycastingScene``; spheres are intersected analytically
(a tessellated sphere would put a chord error of R (1 - cos(pi / n)) into the very constraint under test).

The sensor (patent [0043]-[0046])
---------------------------------
Two line cameras (pinhole + OpenCV radial distortion, one sensor row at ``v = c_y``) share one scan plane, the
plane ``y_V = 0`` of the left camera, which stands across the track (normal along body x).  The vision frame V
is the left camera frame; ``imu_T_vision`` the calibrated extrinsic.  Each clock, the left camera's pixels (every
``pixel_step``-th) are cast into the scene; a hit seen by the right camera (in its field and not occluded) is
projected into it; both pixel coordinates get Gaussian noise ``pixel_sigma`` (matching precision) and the point
is triangulated with ``cv2.undistortPoints`` + ``cv2.triangulatePoints``: set A, in the vision frame.

Motion and the INS
------------------
A rail vehicle: speed ``speed_m_s`` varied by ``speed_change_m_s`` over the run (so accelerometer scale shows),
lateral sway, heave, roll and pitch oscillations.  Truth is sampled at the INS rate; velocity and specific force
are the finite differences that make the strapdown recursion reproduce the truth exactly, so the INS solution
is a *real* strapdown integration of the corrupted IMU (``w~ = (I + diag(s_g)) w + b_g``,
``f~ = (I + diag(s_a)) f + b_a``) from an erroneous initial state: the 15 error terms of
:mod:`selfcal.models.scan` act through the nonlinear mechanisation, which the estimator's linear model only
approximates (second order).  The INS output poses carry white jitter (``ins_jitter_m``, ``ins_jitter_rad``).

Hidden effects (for the audit): ``time_offset_s`` (a clock stamped ``t`` on the camera clock happened at INS
time ``t + dt``), ``extrinsic_rotation_rad`` (true ``R_IV = R_IV,cal Exp(eps)``), ``sphere_radius_error_m``
(true radius = nominal + dR), ``accel_scale``, ``gyro_scale``; outside the audit's catalog:
``sphere_radius_per_range`` (apparent radius growing with range), ``sphere_radius_step_m`` (apparent radius jumping
at a fraction ``sphere_radius_step_at`` of the run), ``disparity_offset_px`` (a stereo matching bias).

Recording (written by :func:`write_scan_recording`)
---------------------------------------------------
``scan0/data.csv``: ``#timestamp [ns],points [1],file_index [1]``; points of the clock in
``scan0/<timestamp>.npy`` (float32 (k, 3), vision frame, m).  ``scan0/sensor.yaml``: cameras, extrinsic,
nominal sphere radius, point sigma.  ``ins0/data.csv``: INS pose, velocity and raw IMU (see docs/scan.md);
``ins0/sensor.yaml``: the error terms' prior sigmas and the output jitter.  ``truth/truth.yaml`` (error
terms, sphere centres, effects), ``truth/poses.npz`` (true clock poses, sphere label per point),
``truth/reference_mesh.ply``.
"""
from __future__ import annotations

import io
import logging
import os
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from selfcal.models import scan as ms
from selfcal.core import so3
from selfcal.io.camera import camera_keys, read_camera

log = logging.getLogger(__name__)

DEFAULT_ERROR_SIGMAS = ms.DEFAULT_PRIOR_SIGMAS


@dataclass
class LineCamera:
    """One line camera: OpenCV intrinsics (the sensor row is ``v = cy``) and its pose in the vision frame."""

    K: np.ndarray
    dist: np.ndarray
    width_px: int
    vision_R_cam: np.ndarray = field(default_factory=lambda: np.eye(3))
    vision_t_cam: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def to_dict(self) -> dict:
        """sensor.yaml keys: the shared camera keys (:mod:`selfcal.io.camera`; one sensor row) and the pose."""
        return {**camera_keys(self.K, self.dist, (self.width_px, 1)),
                "vision_R_cam": self.vision_R_cam.tolist(), "vision_t_cam": self.vision_t_cam.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "LineCamera":
        cam = read_camera(d)
        return cls(cam.K, cam.dist, int(cam.resolution[0]), np.array(d["vision_R_cam"], float),
                   np.array(d["vision_t_cam"], float))


def default_stereo(baseline_m: float = 0.6, convergence_m: float = 2.5) -> tuple[LineCamera, LineCamera]:
    """Left camera = vision frame; right camera ``baseline_m`` along the left's x, toed in to meet at ``convergence_m``."""
    K = np.array([[1000.0, 0.0, 1024.0], [0.0, 1000.0, 0.5], [0.0, 0.0, 1.0]])
    dist = np.array([-0.04, 0.01, 0.0, 0.0, 0.0])
    left = LineCamera(K, dist, 2048)
    toe = np.arctan2(baseline_m, convergence_m)
    # toe-in about the common y axis keeps both scan planes the same plane y_V = 0
    R = so3.exp(np.array([0.0, -toe, 0.0]))
    right = LineCamera(K.copy(), dist.copy(), 2048, R, np.array([baseline_m, 0.0, 0.0]))
    return left, right


def default_imu_T_vision(elevation_deg: float = 45.0) -> tuple[np.ndarray, np.ndarray]:
    """Vision frame in the body: scan plane across the track (y_V along body x), looking left and up."""
    a = np.radians(elevation_deg)
    y_v = np.array([1.0, 0.0, 0.0])
    z_v = np.array([0.0, np.cos(a), np.sin(a)])
    x_v = np.cross(y_v, z_v)
    return np.column_stack([x_v, y_v, z_v]), np.array([0.1, 0.15, 0.35])


@dataclass
class ScanScenario:
    """Parameters of a simulated scan (SI units; defaults: a 24 m tunnel section at 0.5 m/s)."""

    length_m: float = 24.0
    speed_m_s: float = 0.5
    speed_change_m_s: float = 0.25
    clock_hz: float = 50.0
    ins_rate_hz: float = 200.0
    tunnel_radius_m: float = 3.0
    floor_z_m: float = -1.9
    imu_height_m: float = -1.3
    n_spheres: int = 10
    sphere_radius_m: float = 0.1
    sphere_range_m: tuple[float, float] = (1.4, 2.2)
    pixel_step: int = 4
    pixel_sigma: float = 0.1
    error_sigmas: np.ndarray = field(default_factory=lambda: DEFAULT_ERROR_SIGMAS.copy())
    error_terms: np.ndarray | None = None  # None: drawn from error_sigmas
    ins_jitter_m: float = 5e-5
    ins_jitter_rad: float = 1e-5
    sway_m: float = 0.01
    heave_m: float = 0.005
    roll_deg: float = 0.3
    pitch_deg: float = 0.1
    # hidden effects
    time_offset_s: float = 0.0
    extrinsic_rotation_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sphere_radius_error_m: float = 0.0
    sphere_radius_per_range: float = 0.0  # m of apparent radius per m of range from the sensor to the sphere
    # (not in the audit's catalog; as a beam footprint or a matcher's window growing with range would do)
    disparity_offset_px: float = 0.0  # a matching bias of the right camera (not in the audit's catalog): depth
    # error ~ z^2 d / (f B), every sphere scaled about the sensor by a factor growing with its range
    sphere_radius_step_m: float = 0.0  # apparent radius jumping by this much at ``sphere_radius_step_at`` of the
    # run's duration (not in the audit's catalog; as an auto-exposure change that blooms bright surfaces would do)
    sphere_radius_step_at: float = 0.5
    accel_scale: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_scale: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class ScanSimulation:
    """A simulated scan: per-clock point sets (vision frame), the INS solution, and the truth."""

    scenario: ScanScenario
    clock_stamp_s: np.ndarray  # (M,) camera-clock stamps
    points_V: list  # M arrays (k, 3), vision frame, m
    sphere_label: list  # M arrays (k,), -1 for the tunnel, j for sphere j (truth)
    ins_t_s: np.ndarray  # (K,)
    ins_R: np.ndarray  # (K, 3, 3) INS attitude world_R_imu
    ins_r: np.ndarray  # (K, 3)
    ins_v: np.ndarray  # (K, 3)
    ins_gyro: np.ndarray  # (K, 3) raw gyro (what the INS integrated)
    ins_accel: np.ndarray  # (K, 3) raw accelerometer
    true_R: np.ndarray  # (M, 3, 3) true world_R_imu at each clock
    true_r: np.ndarray  # (M, 3)
    error_terms: np.ndarray  # (15,)
    sphere_centers: np.ndarray  # (S, 3)
    sphere_radius_true_m: float
    left: LineCamera
    right: LineCamera
    imu_R_vision: np.ndarray  # calibrated (as written to the recording)
    imu_t_vision: np.ndarray
    mesh: o3d.geometry.TriangleMesh  # tunnel only
    truth_R_all: np.ndarray = None  # (K, 3, 3) truth at the INS samples
    truth_r_all: np.ndarray = None

    def reference_mesh(self) -> o3d.geometry.TriangleMesh:
        """Tunnel + spheres (the true object) for QC."""
        mesh = o3d.geometry.TriangleMesh(self.mesh)
        for c in self.sphere_centers:
            s = o3d.geometry.TriangleMesh.create_sphere(self.sphere_radius_true_m, resolution=60)
            s.translate(c)
            mesh += s
        return mesh


def tunnel_mesh(scenario: ScanScenario, x_range: tuple[float, float], segments: int = 720,
                x_step_m: float = 0.5) -> o3d.geometry.TriangleMesh:
    """Vault (cylinder about x, radius R, above the floor) + floor, as one open3d mesh, normals inward."""
    R, zf = scenario.tunnel_radius_m, scenario.floor_z_m
    a0 = np.arcsin(np.clip(zf / R, -1, 1))  # angle (from +y towards +z) where the vault meets the floor
    angles = np.linspace(a0, np.pi - a0, segments + 1)
    xs = np.arange(x_range[0], x_range[1] + x_step_m, x_step_m)
    ring = np.column_stack([R * np.cos(angles), R * np.sin(angles)])
    verts = np.array([[x, y, z] for x in xs for y, z in ring])
    n_ring = len(ring)
    tris = []
    for i in range(len(xs) - 1):
        for j in range(n_ring - 1):
            a, b = i * n_ring + j, i * n_ring + j + 1
            c, d = a + n_ring, b + n_ring
            tris += [[a, c, b], [b, c, d]]
    y_floor = R * np.cos(a0)
    base = len(verts)
    floor = np.array([[x, y, zf] for x in xs for y in (-y_floor, y_floor)])
    verts = np.vstack([verts, floor])
    for i in range(len(xs) - 1):
        a, b, c, d = base + 2 * i, base + 2 * i + 1, base + 2 * i + 2, base + 2 * i + 3
        tris += [[a, b, c], [b, d, c]]
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(np.array(tris)))
    mesh.compute_vertex_normals()
    return mesh


def _trajectory(sc: ScanScenario, t: np.ndarray, phase: np.ndarray):
    """True positions (N, 3) and attitudes (N, 3, 3) at times t (analytic)."""
    T = sc.length_m / sc.speed_m_s
    w = 2 * np.pi / T
    x = sc.speed_m_s * t - sc.speed_change_m_s / w * np.sin(w * t)  # speed v - dv cos(w t): slow, fast, slow
    y = sc.sway_m * np.sin(2 * np.pi * t / 2.7 + phase[0])
    z = sc.imu_height_m + sc.heave_m * np.sin(2 * np.pi * t / 1.3 + phase[1])
    roll = np.radians(sc.roll_deg) * np.sin(2 * np.pi * t / 1.9 + phase[2])
    pitch = np.radians(sc.pitch_deg) * np.sin(2 * np.pi * t / 1.1 + phase[3])
    yaw = 0.002 * np.sin(2 * np.pi * t / 3.1 + phase[4])
    from scipy.spatial.transform import Rotation
    R = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll])).as_matrix()
    return np.column_stack([x, y, z]), R


class _Scene:
    """Ray casting against the tunnel mesh (open3d) and the spheres (analytic)."""

    def __init__(self, mesh, centers, radius):
        self.scene = None
        if mesh is not None:  # None: the spheres alone
            self.scene = o3d.t.geometry.RaycastingScene()
            self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        self.centers, self.radius = np.asarray(centers, float), float(radius)

    def cast(self, origins, dirs):
        """Distance along unit ``dirs`` to the first hit (inf: none) and what was hit (-1 tunnel, j sphere)."""
        if self.scene is None:
            t_mesh = np.full(len(dirs), np.inf)
        else:
            rays = o3d.core.Tensor(np.hstack([origins, dirs]).astype(np.float32))
            t_mesh = self.scene.cast_rays(rays)["t_hit"].numpy().astype(float)
        label = np.full(len(dirs), -1)
        t = t_mesh.copy()
        for j, c in enumerate(self.centers):
            oc = origins - c
            b = np.einsum("ij,ij->i", oc, dirs)
            disc = b * b - (np.einsum("ij,ij->i", oc, oc) - self.radius**2)
            with np.errstate(invalid="ignore"):
                ts = -b - np.sqrt(disc)
            hit = (disc > 0) & (ts > 0) & (ts < t)
            t[hit], label[hit] = ts[hit], j
        # open3d casts in float32: mesh hits carry ~1e-7 relative rounding (a few micrometres), far below the
        # point noise; the spheres, where the estimator looks, are exact
        return t, label


def _place_spheres(sc: ScanScenario, rng, imu_R_vision, imu_t_vision) -> np.ndarray:
    """Sphere centres in the common field of view, spaced along the track, clear of the walls."""
    n = sc.n_spheres
    margin = 1.5
    xs = np.linspace(margin, sc.length_m - margin, n) + rng.uniform(-0.3, 0.3, n)
    centers = []
    cam_W = imu_t_vision + np.array([0.0, 0.0, sc.imu_height_m])  # left camera with the vehicle level at y = 0
    for x in xs:
        for _ in range(100):
            ang = np.radians(rng.uniform(-20.0, 20.0))  # in the scan plane, about the optical axis
            rng_m = rng.uniform(*sc.sphere_range_m)
            d_V = np.array([np.sin(ang), 0.0, np.cos(ang)])
            c = cam_W + imu_R_vision @ d_V * rng_m
            c[0] = x
            wall_gap = sc.tunnel_radius_m - np.hypot(c[1], c[2])
            if wall_gap > 3 * sc.sphere_radius_m and c[2] - sc.floor_z_m > 3 * sc.sphere_radius_m:
                centers.append(c)
                break
    return np.array(centers)


def simulate_scan(scenario: ScanScenario | None = None, seed: int = 0, spheres_only: bool = False) -> ScanSimulation:
    """Simulate a scan (see the module docstring); everything random comes from ``seed``.

    ``spheres_only``: the spheres without the tunnel (no wall hits, no occlusion by the walls), and only the
    clocks whose scan plane cuts a sphere are cast (the others hold no point): the sphere profiles a plan's
    covariance analysis needs, in a fraction of the time.
    """
    sc = scenario or ScanScenario()
    rng = np.random.default_rng(seed)
    h = 1.0 / sc.ins_rate_hz
    duration = sc.length_m / sc.speed_m_s
    K = int(round(duration * sc.ins_rate_hz)) + 1
    t = np.arange(K + 1) * h
    phase = rng.uniform(0, 2 * np.pi, 5)
    r_true, R_true = _trajectory(sc, t, phase)
    # velocity and specific force as the finite differences the strapdown recursion integrates exactly
    v_true = np.diff(r_true, axis=0) / h  # (K, 3)
    a_true = np.diff(v_true, axis=0) / h  # (K - 1, 3)
    R_true, r_true, t = R_true[:K], r_true[:K], t[:K]
    f_true = np.einsum("kji,kj->ki", R_true[:-1], a_true - ms.GRAVITY_W_M_S2)
    f_true = np.vstack([f_true, f_true[-1]])
    w_true = so3.log(np.einsum("kji,kjl->kil", R_true[:-1], R_true[1:])) / h
    w_true = np.vstack([w_true, w_true[-1]])

    theta = (np.asarray(sc.error_terms, float) if sc.error_terms is not None
             else rng.normal(0.0, 1.0, 15) * np.asarray(sc.error_sigmas, float))
    psi0 = ms._ATT @ theta[0:3]
    gyro = w_true * (1.0 + np.asarray(sc.gyro_scale)) + theta[9:12]
    accel = f_true * (1.0 + np.asarray(sc.accel_scale)) + theta[12:15]
    ins_R, ins_v, ins_r = ms.strapdown(so3.exp(psi0) @ R_true[0], v_true[0] + theta[3:6], r_true[0] + theta[6:9],
                                       gyro, accel, t)
    # output jitter (quantisation, interpolation inside the INS): white, not propagated
    ins_R_out = ins_R @ so3.exp(rng.normal(0.0, sc.ins_jitter_rad, (K, 3)))
    ins_r_out = ins_r + rng.normal(0.0, sc.ins_jitter_m, (K, 3))

    imu_R_vision, imu_t_vision = default_imu_T_vision()
    true_R_IV = imu_R_vision @ so3.exp(np.asarray(sc.extrinsic_rotation_rad, float))
    left, right = default_stereo()
    centers = _place_spheres(sc, rng, imu_R_vision, imu_t_vision)
    radius_true = sc.sphere_radius_m + sc.sphere_radius_error_m
    mesh = tunnel_mesh(sc, (-5.0, sc.length_m + 5.0))
    scene = _Scene(None if spheres_only else mesh, centers, radius_true)

    # clocks: the events happen on the INS grid; the camera stamps them dt earlier (t_ins = t_cam + dt)
    step = int(round(sc.ins_rate_hz / sc.clock_hz))
    clock_idx = np.arange(0, K, step)
    true_R_c, true_r_c = R_true[clock_idx], r_true[clock_idx]
    u = np.arange(0.5 * sc.pixel_step, left.width_px, sc.pixel_step)
    norm = cv2.undistortPoints(np.column_stack([u, np.full_like(u, left.K[1, 2])]).reshape(-1, 1, 2),
                               left.K, left.dist).reshape(-1, 2)
    dir_V = np.column_stack([norm[:, 0], np.zeros(len(u)), np.ones(len(u))])
    dir_V /= np.linalg.norm(dir_V, axis=1, keepdims=True)
    right_R_left = right.vision_R_cam.T  # X_R = R X_V + t (OpenCV convention)
    right_t_left = -right.vision_R_cam.T @ right.vision_t_cam
    rvec_R, _ = cv2.Rodrigues(right_R_left)
    P_left = np.hstack([np.eye(3), np.zeros((3, 1))])
    P_right = np.hstack([right_R_left, right_t_left[:, None]])
    points_V, labels = [], []
    step_at_s = t[0] + sc.sphere_radius_step_at * (t[-1] - t[0])
    for t_c, R_WI, r_WI in zip(t[clock_idx], true_R_c, true_r_c):
        R_WV = R_WI @ true_R_IV
        o_W = R_WI @ imu_t_vision + r_WI
        d_W = dir_V @ R_WV.T
        tl, lab = scene.cast(np.broadcast_to(o_W, d_W.shape).copy(), d_W)
        ok = np.isfinite(tl)
        if not ok.any():  # only without the tunnel: the scan plane cuts no sphere
            points_V.append(np.zeros((0, 3)))
            labels.append(np.zeros(0, dtype=int))
            continue
        X_W = o_W + d_W[ok] * tl[ok][:, None]
        lab = lab[ok]
        X_V = (X_W - o_W) @ R_WV  # exact point in the vision frame
        if (sc.sphere_radius_per_range or sc.sphere_radius_step_m) and np.any(lab >= 0):
            on = lab >= 0
            c_V = (centers[lab[on]] - o_W) @ R_WV
            grow = (sc.sphere_radius_per_range * (np.linalg.norm(c_V, axis=1) - np.mean(sc.sphere_range_m))
                    + (sc.sphere_radius_step_m if t_c >= step_at_s else 0.0))
            X_V[on] = c_V + (X_V[on] - c_V) * (1.0 + grow / radius_true)[:, None]
            X_W = o_W + X_V @ R_WV.T
        # right camera: in front, in the field, and not occluded
        c_R_W = o_W + R_WV @ right.vision_t_cam
        to = X_W - c_R_W
        dist_R = np.linalg.norm(to, axis=1)
        tr, _ = scene.cast(np.broadcast_to(c_R_W, to.shape).copy(), to / dist_R[:, None])
        uvR, _ = cv2.projectPoints(X_V.reshape(-1, 1, 3), rvec_R, right_t_left, right.K, right.dist)
        uvR = uvR.reshape(-1, 2)
        z_R = X_V @ right_R_left[2] + right_t_left[2]
        visible = (tr > dist_R - 1e-3) & (z_R > 0) & (uvR[:, 0] >= 0) & (uvR[:, 0] < right.width_px)
        uvL, _ = cv2.projectPoints(X_V[visible].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), left.K, left.dist)
        uvL = uvL.reshape(-1, 2)
        uvR = uvR[visible]
        n = len(uvL)
        # matching noise along the line only: the row is the sensor's single row on both cameras
        uvL[:, 0] += rng.normal(0.0, sc.pixel_sigma, n) if sc.pixel_sigma > 0 else 0.0
        uvR[:, 0] += rng.normal(0.0, sc.pixel_sigma, n) if sc.pixel_sigma > 0 else 0.0
        uvR[:, 0] += sc.disparity_offset_px
        nL = cv2.undistortPoints(uvL.reshape(-1, 1, 2), left.K, left.dist).reshape(-1, 2)
        nR = cv2.undistortPoints(uvR.reshape(-1, 1, 2), right.K, right.dist).reshape(-1, 2)
        Xh = cv2.triangulatePoints(P_left, P_right, nL.T.astype(float), nR.T.astype(float))
        points_V.append((Xh[:3] / Xh[3]).T)
        labels.append(lab[visible])
    stamps = t[clock_idx] - sc.time_offset_s
    log.info("simulated %d clocks, %d points, %d spheres", len(clock_idx), sum(len(p) for p in points_V),
             len(centers))
    return ScanSimulation(sc, stamps, points_V, labels, t, ins_R_out, ins_r_out, ins_v, gyro, accel,
                          true_R_c, true_r_c, theta, centers, radius_true, left, right, imu_R_vision,
                          imu_t_vision, mesh, R_true, r_true)


def scan_sensor_meta(sim: ScanSimulation) -> dict:
    sc = sim.scenario
    return {"sensor_type": "line_scan_stereo", "rate_hz": sc.clock_hz, "file_pattern": "{timestamp}.npy",
            "frame": "vision (left camera): x along the line, z optical axis, scan plane y = 0",
            "cameras": {"left": sim.left.to_dict(), "right": sim.right.to_dict()},
            "imu_R_vision": sim.imu_R_vision.tolist(), "imu_t_vision": sim.imu_t_vision.tolist(),
            "pixel_sigma": sc.pixel_sigma, "sphere_radius_m": sc.sphere_radius_m}


INS_COLUMNS = (("p_WI_x", "m"), ("p_WI_y", "m"), ("p_WI_z", "m"), ("q_WI_w", "1"), ("q_WI_x", "1"),
               ("q_WI_y", "1"), ("q_WI_z", "1"), ("v_WI_x", "m s^-1"), ("v_WI_y", "m s^-1"), ("v_WI_z", "m s^-1"),
               ("w_RS_S_x", "rad s^-1"), ("w_RS_S_y", "rad s^-1"), ("w_RS_S_z", "rad s^-1"),
               ("a_RS_S_x", "m s^-2"), ("a_RS_S_y", "m s^-2"), ("a_RS_S_z", "m s^-2"))


def write_scan_recording(sim: ScanSimulation, path, overwrite: bool = False) -> Path:
    """Write the recording (module docstring) with ``truth/`` and the reference mesh."""
    from scipy.spatial.transform import Rotation

    from selfcal.io.recording import Recording, SensorData, write_recording
    sc = sim.scenario
    stamps_ns = np.round(sim.clock_stamp_s * 1e9).astype(np.int64) + 1_000_000_000  # stay positive
    ins_ns = np.round(sim.ins_t_s * 1e9).astype(np.int64) + 1_000_000_000
    counts = np.array([len(p) for p in sim.points_V], dtype=float)
    scan = SensorData("scan0", stamps_ns, {"points": counts, "file_index": np.arange(len(counts), dtype=float)},
                      {"points": "1", "file_index": "1"}, scan_sensor_meta(sim))
    q = Rotation.from_matrix(sim.ins_R).as_quat()  # x y z w
    cols = np.column_stack([sim.ins_r, q[:, 3], q[:, :3], sim.ins_v, sim.ins_gyro, sim.ins_accel])
    ins = SensorData("ins0", ins_ns, {n: cols[:, j].copy() for j, (n, _) in enumerate(INS_COLUMNS)},
                     {n: u for n, u in INS_COLUMNS},
                     {"sensor_type": "ins", "rate_hz": sc.ins_rate_hz, "frame": "world_T_imu, world z up",
                      "error_term_names": list(ms.ERROR_TERMS), "error_term_sigmas": np.asarray(sc.error_sigmas).tolist(),
                      "pose_jitter_m": sc.ins_jitter_m, "pose_jitter_rad": sc.ins_jitter_rad})
    extra = {}
    for ts, pts in zip(stamps_ns, sim.points_V):
        buf = io.BytesIO()
        np.save(buf, pts.astype(np.float32))
        extra[f"scan0/{ts}.npy"] = buf.getvalue()
    buf = io.BytesIO()
    np.savez_compressed(buf, true_R=sim.true_R, true_r=sim.true_r, stamps_ns=stamps_ns,
                        labels=np.concatenate(sim.sphere_label).astype(np.int16), counts=counts.astype(np.int64))
    extra["truth/poses.npz"] = buf.getvalue()
    with tempfile.TemporaryDirectory() as tmp:
        mesh_file = os.path.join(tmp, "reference_mesh.ply")
        o3d.io.write_triangle_mesh(mesh_file, sim.reference_mesh())
        extra["truth/reference_mesh.ply"] = Path(mesh_file).read_bytes()
    truth = {"error_terms": dict(zip(ms.ERROR_TERMS, sim.error_terms.tolist())),
             "sphere_centers_m": sim.sphere_centers.tolist(), "sphere_radius_true_m": sim.sphere_radius_true_m,
             "time_offset_s": sc.time_offset_s, "extrinsic_rotation_rad": np.asarray(sc.extrinsic_rotation_rad).tolist(),
             "sphere_radius_error_m": sc.sphere_radius_error_m, "accel_scale": np.asarray(sc.accel_scale).tolist(),
             "gyro_scale": np.asarray(sc.gyro_scale).tolist(),
             "scenario": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(sc).items()}}
    rec = Recording(None, {"ins0": ins, "scan0": scan})
    return write_recording(rec, path, truth=truth, overwrite=overwrite, extra_files=extra)
