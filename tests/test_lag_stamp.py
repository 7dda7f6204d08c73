"""core.solve.lag_stamp_s: variables leave a fixed-lag window in blocks, never before the lag has passed."""
import gtsam
import numpy as np

from selfcal.core.solve import lag_stamp_s


def test_stamp_rounds_up_to_the_grid():
    assert lag_stamp_s(2.3, 1.0) == 3.0
    assert lag_stamp_s(3.0, 1.0) == 3.0  # on the grid: kept (a float step of 0.1 s lands within 1e-9 of it)
    assert lag_stamp_s(0.1 * 30, 0.1) == 3.0
    assert lag_stamp_s(2.3, 0.0) == 2.3  # no grid


def test_window_keeps_at_least_the_lag():
    """A chain of keyframes every 0.1 s through gtsam's IncrementalFixedLagSmoother with grid stamps: after each
    update, every keyframe younger than the lag is still in the window and none older than lag + step is."""
    lag_s, step_s, dt = 2.0, 0.5, 0.1
    smoother = gtsam.IncrementalFixedLagSmoother(lag_s, gtsam.ISAM2Params())
    noise = gtsam.noiseModel.Isotropic.Sigma(1, 0.1)
    for k in range(60):
        graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), gtsam.FixedLagSmootherKeyTimestampMap()
        if k == 0:
            graph.add(gtsam.PriorFactorVector(k, np.zeros(1), noise))
        else:
            graph.add(gtsam.BetweenFactorVector(k - 1, k, np.ones(1), noise))
        values.insert(k, np.full(1, float(k)))
        stamps.insert((k, lag_stamp_s(k * dt, step_s)))
        smoother.update(graph, values, stamps)
        kept = set(smoother.calculateEstimate().keys())
        assert all(j in kept for j in range(k + 1) if (k - j) * dt <= lag_s + 1e-9)
        assert not any(j in kept for j in range(k + 1) if (k - j) * dt > lag_s + step_s + 1e-9)
