"""Monte Carlo (small): the pair graph's rotation error against the Cramér–Rao bound, and honest sigmas.

The full study (>= 100 runs) is benchmarks/imu_pair_monte_carlo.py; this one keeps 40 runs (~5 s).
"""
import numpy as np
from scipy.stats import chi2

from selfcal.pipelines.imu_pair import imu_pair_rotation_study

RUNS = 40


def test_rotation_error_near_bound_and_nees_consistent():
    study = imu_pair_rotation_study(RUNS)
    # Efficiency: the target is RMS error <= 1.15 x the bound.  The RMS over 3*RUNS squared errors has a
    # relative sampling sigma of 1/sqrt(2*3*RUNS) (chi-square), so a 2-sigma allowance is added to 1.15 here.
    allowance = 1.15 * (1 + 2 / np.sqrt(6 * RUNS))
    assert study.rms_graph_rad <= allowance * study.rms_bound_rad, study.summary()
    # No estimator beats the bound by more than sampling noise either (a too-small "bound" would hide bugs).
    assert study.rms_graph_rad >= (1 - 3 / np.sqrt(6 * RUNS)) * study.rms_bound_rad, study.summary()
    # Consistency: sum of NEES over runs ~ chi2(3 * RUNS) when reported covariances are right; 99.9 % interval.
    total = float(np.sum(study.nees))
    assert chi2.ppf(0.0005, 3 * RUNS) < total < chi2.ppf(0.9995, 3 * RUNS), study.summary()
