"""Sphere centres against their reported covariance over seeded simulated scans (Monte Carlo).

Each run draws new INS error terms (from the prior the estimator uses), new pixel noise and new sphere
positions.  NEES of a centre is chi2(3) if the covariance is right; the sum over n centres is chi2(3n).  The
test uses the two-sided 99.9 % bounds of chi2(3n) / n, so a consistent estimator fails it once in 1000.
"""
import numpy as np
import pytest
from scipy import stats

from scan_helpers import scan_data
from selfcal.graphs.scan import solve_batch
from selfcal.pipelines.scan import scan_problem
from selfcal.sim.scan import ScanScenario, simulate_scan


def centre_nees(tmp_path, runs, first_seed=100):
    nees = []
    for seed in range(first_seed, first_seed + runs):
        sim = simulate_scan(ScanScenario(length_m=5.0, n_spheres=3, pixel_step=8), seed=seed)
        est = solve_batch(scan_problem(scan_data(sim)))
        assert len(est.centers) == len(sim.sphere_centers)
        for c, C, truth in zip(est.centers, est.centers_cov, sim.sphere_centers):
            e = c - truth
            nees.append(float(e @ np.linalg.solve(C, e)))
    return np.array(nees)


def assert_consistent(nees):
    n = len(nees)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], 3 * n) / n
    assert lo < nees.mean() < hi, (nees.mean(), lo, hi)


def test_sphere_centres_consistent_with_reported_covariance(tmp_path):
    assert_consistent(centre_nees(tmp_path, runs=5))


@pytest.mark.slow
def test_sphere_centres_consistent_long(tmp_path):
    assert_consistent(centre_nees(tmp_path, runs=30, first_seed=200))
