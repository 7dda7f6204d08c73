"""Point clouds and meshes on disk: PLY / PCD / XYZ (open3d), plain ASCII ``.xyz[.gz]`` (numpy), numpy views.

Points are metres in the frame the file states (the scanner or vision frame of a recording, the world frame of
a corrected scan).  open3d holds the clouds (``open3d.geometry.PointCloud``); the models see ``(N, 3)`` float64
arrays (:func:`points_of`).  Bad input is refused with one line naming the file: an empty cloud, a file
open3d cannot parse, a mesh without triangles; non-finite points (NaN / inf, as some scanners write for "no
return") are either refused or, with ``drop_nonfinite=True``, removed and counted.
"""
from __future__ import annotations

import gzip
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from selfcal.io.atomic import atomic_file
from selfcal.core.errors import SelfcalError

log = logging.getLogger(__name__)

__all__ = ["PointCloudError", "LoadedCloud", "points_of", "cloud_from_points", "read_point_cloud",
           "write_point_cloud", "read_point_attribute", "point_cloud_bytes", "read_triangle_mesh",
           "write_triangle_mesh"]

CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
MESH_SUFFIXES = (".ply", ".stl", ".obj", ".off", ".gltf", ".glb")


class PointCloudError(SelfcalError):
    """A point cloud or mesh file that cannot be used (empty, unreadable, non-finite points)."""


@dataclass
class LoadedCloud:
    """A cloud read from disk and what was removed from it.

    Attributes
    ----------
    cloud : open3d.geometry.PointCloud
        The finite points (with colours / normals where the file has them).
    path : Path
        Where it came from.
    n_read : int
        Points in the file.
    n_nonfinite : int
        Points dropped because a coordinate was NaN or inf.
    """

    cloud: o3d.geometry.PointCloud
    path: Path
    n_read: int
    n_nonfinite: int


def points_of(cloud: o3d.geometry.PointCloud) -> np.ndarray:
    """The points of an open3d cloud as an (N, 3) float64 array (a copy-free view where open3d allows)."""
    return np.asarray(cloud.points)


def cloud_from_points(points_m, colors=None, normals=None) -> o3d.geometry.PointCloud:
    """An open3d cloud from (N, 3) points (m), optional colours in [0, 1] and normals."""
    pts = np.ascontiguousarray(points_m, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise PointCloudError(f"points must be an (N, 3) array, got shape {pts.shape}")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    if colors is not None:
        cloud.colors = o3d.utility.Vector3dVector(np.ascontiguousarray(colors, dtype=np.float64))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals, dtype=np.float64))
    return cloud


def _read_ascii_xyz(path: Path) -> np.ndarray:
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as f:
        try:
            data = np.loadtxt(f, ndmin=2)
        except ValueError as err:
            raise PointCloudError(f"{path}: not a whitespace-separated x y z table ({err})") from err
    if data.size and data.shape[1] < 3:
        raise PointCloudError(f"{path}: {data.shape[1]} columns, need at least x y z")
    return data[:, :3] if data.size else np.zeros((0, 3))


def read_point_cloud(path, drop_nonfinite: bool = False) -> LoadedCloud:
    """Read a point cloud (PLY, PCD, XYZ, ... via open3d; ``.xyz.gz`` / ``.txt`` via numpy).

    Parameters
    ----------
    path : str or Path
        The file.
    drop_nonfinite : bool
        Remove points with a NaN / inf coordinate (and count them) instead of refusing the file.

    Returns
    -------
    LoadedCloud

    Raises
    ------
    FileNotFoundError
        No such file.
    PointCloudError
        Unknown format, unreadable, empty, only non-finite points, or non-finite points without
        ``drop_nonfinite``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such point cloud file")
    name = path.name.lower()
    if name.endswith((".xyz.gz", ".txt", ".txt.gz", ".csv")):
        cloud = cloud_from_points(_read_ascii_xyz(path))
    elif name.endswith(CLOUD_SUFFIXES):
        # open3d drops NaN/inf itself only when asked: keep them so that they can be counted and reported
        cloud = o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    else:
        raise PointCloudError(f"{path}: unknown point cloud format (known: {', '.join(CLOUD_SUFFIXES)}, "
                              ".xyz.gz, .txt)")
    pts = points_of(cloud)
    n_read = len(pts)
    if n_read == 0:
        raise PointCloudError(f"{path}: the point cloud is empty (or open3d could not parse it)")
    finite = np.isfinite(pts).all(axis=1)
    n_bad = int(n_read - np.count_nonzero(finite))
    if n_bad:
        if n_bad == n_read:
            raise PointCloudError(f"{path}: all {n_read} points are non-finite (NaN/inf)")
        if not drop_nonfinite:
            raise PointCloudError(f"{path}: {n_bad} of {n_read} points are non-finite (NaN/inf)")
        log.warning("%s: dropped %d non-finite points of %d", path, n_bad, n_read)
        # rebuilt from numpy: select_by_index would need a Python list of millions of indices
        kept = cloud_from_points(pts[finite],
                                 np.asarray(cloud.colors)[finite] if cloud.has_colors() else None,
                                 np.asarray(cloud.normals)[finite] if cloud.has_normals() else None)
        cloud = kept
    return LoadedCloud(cloud=cloud, path=path, n_read=n_read, n_nonfinite=n_bad)


def write_point_cloud(path, cloud, binary: bool = True, attributes: dict | None = None) -> Path:
    """Write a cloud (open3d cloud or (N, 3) array) atomically; the format follows the suffix (.ply, .pcd).

    open3d writes to a temporary name in the destination folder (same suffix, so the format is kept), which
    is then renamed: a failed write leaves no half file.  PLY keeps float64 coordinates; open3d's PCD writer
    stores float32 (2^-24 relative: 6 mm at 100 km survey coordinates), so write PLY for metrology.
    ``attributes``: per-point scalars ``{name: (N,) array}`` written as PLY vertex properties (float32, through
    open3d's tensor cloud; other readers skip properties they do not know); PLY only.
    """
    path = Path(path)
    if not isinstance(cloud, o3d.geometry.PointCloud):
        cloud = cloud_from_points(cloud)
    if not cloud.has_points():
        raise PointCloudError(f"{path}: refusing to write an empty point cloud")
    if path.suffix.lower() not in (".ply", ".pcd", ".xyz", ".pts"):
        raise PointCloudError(f"{path}: unknown point cloud format for writing (.ply, .pcd, .xyz, .pts)")
    if attributes:
        return _write_with_attributes(path, cloud, attributes, binary)
    with atomic_file(path) as tmp:
        if not o3d.io.write_point_cloud(str(tmp), cloud, write_ascii=not binary):
            raise PointCloudError(f"{path}: open3d could not write the point cloud")
    return path


def _write_with_attributes(path: Path, cloud: o3d.geometry.PointCloud, attributes: dict, binary: bool) -> Path:
    if path.suffix.lower() != ".ply":
        raise PointCloudError(f"{path}: per-point properties ({', '.join(attributes)}) are written to .ply only")
    n = len(cloud.points)
    tensor = o3d.t.geometry.PointCloud(o3d.core.Tensor(points_of(cloud)))
    if cloud.has_colors():
        tensor.point.colors = o3d.core.Tensor(np.asarray(cloud.colors))
    if cloud.has_normals():
        tensor.point.normals = o3d.core.Tensor(np.asarray(cloud.normals))
    for name, values in attributes.items():
        values = np.asarray(values, dtype=np.float32).reshape(-1, 1)
        if len(values) != n:
            raise PointCloudError(f"{path}: property {name!r} has {len(values)} values for {n} points")
        tensor.point[name] = o3d.core.Tensor(values)
    with atomic_file(path) as tmp:
        if not o3d.t.io.write_point_cloud(str(tmp), tensor, write_ascii=not binary):
            raise PointCloudError(f"{path}: open3d could not write the point cloud")
    return path


def read_point_attribute(path, name: str, drop_nonfinite: bool = True) -> np.ndarray | None:
    """The per-point property ``name`` (N,) of a PLY file (None if the file has none), for the points that
    :func:`read_point_cloud` keeps (non-finite points dropped with ``drop_nonfinite``): the same order."""
    path = Path(path)
    if path.suffix.lower() != ".ply":
        return None
    tensor = o3d.t.io.read_point_cloud(str(path))
    if name not in tensor.point:
        return None
    values = tensor.point[name].numpy().reshape(-1).astype(float)
    if drop_nonfinite:
        values = values[np.isfinite(tensor.point.positions.numpy()).all(axis=1)]
    return values


def point_cloud_bytes(points_m, suffix: str = ".ply") -> bytes:
    """The file content of a cloud as open3d writes it (binary PLY by default): a payload that an importer puts
    into a recording (``Recording.payloads``) and :func:`read_point_cloud` reads back."""
    import tempfile
    with tempfile.TemporaryDirectory() as folder:
        file = write_point_cloud(Path(folder) / f"cloud{suffix}", points_m)
        return file.read_bytes()


def read_triangle_mesh(path) -> o3d.geometry.TriangleMesh:
    """Read a reference mesh (PLY, STL, OBJ, OFF, glTF via open3d); refuse one without triangles.

    Raises
    ------
    FileNotFoundError, PointCloudError
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    if not path.name.lower().endswith(MESH_SUFFIXES):
        raise PointCloudError(f"{path}: unknown mesh format (known: {', '.join(MESH_SUFFIXES)})")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if not mesh.has_triangles():
        raise PointCloudError(f"{path}: the mesh has no triangles (empty, or a point cloud saved as .ply?)")
    vertices = np.asarray(mesh.vertices)
    if not np.isfinite(vertices).all():
        raise PointCloudError(f"{path}: the mesh has non-finite vertices")
    return mesh


def write_triangle_mesh(path, mesh: o3d.geometry.TriangleMesh) -> Path:
    """Write a mesh atomically (format from the suffix)."""
    path = Path(path)
    with atomic_file(path) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh):
            raise PointCloudError(f"{path}: open3d could not write the mesh")
    return path
