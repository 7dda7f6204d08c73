"""Encoder self-calibration end to end at a small scale (m = 63 cells, n = 128 diodes, N = 40 positions, each
cell in ~9 frames): decoding, the patent baseline, the batch ML graph, measuring new positions, Monte Carlo
against the reported covariance, bad input, the command line.  The patent's scale is in
``benchmarks/encoder_vs_patent.py`` and the ``slow`` test at the end.

Statistical tolerances: with R independent runs, the sum of squared z-scores (or of full-covariance NEES with
d dof each) is chi-square with R (R d) dof; the tests accept the two-sided 99.9 % interval.
"""
import math
import shutil

import numpy as np
import pytest
import yaml
from scipy.stats import chi2

from selfcal.baselines.encoder import patent_calibration, patent_measure
from selfcal.cli.main import main
from selfcal.graphs.encoder import calibration as ge
from selfcal.io.encoder import EncoderRecordingError
from selfcal.io.recording import read_recording
from selfcal.models import encoder as enc
from selfcal.pipelines import encoder as pe
from selfcal.sim.encoder import EncoderScenario, npy_bytes

SMALL = dict(l=6, n_diodes=128, n_positions=40, cells_per_image=14.0)
RUNS = 16


def wrapped(x):
    return np.remainder(np.asarray(x) + math.pi, 2 * math.pi) - math.pi


def chi2_interval(dof, p=1e-3):
    return chi2.ppf(p / 2, dof), chi2.ppf(1 - p / 2, dof)


def calibrate_scenario(sc, seed, frames=None):
    rec, files = sc.perturbed_measurements(seed)
    frames = {"array0": sc.perturbed_frames(seed)} if frames is None else frames
    return pe.calibrate_encoder(rec, frames=frames)


def test_decoding_finds_every_frame_and_start_values_are_near():
    sc = EncoderScenario(seed=1, **SMALL)
    frames = sc.perturbed_frames(0)
    g = np.array([sc.p_nominal, 0, 0, 0, 0, 0])
    decoded = [enc.decode_frame(f, sc.code, g, adc_max=sc.adc_max, noise_sigma=sc.noise_sigma) for f in frames]
    assert all(d.ok for d in decoded)
    err = wrapped([d.beta_rad for d in decoded] - sc.beta_rad)
    # start values within a quarter cell: the window was read correctly (a wrong window is off by whole cells)
    assert np.max(np.abs(err)) < 0.25 * sc.code.cell_rad


def test_monte_carlo_edges_positions_and_new_angles_agree_with_reported_covariance():
    """R runs, each with fresh noise and graduation errors: full-covariance NEES of the edges, z of a new angle."""
    nees_edges, z_new, dof = 0.0, [], 0
    ratio_to_patent = []
    for run in range(RUNS):
        sc = EncoderScenario(seed=100 + run, **SMALL)
        cal = calibrate_scenario(sc, seed=run)
        est = cal.estimate
        idx = [i for i, (name, _) in enumerate(est.covariance_layout) if name == "edge"]
        edges = [e for name, e in est.covariance_layout if name == "edge"]
        err = est.edges_rad[edges] - sc.edges_rad[edges]
        cov = est.calibration_covariance[np.ix_(idx, idx)]
        nees_edges += float(err @ np.linalg.solve(cov, err))
        dof += len(edges)
        # one new position per run (independent across runs)
        beta_new = np.random.default_rng(run).uniform(0, 2 * math.pi)
        new = EncoderScenario(seed=100 + run, positions_rad=[beta_new], **{**SMALL, "n_positions": 1})
        frame = new.perturbed_frames(1000 + run)[0]
        arr_cal, edge_index = ge.array_calibration(est, cal.problem)
        m = ge.measure_frame(frame, sc.code, est.edges_rad, arr_cal, est.calibration_covariance, edge_index)
        assert m.flag == ""
        z_new.append(wrapped(m.beta_rad - beta_new) / m.sigma_rad)
        base = patent_calibration(sc.perturbed_frames(run), sc.code, [sc.p_nominal, 0, 0, 0, 0, 0], sc.adc_max,
                                  sc.noise_sigma)
        b_pat, _ = patent_measure(frame, sc.code, base, sc.adc_max, sc.noise_sigma)
        ratio_to_patent.append((wrapped(b_pat - beta_new), wrapped(m.beta_rad - beta_new)))
    lo, hi = chi2_interval(dof)
    assert lo < nees_edges < hi, (nees_edges, dof)
    lo, hi = chi2_interval(RUNS)
    assert lo < float(np.sum(np.square(z_new))) < hi
    patent_err, graph_err = np.array(ratio_to_patent).T
    assert np.sqrt(np.mean(graph_err**2)) < np.sqrt(np.mean(patent_err**2))


def test_wrong_frame_width_is_a_one_line_error(tmp_path):
    sc = EncoderScenario(seed=2, **SMALL)
    sc.write(tmp_path / "rec", seed=0)
    frames = sc.perturbed_frames(0)[:, :100]
    (tmp_path / "rec" / "array0" / "frames.npy").write_bytes(npy_bytes(frames))
    with pytest.raises(EncoderRecordingError, match="100 diodes wide, sensor.yaml says n_diodes: 128"):
        pe.calibrate_encoder(read_recording(tmp_path / "rec"))
    assert main(["calibrate", "encoder", str(tmp_path / "rec")]) == 1


def test_bad_frames_are_flagged_never_a_wrong_angle():
    sc = EncoderScenario(seed=3, **{**SMALL, "n_positions": 60})
    frames = sc.perturbed_frames(0)
    cal_frames = frames.copy()
    rng = np.random.default_rng(0)
    saturated, dark, painted, shifted = 3, 7, 11, 19
    cal_frames[saturated] = np.minimum(cal_frames[saturated] * 8, sc.adc_max)
    cal_frames[dark] = sc.a0 + sc.noise_sigma * rng.normal(size=sc.n_diodes)
    cal_frames[painted, 40:70] = sc.a0            # dirt over a bar: the window may still decode, the fit must not
    cal_frames[shifted] = np.roll(cal_frames[shifted], 9)   # a frame the model cannot produce
    cal = calibrate_scenario(sc, 0, frames={"array0": cal_frames})
    assert cal.flags["array0/3"] == "saturated" and cal.flags["array0/7"] == "dark"
    est = cal.estimate
    arr_cal, edge_index = ge.array_calibration(est, cal.problem)
    for J in (saturated, dark, painted, shifted, 0, 1):
        m = ge.measure_frame(cal_frames[J], sc.code, est.edges_rad, arr_cal, est.calibration_covariance,
                             edge_index)
        if not m.flag:   # an unflagged angle must be right (within 5 sigma)
            assert abs(wrapped(m.beta_rad - sc.beta_rad[J])) < 5 * m.sigma_rad, J
    for J, flag in ((saturated, "saturated"), (dark, "dark")):
        assert ge.measure_frame(cal_frames[J], sc.code, est.edges_rad, arr_cal).flag == flag
    assert ge.measure_frame(cal_frames[painted], sc.code, est.edges_rad, arr_cal).flag != ""
    assert ge.measure_frame(cal_frames[shifted], sc.code, est.edges_rad, arr_cal).flag != ""
    # too few cells on the array to read a window: undecodable
    narrow = EncoderScenario(seed=3, **{**SMALL, "cells_per_image": 5.0, "n_positions": 3})
    d = enc.decode_frame(narrow.perturbed_frames(0)[0], narrow.code, [narrow.p_nominal, 0, 0, 0, 0, 0])
    assert d.flag == "undecodable"


def test_cli_simulate_calibrate_measure(tmp_path):
    rec, new = tmp_path / "rec", tmp_path / "new"
    assert main(["simulate", "encoder", "--out", str(rec), "--positions", "40", "--diodes", "128", "--code-bits",
                 "6", "--cells-per-image", "14", "--seed", "4"]) == 0
    assert main(["simulate", "encoder", "--out", str(new), "--positions", "12", "--diodes", "128", "--code-bits",
                 "6", "--cells-per-image", "14", "--seed", "4"]) == 0
    # a second noise realisation of other positions of the same disk: regenerate with shifted positions
    sc = EncoderScenario(seed=4, **{**SMALL, "n_positions": 12}, positions_rad=np.linspace(0.1, 6.0, 12))
    shutil.rmtree(new)
    sc.write(new, seed=9)
    cal_path = tmp_path / "out" / "cal.yaml"
    assert main(["calibrate", "encoder", str(rec), "--out", str(cal_path)]) == 0
    cal = yaml.safe_load(cal_path.read_text())
    for key in ("edges_rad", "edges_sigma_rad", "positions", "arrays"):
        assert key in cal
    assert cal["arrays"]["array0"]["geometry_sigma"]["p"] > 0
    assert main(["measure", "encoder", str(new), "--calibration", str(cal_path), "--out",
                 str(tmp_path / "angles.csv")]) == 0
    rows = np.genfromtxt(tmp_path / "angles.csv", delimiter=",", skip_header=1, usecols=(1, 2, 3))
    z = wrapped(rows[:, 0] - sc.beta_rad) / rows[:, 1]
    assert np.all(rows[:, 2] == 1)
    assert np.all(np.abs(z) < 4.0)   # 12 angles, each within 4 sigma (all 12 pass with probability 0.9992)


@pytest.mark.slow
def test_patent_scale_calibration_time_and_accuracy():
    """N = 240, n = 1024, m = 1023: calibration under 20 s (wall) and errors consistent with the sigmas."""
    sc = EncoderScenario(seed=5, l=10, n_diodes=1024, n_positions=240, cells_per_image=51.0)
    cal = calibrate_scenario(sc, 0)
    assert cal.seconds < 20.0
    est = cal.estimate
    ok = np.isfinite(est.edges_sigma_rad) & (est.edges_sigma_rad > 0)
    z = (est.edges_rad - sc.edges_rad)[ok] / est.edges_sigma_rad[ok]
    assert 0.7 < np.sqrt(np.mean(z**2)) < 1.3   # correlated edges: a loose band around 1
