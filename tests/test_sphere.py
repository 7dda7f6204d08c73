"""Sphere model: residuals and Jacobians, least-squares fit and its covariance (Monte Carlo), RANSAC, coverage."""
import numpy as np
import pytest
from scipy import stats

from selfcal.core.sphere import (SphereNotFoundError, algebraic_sphere, fit_sphere, ransac_sphere,
                                   sphere_coverage, sphere_residuals_and_jacobians, sphere_residuals_m)

CENTER = np.array([1.2, -0.4, 2.5])
RADIUS = 0.3


def cap_points(rng, n, cap_deg=180.0, center=CENTER, radius=RADIUS, axis=(0.0, 0.0, 1.0), sigma=0.0):
    """n points uniform over a spherical cap of half-angle cap_deg about `axis`, radial noise sigma."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    cos_t = rng.uniform(np.cos(np.radians(cap_deg)), 1.0, n)  # uniform in cos -> uniform in area
    phi = rng.uniform(0, 2 * np.pi, n)
    sin_t = np.sqrt(1 - cos_t**2)
    e1 = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    u = cos_t[:, None] * axis + sin_t[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    return center + u * (radius + sigma * rng.standard_normal(n))[:, None]


def test_residuals_zero_on_the_surface_and_signed():
    rng = np.random.default_rng(1)
    p = cap_points(rng, 100)
    assert np.max(np.abs(sphere_residuals_m(p, CENTER, RADIUS))) < 1e-12
    outside = CENTER + np.array([0.0, 0.0, RADIUS + 0.01])
    inside = CENTER + np.array([0.0, RADIUS - 0.02, 0.0])
    assert sphere_residuals_m(np.array([outside, inside]), CENTER, RADIUS) == pytest.approx([0.01, -0.02])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_residual_jacobians_match_central_differences(seed):
    rng = np.random.default_rng(seed)
    p = CENTER + rng.normal(scale=0.5, size=(20, 3))
    c = CENTER + rng.normal(scale=0.05, size=3)
    e, de_dp, de_dc = sphere_residuals_and_jacobians(p, c, RADIUS)
    h = 1e-6
    for k in range(3):
        dk = np.eye(3)[k] * h
        num_p = (sphere_residuals_m(p + dk, c, RADIUS) - sphere_residuals_m(p - dk, c, RADIUS)) / (2 * h)
        num_c = (sphere_residuals_m(p, c + dk, RADIUS) - sphere_residuals_m(p, c - dk, RADIUS)) / (2 * h)
        np.testing.assert_allclose(de_dp[:, k], num_p, atol=1e-8)
        np.testing.assert_allclose(de_dc[:, k], num_c, atol=1e-8)
    np.testing.assert_allclose(e, sphere_residuals_m(p, c, RADIUS))


def test_exact_points_are_fitted_exactly_with_free_and_known_radius():
    rng = np.random.default_rng(3)
    p = cap_points(rng, 200, cap_deg=70.0, axis=(1.0, 2.0, -0.5))
    c, r = algebraic_sphere(p)
    np.testing.assert_allclose(c, CENTER, atol=1e-9)
    assert r == pytest.approx(RADIUS, abs=1e-9)
    free = fit_sphere(p)
    known = fit_sphere(p, radius_m=RADIUS)
    np.testing.assert_allclose(free.center_m, CENTER, atol=1e-9)
    np.testing.assert_allclose(known.center_m, CENTER, atol=1e-9)
    assert free.radius_m == pytest.approx(RADIUS, abs=1e-9) and not free.radius_known
    assert known.radius_known and known.covariance.shape == (3, 3) and free.covariance.shape == (4, 4)
    assert free.rms_m < 1e-9 and free.n_points == 200


def test_fit_converges_from_a_poor_algebraic_start_far_from_the_origin():
    """Kasa's fit is biased on a noisy small cap; the geometric refit must still reach the truth."""
    rng = np.random.default_rng(4)
    centre = np.array([5000.0, -3000.0, 120.0])  # survey coordinates: centring keeps the algebra well scaled
    p = cap_points(rng, 5000, cap_deg=40.0, center=centre, sigma=0.002)
    fit = fit_sphere(p, radius_m=RADIUS)
    # tolerance: 5 reported sigmas per axis
    assert np.all(np.abs(fit.center_m - centre) < 5 * fit.center_sigma_m)


@pytest.mark.parametrize("cap_deg, known", [(180.0, False), (75.0, False), (45.0, True)])
def test_monte_carlo_centre_scatter_agrees_with_covariance(cap_deg, known):
    """NEES of the centre over K runs: sum ~ chi2(3K) when the covariance is right.

    Tolerance: the 0.1 % and 99.9 % quantiles of chi2(3K) (a correct covariance fails 1 run in 500);
    the covariance here is estimated from the residual scatter (no sigma given), which adds only an
    O(1/N) spread for N = 400 points.
    """
    rng = np.random.default_rng(10 + int(cap_deg))
    sigma, runs = 0.003, 300
    nees = []
    for _ in range(runs):
        p = cap_points(rng, 400, cap_deg=cap_deg, sigma=sigma, axis=(0.3, -1.0, 0.2))
        fit = fit_sphere(p, radius_m=RADIUS if known else None)
        d = fit.center_m - CENTER
        nees.append(d @ np.linalg.solve(fit.covariance[:3, :3], d))
    total = float(np.sum(nees))
    lo, hi = stats.chi2.ppf([0.001, 0.999], 3 * runs)
    assert lo < total < hi, (total / runs, lo / runs, hi / runs)


def test_monte_carlo_radius_scatter_agrees_with_sigma_given():
    """With sigma_m given the covariance is not rescaled; radius NEES ~ chi2(K), bounds 0.1 %/99.9 %."""
    rng = np.random.default_rng(7)
    sigma, runs = 0.002, 300
    z2 = []
    for _ in range(runs):
        fit = fit_sphere(cap_points(rng, 300, cap_deg=90.0, sigma=sigma), sigma_m=sigma)
        z2.append((fit.radius_m - RADIUS) ** 2 / fit.covariance[3, 3])
    lo, hi = stats.chi2.ppf([0.001, 0.999], runs)
    assert lo < np.sum(z2) < hi


def test_coverage_of_full_sphere_hemisphere_and_small_cap():
    rng = np.random.default_rng(5)
    full = sphere_coverage(cap_points(rng, 20000, 180.0), CENTER)
    hemi = sphere_coverage(cap_points(rng, 20000, 90.0, axis=(1, 0, 0)), CENTER)
    cap = sphere_coverage(cap_points(rng, 20000, 30.0, axis=(0, 1, 0)), CENTER)
    # uniform sampling: rho has sampling sd ~ 1/sqrt(3N) ~ 0.004; the caps' angles are exact up to that
    assert full.cap_half_angle_deg > 160 and full.solid_angle_fraction == 1.0
    assert hemi.cap_half_angle_deg == pytest.approx(90.0, abs=1.0)
    assert hemi.solid_angle_fraction == pytest.approx(0.5)  # 2 of 4 equal-area bands
    np.testing.assert_allclose(hemi.mean_direction, [1, 0, 0], atol=0.02)
    assert cap.cap_half_angle_deg == pytest.approx(30.0, abs=1.0)
    assert cap.one_sided() and not hemi.one_sided() and not full.one_sided()


def test_one_sided_sphere_loses_its_size_but_keeps_its_centre_with_known_radius():
    """A narrow cap: the radius sigma grows (radius and centre along the axis become inseparable); with the
    radius known the centre stays well determined.  Ratios from the information matrix of a cap."""
    rng = np.random.default_rng(6)
    sigma = 0.002
    wide = fit_sphere(cap_points(rng, 2000, 90.0, sigma=sigma), sigma_m=sigma)
    narrow = fit_sphere(cap_points(rng, 2000, 20.0, sigma=sigma), sigma_m=sigma)
    narrow_known = fit_sphere(cap_points(rng, 2000, 20.0, sigma=sigma), radius_m=RADIUS, sigma_m=sigma)
    assert narrow.coverage.one_sided() and not wide.coverage.one_sided()
    assert narrow.radius_sigma_m > 10 * wide.radius_sigma_m
    assert narrow_known.center_sigma_m[2] < narrow.center_sigma_m[2] / 10


def test_ransac_finds_sphere_among_plane_and_clutter():
    rng = np.random.default_rng(8)
    sphere = cap_points(rng, 1500, cap_deg=80.0, axis=(0, -1, 0.3), sigma=0.002)
    floor = np.column_stack([rng.uniform(0, 3, 2000), rng.uniform(-2, 1, 2000), np.full(2000, 2.2)])
    floor[:, 2] += 0.002 * rng.standard_normal(2000)
    clutter = rng.uniform([0, -2, 2], [3, 1, 4], size=(1500, 3))
    pts = np.vstack([sphere, floor, clutter])
    truth = np.r_[np.ones(1500, bool), np.zeros(3500, bool)]
    for radius in (None, RADIUS):
        fit, inliers = ransac_sphere(pts, radius_m=radius, threshold_m=0.006, rng=1,
                                     radius_bounds_m=(0.1, 1.0))
        # 3-sigma gate on N(0, 0.002): 99.7 % of the sphere points; a few clutter points fall in the shell
        assert np.count_nonzero(inliers & truth) > 0.99 * 1500
        assert np.count_nonzero(inliers & ~truth) < 0.02 * 3500
        assert np.all(np.abs(fit.center_m - CENTER) < 5 * fit.center_sigma_m)
        if radius is None:
            assert abs(fit.radius_m - RADIUS) < 5 * fit.radius_sigma_m


def test_ransac_is_reproducible_with_a_seed():
    rng = np.random.default_rng(9)
    pts = np.vstack([cap_points(rng, 300, sigma=0.001), rng.uniform(0, 3, size=(300, 3))])
    a = ransac_sphere(pts, threshold_m=0.004, rng=42)[1]
    b = ransac_sphere(pts, threshold_m=0.004, rng=42)[1]
    assert np.array_equal(a, b)


def test_no_sphere_in_clutter_or_in_a_plane():
    rng = np.random.default_rng(11)
    with pytest.raises(SphereNotFoundError, match="no sphere"):
        ransac_sphere(rng.uniform(0, 5, size=(3000, 3)), threshold_m=0.002, min_inliers=200, rng=0,
                      radius_bounds_m=(0.1, 1.0))
    plane = np.column_stack([rng.uniform(0, 2, 2000), rng.uniform(0, 2, 2000), 0.001 * rng.standard_normal(2000)])
    with pytest.raises(SphereNotFoundError):
        ransac_sphere(plane, threshold_m=0.003, rng=0, radius_bounds_m=(0.1, 1.0))


def test_bad_input_is_refused_clearly():
    with pytest.raises(SphereNotFoundError, match="at least"):
        fit_sphere(np.zeros((3, 3)))
    pts = cap_points(np.random.default_rng(0), 100)
    pts[5, 1] = np.nan
    with pytest.raises(SphereNotFoundError, match="not finite"):
        fit_sphere(pts)
    with pytest.raises(SphereNotFoundError, match="plane|line|degenerate"):
        fit_sphere(np.column_stack([np.arange(50.0), np.arange(50.0) * 2, np.zeros(50)]))
    with pytest.raises(ValueError, match="shape"):
        fit_sphere(np.zeros((10, 2)))


def test_sphere_not_found_is_a_user_error():
    from selfcal.core.errors import USER_ERRORS
    assert issubclass(SphereNotFoundError, USER_ERRORS)


def test_monte_carlo_ransac_centres_agree_with_covariance_despite_clutter():
    """RANSAC + refit on a cap among clutter: centre NEES summed over K runs within the 0.1 %/99.9 %
    quantiles of chi2(3K).  Clutter inside the 3-sigma gate is ~0.2 % of the inliers, too few to bias."""
    rng = np.random.default_rng(21)
    sigma, runs = 0.002, 150
    total = 0.0
    for _ in range(runs):
        pts = np.vstack([cap_points(rng, 300, cap_deg=80.0, sigma=sigma, axis=(0, -1, 0.3)),
                         CENTER + rng.uniform(-1, 1, size=(300, 3))])
        fit, _ = ransac_sphere(pts, threshold_m=3 * sigma, rng=rng, radius_bounds_m=(0.1, 1.0))
        d = fit.center_m - CENTER
        total += d @ np.linalg.solve(fit.covariance[:3, :3], d)
    lo, hi = stats.chi2.ppf([0.001, 0.999], 3 * runs)
    assert lo < total < hi, (total / runs, lo / runs, hi / runs)
