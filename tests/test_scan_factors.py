"""Scan factors (patent 001): Jacobians against numerical derivatives at seeded random points, H=None path,
zero error on exact simulated data."""
import gtsam
import numpy as np
import pytest

from factor_checks import assert_factor_jacobians
from selfcal.factors import scan as fs
from selfcal.models import scan as ms
from selfcal.core import so3
from selfcal.sim.scan import ScanScenario, simulate_scan


def _random_pose(rng):
    return gtsam.Pose3(gtsam.Rot3(so3.exp(rng.normal(size=3))), rng.normal(size=3))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sphere_surface_factor_jacobians(seed):
    rng = np.random.default_rng(seed)
    R_IV, t_IV = so3.exp(rng.normal(size=3)), rng.normal(size=3) * 0.3
    p_V = rng.normal(size=(9, 3))
    sig = rng.uniform(5e-4, 2e-3, 9)
    full = fs.sphere_surface_factor(sig, p_V, R_IV, t_IV, 0.1, 1, 2, extrinsic_key=3, radius_key=4)
    assert_factor_jacobians(full, {1: _random_pose(rng), 2: rng.normal(size=3), 3: rng.normal(size=3) * 0.2,
                                   4: np.array([0.01])})
    base = fs.sphere_surface_factor(sig, p_V, R_IV, t_IV, 0.1, 1, 2)
    assert_factor_jacobians(base, {1: _random_pose(rng), 2: rng.normal(size=3)})


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_inertial_tie_factor_jacobians(seed):
    rng = np.random.default_rng(seed)
    Phi = rng.normal(size=(9, ms.N_FULL))
    blocks = [(5, np.arange(15), rng.uniform(0.01, 0.1, 15)), (6, np.arange(15, 18), 0.02)]
    f = fs.inertial_tie_factor(rng.uniform(1e-3, 1e-2, 6), so3.exp(rng.normal(size=3)), rng.normal(size=3), Phi,
                               1, blocks, time_offset_key=7, twist=rng.normal(size=6))
    assert_factor_jacobians(f, {1: _random_pose(rng), 5: rng.normal(size=15), 6: rng.normal(size=3),
                                7: np.array([0.05])}, atol=1e-5)
    g = fs.inertial_tie_factor(np.full(6, 1e-3), so3.exp(rng.normal(size=3)), rng.normal(size=3), Phi, 1, blocks[:1])
    assert_factor_jacobians(g, {1: _random_pose(rng), 5: rng.normal(size=15)}, atol=1e-5)


@pytest.fixture(scope="module")
def exact_sim():
    sc = ScanScenario(length_m=4.0, n_spheres=2, pixel_sigma=0.0, ins_jitter_m=0.0, ins_jitter_rad=0.0,
                      error_terms=np.zeros(15), pixel_step=8)
    return simulate_scan(sc, seed=5)


def test_sphere_factor_zero_on_exact_data(exact_sim):
    """Noise-free triangulation at the true pose and centre: residuals at the level of float rounding."""
    sim = exact_sim
    worst = 0.0
    n = 0
    for m, (p, lab) in enumerate(zip(sim.points_V, sim.sphere_label)):
        for j in set(lab.tolist()) - {-1}:
            f = fs.sphere_surface_factor(np.full((lab == j).sum(), 1e-3), p[lab == j], sim.imu_R_vision,
                                         sim.imu_t_vision, sim.sphere_radius_true_m, 1, 2)
            v = gtsam.Values()
            v.insert(1, gtsam.Pose3(gtsam.Rot3(sim.true_R[m]), sim.true_r[m]))
            v.insert(2, sim.sphere_centers[j])
            worst = max(worst, np.abs(f.unwhitenedError(v)).max())
            n += 1
    assert n > 10
    assert worst < 1e-7  # m: triangulation of exact pixels is exact to rounding


def test_tie_factor_zero_on_exact_data(exact_sim):
    """No INS error, no jitter: the INS pose is the true pose and the tie error vanishes."""
    sim = exact_sim
    sens = ms.error_sensitivity(sim.ins_t_s, sim.ins_R, sim.ins_accel, sim.ins_gyro)
    step = int(sim.scenario.ins_rate_hz / sim.scenario.clock_hz)
    for m in (0, len(sim.true_R) // 2, len(sim.true_R) - 1):
        k = m * step
        f = fs.inertial_tie_factor(np.full(6, 1e-5), sim.ins_R[k], sim.ins_r[k], sens.Phi[k], 1,
                                   [(2, np.arange(15), ms.DEFAULT_PRIOR_SIGMAS)])
        v = gtsam.Values()
        v.insert(1, gtsam.Pose3(gtsam.Rot3(sim.true_R[m]), sim.true_r[m]))
        v.insert(2, np.zeros(15))
        np.testing.assert_allclose(f.unwhitenedError(v), 0.0, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1])
def test_sphere_theta_factor_jacobians(seed):
    rng = np.random.default_rng(seed)
    Phi = rng.normal(size=(9, ms.N_FULL))
    blocks = [(5, np.arange(15), rng.uniform(0.01, 0.1, 15)), (6, np.arange(15, 18), 0.02)]
    f = fs.sphere_theta_factor(rng.uniform(5e-4, 2e-3, 6), rng.normal(size=(6, 3)), so3.exp(rng.normal(size=3)),
                               rng.normal(size=3) * 0.3, 0.1, so3.exp(rng.normal(size=3)), rng.normal(size=3), Phi,
                               2, blocks, time_offset_key=7, twist=rng.normal(size=6), extrinsic_key=3,
                               radius_key=4)
    assert_factor_jacobians(f, {2: rng.normal(size=3), 5: rng.normal(size=15), 6: rng.normal(size=3),
                                7: np.array([0.05]), 3: rng.normal(size=3) * 0.2, 4: np.array([0.01])}, atol=1e-5)
