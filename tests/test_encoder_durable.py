"""Durable self-calibration of the encoder (iSAM2 from the last calibration as a prior): tracking a simulated
temperature drift within the reported sigmas, angles against the static calibration under drift, the null case
without drift, bounded graph size and throughput at n = 1024 diodes, the command line.

Scale: calibration at m = 63 cells, n = 128 diodes, N = 40 positions (as ``test_encoder_calibration.py``); then
a run of ``RUN`` ordinary measurements at random positions, one frame every 10 s, while the housing warms by
20 K (a ramp from the calibration's temperature): ``dp/p`` 1e-5/K (2e-4 over the run, ~40x the calibration's
sigma of p), dark level +0.1 counts/K, aperture +2e-4/K, light -0.3 %/K.

Statistical tolerances (stated once, used below)
------------------------------------------------
* Tracking: for a consistent estimator ``z_J = (x_hat_J - x_J) / sigma_J`` is N(0, 1) at every step, so
  ``P(|z| > 3) = 0.27 %``; the issue asks for >= 99 % of steps within 3 sigma.  The steps are correlated: the
  random-walk filter's error is an AR(1) with coefficient ``rho = sigma^2 / (sigma^2 + Q)`` (``Q`` the process
  variance per step: ``1 - K = P / P_prior``), integrated autocorrelation time ``tau = (1 + rho) / (1 - rho)``,
  so ``mean(z^2)`` over N steps is ~ chi-square with ``N / tau`` dof divided by ``N / tau``; its 99.9 % upper
  quantile bounds it (an overconfident sigma fails).  The process noise is deliberately larger than what a
  smooth ramp needs (lag below half a sigma, see ``DriftModel``), so ``mean(z^2) < 1`` is expected and only the
  upper side is tested; that the sigma is informative is checked separately (final sigma of p below 1/5 of
  the drift).
* Angles: the RMS of ``M`` errors has a relative standard error ``1 / sqrt(2 M)``; the durable angles must beat
  the static calibration's by more than 3 standard errors of the ratio of two such RMS values,
  ``1 + 3 sqrt(2) / sqrt(2 M)``, on the frames where the drift of p exceeds 3 calibration sigmas.
"""
import math
import time

import numpy as np
import pytest
import yaml
from scipy.stats import chi2

from selfcal.cli.main import main
from selfcal.graphs.encoder import calibration as ge
from selfcal.graphs.encoder import durable as ged
from selfcal.pipelines import encoder as pe
from selfcal.sim.encoder import EncoderScenario

SMALL = dict(l=6, n_diodes=128, cells_per_image=14.0)
RUN = 300
PERIOD_S = 10.0
DRIFT = dict(temperature_scale_per_degC=1e-5, temperature_range_degC=20.0, temperature_profile="ramp",
             a0_per_degC=0.1, aperture_per_degC=2e-4, intensity_per_degC=-3e-3)


def wrapped(x):
    return np.remainder(np.asarray(x) + math.pi, 2 * math.pi) - math.pi


@pytest.fixture(scope="module")
def calibration():
    sc = EncoderScenario(seed=1, n_positions=40, **SMALL)
    rec, _ = sc.perturbed_measurements(0)
    cal = pe.calibrate_encoder(rec, frames={"array0": sc.perturbed_frames(0)})
    return cal, cal.to_dict("cal.cov.npy"), cal.estimate.calibration_covariance


def durable_run(calibration, drift: dict, seed: int):
    cal, cal_dict, cov = calibration
    positions = np.random.default_rng(seed).uniform(0, 2 * math.pi, RUN)
    run = EncoderScenario(seed=1, positions_rad=positions, frame_period_s=PERIOD_S, **SMALL, **drift)
    frames = run.perturbed_frames(seed)
    prior = pe.durable_prior(cal_dict, cov)
    model = ged.DriftModel()
    estimator = ged.DurableEncoder(prior, model)
    steps = [estimator.add_frame(int(t), f) for t, f in zip(run.t_ns, frames)]
    return run, frames, prior, model, estimator, steps


@pytest.fixture(scope="module")
def drifting(calibration):
    return durable_run(calibration, DRIFT, seed=11)


@pytest.fixture(scope="module")
def still(calibration):
    return durable_run(calibration, {}, seed=12)


def tracked(run, steps):
    """(name, estimate, sigma, truth, process sigma per step as a function of the estimate) per parameter."""
    N = len(steps)
    return [
        ("p", np.array([s.geometry[0] for s in steps]), np.array([s.geometry_sigma[0] for s in steps]),
         np.array([run.geometry_at(0, J)[0] for J in range(N)]),
         lambda m, x: m.p_rel * abs(x) * math.sqrt(PERIOD_S)),
        ("a0", np.array([s.a0 for s in steps]), np.array([s.a0_sigma for s in steps]),
         np.array([run.a0_at(J) for J in range(N)]), lambda m, x: m.a0_counts * math.sqrt(PERIOD_S)),
        ("t_plus", np.array([s.aperture[1] for s in steps]), np.array([s.aperture_sigma[1] for s in steps]),
         np.array([run.aperture_at(0, J)[1] for J in range(N)]),
         lambda m, x: m.aperture_rel * abs(x) * math.sqrt(PERIOD_S)),
    ]


def effective_dof(sigma, q_step):
    rho = sigma**2 / (sigma**2 + q_step**2)
    tau = float(np.mean((1 + rho) / (1 - rho)))
    return max(int(len(sigma) / tau), 1), tau


def assert_tracks_truth(run, model, steps):
    assert not any(s.flag for s in steps)
    for name, est, sigma, truth, q in tracked(run, steps):
        z = (est - truth) / sigma
        within = float(np.mean(np.abs(z) <= 3.0))
        dof, tau = effective_dof(sigma, q(model, est))
        upper = chi2.ppf(0.999, dof) / dof
        assert within >= 0.99, (name, within)
        assert float(np.mean(z**2)) < upper, (name, float(np.mean(z**2)), upper, tau)


def test_tracked_parameters_follow_the_drift_within_their_sigma(drifting):
    run, frames, prior, model, estimator, steps = drifting
    assert_tracks_truth(run, model, steps)
    p_true = np.array([run.geometry_at(0, J)[0] for J in range(RUN)])
    drift_p = abs(p_true[-1] - p_true[0])
    assert steps[-1].geometry_sigma[0] < drift_p / 5    # the tracking is informative, not a wide sigma


def test_durable_angles_beat_the_static_calibration_under_drift(calibration, drifting):
    cal, cal_dict, cov = calibration
    run, frames, prior, model, estimator, steps = drifting
    arr_cal, edge_index = ge.array_calibration(cal.estimate, cal.problem)
    static = [ge.measure_frame(f, run.code, cal.estimate.edges_rad, arr_cal, cov, edge_index) for f in frames]
    p_cal, p_cal_sigma = prior.geometry[0], math.sqrt(prior.covariance[len(prior.edge_vars),
                                                                       len(prior.edge_vars)])
    p_true = np.array([run.geometry_at(0, J)[0] for J in range(RUN)])
    drifted = np.abs(p_true - p_cal) > 3 * p_cal_sigma
    err_static = wrapped(np.array([m.beta_rad for m in static]) - run.beta_rad)
    err_durable = wrapped(np.array([s.beta_rad for s in steps]) - run.beta_rad)
    ok = drifted & np.isfinite(err_static)     # a static frame flagged by its residual is not counted for it
    M = int(ok.sum())
    assert M > RUN // 2
    rms_static = math.sqrt(np.mean(err_static[ok] ** 2))
    rms_durable = math.sqrt(np.mean(err_durable[ok] ** 2))
    ratio = rms_static / rms_durable
    assert ratio > 1 + 3 * math.sqrt(2) / math.sqrt(2 * M), (ratio, rms_static, rms_durable)
    # the durable angles' sigmas: for independent z the count beyond 3 sigma is ~ Poisson(0.0027 RUN = 0.81),
    # P(count > 5) = 2e-4 (errors of frames that share edges are correlated: clusters, hence 5 and not 3)
    z = err_durable / np.array([s.beta_sigma_rad for s in steps])
    assert int(np.sum(np.abs(z) > 3)) <= 5


def test_without_drift_the_tracked_parameters_stay_at_the_calibration(still):
    run, frames, prior, model, estimator, steps = still
    assert_tracks_truth(run, model, steps)
    # |x_hat_J - x_cal| <= 3 (sigma_J + sigma_cal): Var(x_hat - x_cal) <= (sigma_J + sigma_cal)^2 whatever the
    # correlation of the two errors
    E, nf = len(prior.edge_vars), len(prior.geometry_free)
    cal_sd = np.sqrt(np.diag(prior.covariance))
    for est, sig, ref, ref_sd in (
            (np.array([s.geometry[0] for s in steps]), np.array([s.geometry_sigma[0] for s in steps]),
             prior.geometry[0], cal_sd[E]),
            (np.array([s.a0 for s in steps]), np.array([s.a0_sigma for s in steps]), prior.a0, cal_sd[-1]),
            (np.array([s.aperture[1] for s in steps]), np.array([s.aperture_sigma[1] for s in steps]),
             prior.aperture[1], cal_sd[E + nf + 1])):
        assert float(np.mean(np.abs(est - ref) <= 3 * (sig + ref_sd))) >= 0.99


def test_updated_calibration_keeps_the_layout_and_shrinks_edge_sigmas(calibration, still):
    """The posterior is the next calibration: same layout, symmetric positive definite, edges seen by the run
    no less certain than before (more data never increases a Gaussian posterior's variance)."""
    run, frames, prior, model, estimator, steps = still
    mean, post = estimator.posterior()
    assert post.shape == prior.covariance.shape
    np.testing.assert_allclose(post, post.T, rtol=0, atol=1e-12 * np.max(np.abs(post)))
    assert np.all(np.linalg.eigvalsh(post / np.sqrt(np.outer(np.diag(post), np.diag(post)))) > 0)
    E = len(prior.edge_vars)
    ratio = np.sqrt(np.diag(post)[:E] / np.diag(prior.covariance)[:E])
    assert np.all(ratio <= 1 + 1e-6)
    assert np.median(ratio) < 0.9    # 300 frames add to 40: every edge is seen ~8x more often


def test_graph_stays_bounded_and_throughput_at_1024_diodes():
    """n = 1024 diodes, m = 1023 cells (511 edge variables in the prior, ~50 per frame): the iSAM2 graph holds
    the same number of factors after every frame (bounded memory), and frames per second are reported."""
    N = 8
    positions = np.random.default_rng(0).uniform(0, 2 * math.pi, N)
    sc = EncoderScenario(seed=2, l=10, n_diodes=1024, cells_per_image=51.0, positions_rad=positions)
    E = sc.code.n_edges
    rng = np.random.default_rng(1)
    # a prior as a calibration at the patent's scale reports it (edges 0.5 urad, p 1e-6 relative, ...)
    sd = np.concatenate([np.full(E - 1, 5e-7), [1e-6 * sc.geometry[0][0], 1e-5, 1e-5, 1e-5, 0.03]])
    mean_edges = sc.edges_rad + np.r_[0.0, sd[:E - 1] * rng.normal(size=E - 1)]
    prior = ged.DurablePrior(sc.code, mean_edges, list(range(1, E)), sc.geometry[0], (0, 1), sc.aperture[0],
                             sc.a0, sc.noise_sigma, np.diag(sd**2), 2, sc.adc_max)
    frames = sc.perturbed_frames(0)
    estimator = ged.DurableEncoder(prior)
    sizes, seconds = [], []
    for t, f in zip(sc.t_ns, frames):
        start = time.perf_counter()
        step = estimator.add_frame(int(t), f)
        seconds.append(time.perf_counter() - start)
        sizes.append(estimator.isam.getFactorsUnsafe().nrFactors())
        assert step.flag == ""
    assert len(set(sizes[1:])) == 1, sizes
    fps = (N - 1) / sum(seconds[1:])
    print(f"durable encoder, n = 1024, 511 edges: {fps:.1f} frames/s (shared machine), factors {sizes[-1]}")
    assert fps > 0.5   # budget: 2 s per frame on this shared 2-core machine (measured ~6/s; see docs/encoder.md)


def test_cli_track_drift_writes_columns_and_an_updated_calibration(tmp_path):
    rec, run = tmp_path / "rec", tmp_path / "run"
    common = ["--diodes", "128", "--code-bits", "6", "--cells-per-image", "14", "--seed", "4"]
    assert main(["simulate", "encoder", "--out", str(rec), "--positions", "40", *common]) == 0
    assert main(["simulate", "encoder", "--out", str(run), "--positions", "30", "--temperature-scale", "1e-5",
                 "--temperature-range", "10", "--temperature-profile", "ramp", "--a0-per-degc", "0.1",
                 "--aperture-per-degc", "2e-4", "--light-per-degc=-3e-3", "--frame-period", "10",
                 *common]) == 0
    cal = tmp_path / "cal.yaml"
    assert main(["calibrate", "encoder", str(rec), "--out", str(cal)]) == 0
    out_cal = tmp_path / "cal2.yaml"
    assert main(["measure", "encoder", str(run), "--calibration", str(cal), "--out", str(tmp_path / "a.csv"),
                 "--track-drift", "--out-calibration", str(out_cal)]) == 0
    header = (tmp_path / "a.csv").read_text().splitlines()[0].split(",")
    for col in ("p [1]", "p_sigma [1]", "q [1]", "t_plus [1]", "a0 [counts]", "a0_sigma [counts]"):
        assert col in header
    rows = np.genfromtxt(tmp_path / "a.csv", delimiter=",", skip_header=1)
    assert rows.shape == (30, len(header)) and np.all(rows[:, 3] == 1)
    updated = yaml.safe_load(out_cal.read_text())
    assert updated["durable"]["frames_used"] == 30
    assert (tmp_path / updated["covariance_file"]).is_file()
    # the updated calibration is a calibration: measuring with it works, statically and durably
    assert main(["measure", "encoder", str(run), "--calibration", str(out_cal), "--out",
                 str(tmp_path / "b.csv")]) == 0
    assert main(["measure", "encoder", str(run), "--calibration", str(cal), "--out-calibration",
                 str(tmp_path / "x.yaml")]) == 1


def test_simulated_drift_follows_the_stated_coefficients():
    sc = EncoderScenario(seed=3, n_positions=5, **SMALL, **DRIFT)
    dT = sc.temperature_degC - 25.0
    assert dT[0] == pytest.approx(0.0, abs=1e-12) and dT[-1] == pytest.approx(20.0, abs=1e-9)
    assert sc.a0_at(4) == pytest.approx(30.0 + 0.1 * dT[4])
    np.testing.assert_allclose(sc.aperture_at(0, 4), sc.aperture[0] * (1 + 2e-4 * dT[4]))
    truth = sc.truth()
    assert len(truth["drift"]["p"]) == 5
    # without drift coefficients the recording is the one of the original simulator
    base = EncoderScenario(seed=3, n_positions=5, **SMALL)
    assert np.array_equal(base.exact_frames(), EncoderScenario(seed=3, n_positions=5, **SMALL,
                                                               a0_per_degC=0.0).exact_frames())
