"""A simulated VDI/VDE 2634-2 test artefact and its scans: a flat plate with spheres above it (numpy only).

The artefact (world frame, m, z up): a plate ``[0, Lx] x [0, Ly]`` at ``z = 0`` and spheres of radius ``R``
whose centres stand ``R + clearance`` above it (on rods the scanner does not resolve).  A scan samples points
uniformly over the plate and over the visible cap of each sphere (half-angle ``cap_deg`` about +z, the
scanner looking down), with Gaussian noise ``sigma_m`` along the surface normal.  Known errors can be put
into the scan to make a QC fail on purpose:

* ``scale_error`` (dimensionless): every coordinate scaled by ``1 + s`` about the origin, so a calibrated
  centre distance ``L`` is measured ``(1 + s) L`` (sphere-spacing error ``s L``, size error ``2 s R``);
* ``bump_m``: a Gaussian bump of this height (sigma ``Lx / 8``) in the middle of the plate (flatness and
  deviation, spheres untouched).

The reference mesh (plate as two triangles, spheres as UV spheres with outward winding) comes as vertex and
triangle arrays; the tessellation error of the spheres is ``R (1 - cos(pi / n_lat))`` at most.

Truth is kept as attributes; :meth:`scan` is seeded (``np.random.default_rng``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PlateWithSpheres:
    """The artefact; all lengths in metres."""

    plate_m: tuple[float, float] = (1.0, 0.6)
    radius_m: float = 0.05
    clearance_m: float = 0.05
    sphere_xy_m: np.ndarray = field(default_factory=lambda: np.array([[0.15, 0.15], [0.85, 0.15], [0.5, 0.45]]))
    names: tuple[str, ...] = ("A", "B", "C")

    @property
    def centres_m(self) -> np.ndarray:
        """Sphere centres (K, 3)."""
        z = np.full(len(self.sphere_xy_m), self.radius_m + self.clearance_m)
        return np.column_stack([self.sphere_xy_m, z])

    def distances(self) -> list[tuple[str, str, float]]:
        """Calibrated centre distances of every pair."""
        c = self.centres_m
        return [(self.names[i], self.names[j], float(np.linalg.norm(c[i] - c[j])))
                for i in range(len(c)) for j in range(i + 1, len(c))]

    def mesh_arrays(self, n_lat: int = 90, n_lon: int = 180) -> tuple[np.ndarray, np.ndarray]:
        """Reference mesh as (vertices (V, 3), triangles (T, 3) int) with outward counter-clockwise winding."""
        lx, ly = self.plate_m
        verts = [np.array([[0, 0, 0], [lx, 0, 0], [lx, ly, 0], [0, ly, 0]], dtype=float)]
        tris = [np.array([[0, 1, 2], [0, 2, 3]])]
        offset = 4
        theta = np.linspace(0, np.pi, n_lat + 1)[1:-1]  # polar angle, poles added separately
        phi = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
        ring = np.stack(np.meshgrid(theta, phi, indexing="ij"), axis=-1).reshape(-1, 2)
        unit = np.column_stack([np.sin(ring[:, 0]) * np.cos(ring[:, 1]), np.sin(ring[:, 0]) * np.sin(ring[:, 1]),
                                np.cos(ring[:, 0])])
        unit = np.vstack([[0, 0, 1], unit, [0, 0, -1]])
        n_ring = n_lat - 1
        sphere_tris = []
        idx = lambda i, j: 1 + i * n_lon + (j % n_lon)  # noqa: E731  (ring i, longitude j)
        for j in range(n_lon):
            sphere_tris.append([0, idx(0, j), idx(0, j + 1)])
            sphere_tris.append([len(unit) - 1, idx(n_ring - 1, j + 1), idx(n_ring - 1, j)])
            for i in range(n_ring - 1):
                sphere_tris.append([idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)])
                sphere_tris.append([idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)])
        sphere_tris = np.array(sphere_tris)
        for c in self.centres_m:
            verts.append(c + self.radius_m * unit)
            tris.append(sphere_tris + offset)
            offset += len(unit)
        return np.vstack(verts), np.vstack(tris).astype(np.int32)

    def scan(self, n_points: int, sigma_m: float = 0.0002, cap_deg: float = 100.0, seed: int = 0,
             scale_error: float = 0.0, bump_m: float = 0.0, sphere_point_share: float | None = None,
             dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
        """A scan: points (N, 3) and the truth label per point (-1 plate, k sphere k).

        ``sphere_point_share`` is the fraction of points on the spheres (default: by visible area, i.e. a
        uniform point density over the whole artefact).
        """
        rng = np.random.default_rng(seed)
        lx, ly = self.plate_m
        k = len(self.sphere_xy_m)
        cap_area = 2 * np.pi * self.radius_m**2 * (1 - np.cos(np.radians(cap_deg)))
        share = sphere_point_share if sphere_point_share is not None else k * cap_area / (k * cap_area + lx * ly)
        n_sphere = int(round(n_points * share / k)) if k else 0
        n_plate = n_points - k * n_sphere
        out = np.empty((n_points, 3), dtype=dtype)
        labels = np.empty(n_points, dtype=np.int16)
        x, y = rng.uniform(0, lx, n_plate), rng.uniform(0, ly, n_plate)
        z = sigma_m * rng.standard_normal(n_plate)
        if bump_m:
            z += bump_m * np.exp(-((x - lx / 2) ** 2 + (y - ly / 2) ** 2) / (2 * (lx / 8) ** 2))
        out[:n_plate, 0], out[:n_plate, 1], out[:n_plate, 2] = x, y, z
        labels[:n_plate] = -1
        start = n_plate
        for j, c in enumerate(self.centres_m):
            cos_t = rng.uniform(np.cos(np.radians(cap_deg)), 1.0, n_sphere)
            phi = rng.uniform(0, 2 * np.pi, n_sphere)
            sin_t = np.sqrt(1 - cos_t**2)
            r = self.radius_m + sigma_m * rng.standard_normal(n_sphere)
            out[start:start + n_sphere] = c + r[:, None] * np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi),
                                                                           cos_t])
            labels[start:start + n_sphere] = j
            start += n_sphere
        if scale_error:
            out *= 1.0 + scale_error
        return out, labels


@dataclass
class LidarSphereScenes:
    """One sphere seen by a scanning LiDAR (origin = its range zero point) in several scenes at different ranges.

    Rays on an azimuth x elevation grid (``azimuth_step_deg`` x ``ring_step_deg``) are cast at the sphere; a
    return's range is the true one plus ``range_offset_m`` (the catalog's ``range_offset``), white noise
    ``range_noise_m`` and, to hide effects the audit's catalog does not list:

    * ``radius_slope``: the sphere looks bigger or smaller with range, ``R(d) = R + slope (d - d_mid)``
      (dimensionless: m of radius per m of range; beam-footprint growth mixing edge returns with background);
    * ``incidence_error_m``: a range error growing with the incidence angle ``i``,
      ``a (i / 90 deg)^2`` (footprint elongation on a surface seen at a slant).

    ``scene_radius_sigma_m``: each scene's sphere radius off by its own N(0, s^2) (a target that is not a
    reference sphere, a different cap seen each time).  Truth is kept as attributes.
    """

    ranges_m: tuple[float, ...] = (2.5, 1.8, 3.2, 2.2, 3.5, 2.0, 2.7, 3.0)  # in scan order: not sorted, so that
    # range and time are not the same driver
    radius_m: float = 0.3
    range_noise_m: float = 0.005
    range_offset_m: float = 0.0
    radius_slope: float = 0.0
    incidence_error_m: float = 0.0
    scene_radius_sigma_m: float = 0.0
    azimuth_step_deg: float = 0.4
    ring_step_deg: float = 1.0

    def centres_m(self, seed: int) -> np.ndarray:
        """Scene centres: the given ranges, random azimuth (+-60 deg) and elevation (+-10 deg)."""
        rng = np.random.default_rng([seed, 1])
        az = np.radians(rng.uniform(-60, 60, len(self.ranges_m)))
        el = np.radians(rng.uniform(-10, 10, len(self.ranges_m)))
        u = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        return u * np.asarray(self.ranges_m, dtype=float)[:, None]

    def scene_radii_m(self, seed: int) -> np.ndarray:
        rng = np.random.default_rng([seed, 2])
        d = np.asarray(self.ranges_m, dtype=float)
        return (self.radius_m + self.radius_slope * (d - 0.5 * (d.min() + d.max()))
                + self.scene_radius_sigma_m * rng.normal(size=len(d)))

    def scenes(self, seed: int) -> list[np.ndarray]:
        """Returns (N_s, 3) per scene, sensor frame, m."""
        rng = np.random.default_rng([seed, 3])
        out = []
        for c, radius in zip(self.centres_m(seed), self.scene_radii_m(seed)):
            d = np.linalg.norm(c)
            half = np.arcsin(min(radius / d, 1.0)) + np.radians(self.ring_step_deg)
            az0, el0 = np.arctan2(c[1], c[0]), np.arcsin(c[2] / d)
            az = np.arange(az0 - half / np.cos(el0), az0 + half / np.cos(el0), np.radians(self.azimuth_step_deg))
            el = np.arange(np.floor((el0 - half) / np.radians(self.ring_step_deg)),
                           np.ceil((el0 + half) / np.radians(self.ring_step_deg)) + 1) * np.radians(self.ring_step_deg)
            A, E = np.meshgrid(az, el)
            u = np.column_stack([(np.cos(E) * np.cos(A)).ravel(), (np.cos(E) * np.sin(A)).ravel(), np.sin(E).ravel()])
            uc = u @ c
            disc = uc**2 - (d**2 - radius**2)
            u, uc, disc = u[disc > 0], uc[disc > 0], disc[disc > 0]
            rho = uc - np.sqrt(disc)
            normal = (u * rho[:, None] - c) / radius
            incidence = np.arccos(np.clip(-np.einsum("ij,ij->i", normal, u), -1.0, 1.0))
            rho = (rho + self.range_offset_m + self.incidence_error_m * (incidence / (0.5 * np.pi)) ** 2
                   + self.range_noise_m * rng.normal(size=len(rho)))
            out.append(u * rho[:, None])
        return out
