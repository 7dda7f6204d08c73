"""Point-cloud input errors (kept apart from :mod:`selfcal.io.pointcloud` so that importing the error class
does not import open3d)."""


class PointCloudError(ValueError):
    """A point cloud or mesh file that cannot be used (empty, unreadable, non-finite points)."""
