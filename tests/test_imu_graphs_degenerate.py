"""Degenerate data get an error that says what motion to add, never a silent wrong answer."""
import numpy as np
import pytest

from selfcal.graphs import imu as gi
from selfcal.graphs import imu_pair as gp
from selfcal.core.solve import DegenerateDataError

G = 9.81


def poses_with_up(directions, sigma=1e-3):
    return [gi.StaticPose(G * np.asarray(d) / np.linalg.norm(d), np.zeros(3), np.full(3, sigma), np.full(3, sigma))
            for d in directions]


def test_too_few_poses():
    with pytest.raises(DegenerateDataError, match="at least 9 needed"):
        gi.solve_intrinsics(poses_with_up(np.eye(3)), [], G)


def test_collinear_poses():
    rng = np.random.default_rng(0)
    ups = [[0, 0, 1] + 1e-3 * rng.normal(size=3) for _ in range(12)]
    with pytest.raises(DegenerateDataError, match="same gravity direction"):
        gi.solve_intrinsics(poses_with_up(ups), [], G)


def test_coplanar_poses():
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ups = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1)
    with pytest.raises(DegenerateDataError, match="one plane"):
        gi.solve_intrinsics(poses_with_up(ups), [], G)


def test_pair_without_rotation_excitation():
    """Two static poses with the same gravity direction leave the rotation about it free."""
    v = np.array([0.0, 0.0, G])
    static = [gp.StaticPair(v, v, np.full(3, 1e-3)) for _ in range(2)]
    with pytest.raises(DegenerateDataError, match="two orientations"):
        gp.solve_pair(static, None)


def test_poses_on_one_cone():
    """Turning only about one axis puts the gravity directions on a circle: bias and scale trade off."""
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ups = np.stack([np.cos(angles), np.sin(angles), np.ones_like(angles)], axis=1)
    with pytest.raises(DegenerateDataError, match="one cone"):
        gi.solve_intrinsics(poses_with_up(ups), [], G)
