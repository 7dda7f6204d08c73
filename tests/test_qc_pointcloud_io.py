"""Point-cloud and mesh I/O: round trips, and clear refusals of empty, unreadable and non-finite input."""
import gzip

import numpy as np
import open3d as o3d
import pytest

from selfcal.core.errors import USER_ERRORS
from selfcal.io.pointcloud import (PointCloudError, cloud_from_points, points_of, read_point_cloud,
                                   read_triangle_mesh, write_point_cloud, write_triangle_mesh)


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_round_trip_keeps_the_points(tmp_path, suffix):
    pts = np.random.default_rng(0).normal(size=(500, 3)) * 10
    path = write_point_cloud(tmp_path / f"c{suffix}", pts)
    got = read_point_cloud(path)
    if suffix == ".ply":  # binary double: bit-exact
        np.testing.assert_array_equal(points_of(got.cloud), pts)
    else:  # open3d's PCD writer stores float32: rounding to 2^-24 relative
        np.testing.assert_allclose(points_of(got.cloud), pts, rtol=2.0**-24, atol=0)
    assert got.n_read == 500 and got.n_nonfinite == 0
    assert [p.name for p in tmp_path.iterdir()] == [f"c{suffix}"]  # no temporary left behind


def test_nonfinite_points_refused_or_dropped_and_counted(tmp_path):
    pts = np.random.default_rng(1).random((100, 3))
    pts[[3, 40], 1] = np.nan
    pts[7, 2] = np.inf
    path = write_point_cloud(tmp_path / "c.ply", pts)
    with pytest.raises(PointCloudError, match="3 of 100 points are non-finite"):
        read_point_cloud(path)
    got = read_point_cloud(path, drop_nonfinite=True)
    assert got.n_nonfinite == 3 and len(got.cloud.points) == 97
    assert np.isfinite(points_of(got.cloud)).all()
    write_point_cloud(tmp_path / "nan.ply", np.full((10, 3), np.nan))
    with pytest.raises(PointCloudError, match="all 10 points"):
        read_point_cloud(tmp_path / "nan.ply", drop_nonfinite=True)


def test_empty_unknown_and_missing_files(tmp_path):
    (tmp_path / "e.ply").write_text("")
    with pytest.raises(PointCloudError, match="empty"):
        read_point_cloud(tmp_path / "e.ply")
    (tmp_path / "c.las").write_text("x")
    with pytest.raises(PointCloudError, match="unknown point cloud format"):
        read_point_cloud(tmp_path / "c.las")
    with pytest.raises(FileNotFoundError):
        read_point_cloud(tmp_path / "none.ply")
    with pytest.raises(PointCloudError, match="empty"):
        write_point_cloud(tmp_path / "w.ply", np.zeros((0, 3)))
    assert issubclass(PointCloudError, USER_ERRORS)


def test_gzipped_ascii_xyz(tmp_path):
    pts = np.random.default_rng(2).random((20, 3))
    with gzip.open(tmp_path / "s.xyz.gz", "wt") as f:
        np.savetxt(f, pts)
    np.testing.assert_allclose(points_of(read_point_cloud(tmp_path / "s.xyz.gz").cloud), pts, rtol=1e-15)
    with gzip.open(tmp_path / "bad.xyz.gz", "wt") as f:
        f.write("1 2\n3 4\n")
    with pytest.raises(PointCloudError, match="columns"):
        read_point_cloud(tmp_path / "bad.xyz.gz")


def test_mesh_round_trip_and_a_cloud_is_no_mesh(tmp_path):
    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 3.0)
    write_triangle_mesh(tmp_path / "m.ply", mesh)
    got = read_triangle_mesh(tmp_path / "m.ply")
    assert len(got.triangles) == 12
    write_point_cloud(tmp_path / "c.ply", cloud_from_points(np.random.default_rng(3).random((30, 3))))
    with pytest.raises(PointCloudError, match="no triangles"):
        read_triangle_mesh(tmp_path / "c.ply")
