"""Scan models: the 15-term error model against a real strapdown integration, pose correction Jacobian,
stereo point covariance against OpenCV triangulation."""
import numpy as np
import pytest

from selfcal.models import scan as ms
from selfcal.core import so3
from selfcal.sim.scan import ScanScenario, simulate_scan


@pytest.fixture(scope="module")
def sims():
    sc = ScanScenario(length_m=6.0, n_spheres=1, pixel_step=16, ins_jitter_m=0.0, ins_jitter_rad=0.0,
                      error_terms=np.zeros(15))
    clean = simulate_scan(sc, seed=3)
    theta = np.random.default_rng(7).normal(size=15) * ms.DEFAULT_PRIOR_SIGMAS
    sc_err = ScanScenario(**{**sc.__dict__, "error_terms": theta})
    return clean, simulate_scan(sc_err, seed=3), theta


def test_error_model_reproduces_strapdown(sims):
    """The linear model predicts the strapdown's pose error to second order: the residual after correction is
    below 2 % of the error itself (products of errors ~ psi * dv are ~1e-3 relative for these sigmas)."""
    clean, err, theta = sims
    sens = ms.error_sensitivity(err.ins_t_s, err.ins_R, err.ins_accel, err.ins_gyro)
    R, r = ms.corrected_pose(err.ins_R, err.ins_r, sens.Phi[:, :, :15], theta)
    pos_error = np.linalg.norm(err.ins_r - err.truth_r_all, axis=1)
    left = np.linalg.norm(r - err.truth_r_all, axis=1)
    assert pos_error[-1] > 0.01  # the scenario drifts by centimetres: a test that can fail
    assert left.max() < 0.02 * pos_error.max()
    att_left = np.linalg.norm(so3.log(np.swapaxes(R, 1, 2) @ err.truth_R_all), axis=1)
    att_error = np.linalg.norm(so3.log(np.swapaxes(err.ins_R, 1, 2) @ err.truth_R_all), axis=1)
    assert att_left.max() < 0.02 * att_error.max()


def test_corrected_pose_jacobian():
    rng = np.random.default_rng(0)
    Phi = rng.normal(size=(9, 15)) * 0.1
    R0, r0, theta = so3.exp(rng.normal(size=3)), rng.normal(size=3), rng.normal(size=15) * 0.1
    R, r, J = ms.corrected_pose(R0, r0, Phi, theta, with_jacobian=True)
    h = 1e-6
    for i in range(15):
        d = np.zeros(15)
        d[i] = h
        Rp, rp = ms.corrected_pose(R0, r0, Phi, theta + d)
        Rm, rm = ms.corrected_pose(R0, r0, Phi, theta - d)
        num_rot = (so3.log(R.T @ Rp) - so3.log(R.T @ Rm)) / (2 * h)
        num_pos = R.T @ (rp - rm) / (2 * h)
        np.testing.assert_allclose(J[:, i], np.r_[num_rot, num_pos], atol=1e-7)


def test_stereo_covariance_matches_triangulation_scatter():
    """Mahalanobis distance of (noisy - exact) triangulated points: mean 2 (rank-2 covariance in the scan plane).
    With n points the mean of chi2(2)/n has sigma 2/sqrt(n): 5 sigma bound."""
    sc = ScanScenario(length_m=2.0, n_spheres=1, pixel_step=8, ins_jitter_m=0.0, ins_jitter_rad=0.0)
    noisy = simulate_scan(sc, seed=4)
    exact = simulate_scan(ScanScenario(**{**sc.__dict__, "pixel_sigma": 0.0}), seed=4)
    pairs = [(a, b) for a, b in zip(noisy.points_V, exact.points_V) if len(a) == len(b)]
    d = np.concatenate([a - b for a, b in pairs])
    C = ms.stereo_point_covariance(np.concatenate([b for _, b in pairs]), [noisy.left, noisy.right], 0.1)
    m = np.einsum("ni,nij,nj->n", d, np.linalg.pinv(C), d)
    assert abs(m.mean() - 2.0) < 5 * 2.0 / np.sqrt(len(m))


def test_remechanized_with_true_terms_recovers_truth(sims):
    """Removing the true 15 terms through the strapdown gives back the true trajectory (exact, no jitter)."""
    _, err, theta = sims
    R, v, r = ms.remechanized(err.ins_t_s, err.ins_R, err.ins_v, err.ins_r, err.ins_gyro, err.ins_accel, theta)
    assert np.abs(err.ins_r - err.truth_r_all).max() > 0.01
    np.testing.assert_allclose(r, err.truth_r_all, atol=1e-9)
    np.testing.assert_allclose(R, err.truth_R_all, atol=1e-9)
