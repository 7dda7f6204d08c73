"""The online smoother takes the tracker's custom factors linearised once (estimator.frozen_jacobian): its poses
must be those of the smoother given the nonlinear factors (a batch run's online pass keeps them)."""
import numpy as np
import pytest

from selfcal.graphs.tracker import GatingOptions, TrackerEstimator, TrackerOptions
from selfcal.pipelines.tracker import noise_from_meta
from selfcal.sim.tracker import TrackerScenario


def _poses(sc, mode: str, keep_graph: bool) -> np.ndarray:
    est = TrackerEstimator(noise_from_meta(sc._meta()), TrackerOptions(mode=mode, gating=GatingOptions(),
                                                                        keep_graph=keep_graph))
    out = []
    for name, t, v in sc.stream(seed=4):
        if name == "imu0":
            out += est.imu(t, [v["w_RS_S_x"], v["w_RS_S_y"], v["w_RS_S_z"]], [v["a_RS_S_x"], v["a_RS_S_y"],
                                                                              v["a_RS_S_z"]])
        elif name == "tracker0":
            vel = [v["vx"], v["vy"], v["vz"]] if "vx" in v else None
            out += est.tracker(t, [v["x"], v["y"], v["z"]], vel)
        elif name == "incl0":
            out += est.incl(t, v["roll"], v["pitch"])
        elif name == "cam0":
            out += est.cam(t, v["u"], v["v"])
    frozen = keep_graph is False
    s = est._smoother
    factors = s.getFactors() if mode == "fixed-lag" else s.getFactorsUnsafe()
    custom = sum(1 for i in range(factors.size()) if factors.exists(i) and type(factors.at(i)).__name__ ==
                 "CustomFactor")
    assert (custom == 0) == frozen  # the switch is what is compared
    return np.array([np.r_[o["position"], o["quaternion"]] for o in out])


@pytest.mark.parametrize("mode", ["fixed-lag", "isam2"])
def test_frozen_custom_factors_give_the_same_online_poses(mode):
    """Frozen at the propagated state, a factor differs from the relinearised one by terms of second order in
    the state's move since (relinearisation threshold 0.01): bearing ~1e-4 / 5 m ~ 2e-5 rad at most, velocity
    ~|w x r| 1e-4; the poses must agree to 1 um and 1e-6 in the quaternion, 500 times below the tracker's
    0.5 mm noise."""
    sc = TrackerScenario(duration_s=10.0, seed=5)
    frozen, nonlinear = _poses(sc, mode, False), _poses(sc, mode, True)
    assert frozen.shape == nonlinear.shape and len(frozen) > 60
    assert np.abs(frozen[:, :3] - nonlinear[:, :3]).max() < 1e-6
    assert np.abs(frozen[:, 3:] - nonlinear[:, 3:]).max() < 1e-6


def test_imu_history_keeps_the_last_capacity_samples_across_batched_writes():
    """The IMU ring fed one sample at a time (written to the ring in batches) against a plain list of
    the same samples: every span read, at any fill, is the list's, with the oldest samples dropped past the
    capacity."""
    from selfcal.graphs.tracker.vibration import ImuHistory
    capacity = 100
    ring, kept = ImuHistory(capacity), []
    rng = np.random.default_rng(1)
    for j in range(700):
        t_ns, a = 5_000_000 * j, rng.normal(size=6)
        ring.append(t_ns, a[:3], a[3:])
        kept = (kept + [(t_ns, a)])[-capacity:]
        if j % 37 == 0 or j in (63, 64, 65, 699):
            t_lo, t_hi = kept[0][0] + 5_000_000 * (j % 5), t_ns + 1
            expected = np.array([x for t, x in kept if t_lo <= t < t_hi])
            np.testing.assert_array_equal(ring.between(t_lo, t_hi), expected)
            if j >= 4:  # the mean of the 4 samples before the latest
                np.testing.assert_array_equal(ring.mean_before(t_ns, 4),
                                              np.mean([x[:3] for _, x in kept[-5:-1]], axis=0))
