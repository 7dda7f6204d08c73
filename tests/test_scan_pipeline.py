"""`smooth_scan` end to end on a simulated tunnel scan: sphere spacing, batch vs iSAM2, patent baseline,
bad input."""
import shutil

import numpy as np
import pytest

from selfcal.graphs import scan as gs
from selfcal.core.solve import DegenerateDataError
from selfcal.io.recording import RecordingError, read_recording
from selfcal.core.sphere import fit_sphere
from selfcal.pipelines.scan import inertial_only_points, read_scan, scan_problem, smooth_scan
from selfcal.sim.scan import ScanScenario, simulate_scan, write_scan_recording


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    sim = simulate_scan(ScanScenario(length_m=10.0, n_spheres=5), seed=3)
    path = write_scan_recording(sim, tmp_path_factory.mktemp("scan") / "rec")
    return sim, read_recording(path), path


def spacing_errors(centers, true_centers):
    i, j = np.triu_indices(len(true_centers), 1)
    return np.linalg.norm(centers[i] - centers[j], axis=1) - np.linalg.norm(true_centers[i] - true_centers[j], axis=1)


def cloud_centers(points_W, guesses, radius):
    """Sphere centres fitted in a cloud (known radius), points within 1.5 R of each guess."""
    out = []
    for c in guesses:
        near = points_W[np.linalg.norm(points_W - c, axis=1) < 1.5 * radius]
        out.append(fit_sphere(near, radius_m=radius).center_m)
    return np.array(out)


def test_smooth_scan_beats_inertial_only_tenfold(recording):
    """Sphere spacing measured in the clouds themselves: corrected at least 10x below inertial-only."""
    sim, rec, _ = recording
    est = smooth_scan(rec)
    assert len(est.centers) == len(sim.sphere_centers)
    # the detection (in the inertial-only cloud) orders spheres as the scan reaches them, as the sim places them
    before = spacing_errors(cloud_centers(inertial_only_points(rec), est.problem.centers0, 0.1), sim.sphere_centers)
    after = spacing_errors(cloud_centers(est.points_W, sim.sphere_centers, 0.1), sim.sphere_centers)
    rms_before, rms_after = np.sqrt(np.mean(before**2)), np.sqrt(np.mean(after**2))
    assert rms_before > 0.005  # the inertial-only scan really is distorted (a test that can fail)
    assert rms_after * 10 < rms_before
    # every error term within 4 sigma of the truth (15 terms: P(any > 4 sigma) ~ 1e-3 if the sigmas are right)
    assert np.all(np.abs(est.theta - sim.error_terms) < 4 * est.theta_sigma)


def test_online_matches_batch(recording):
    """iSAM2 fed sphere by sphere ends where batch LM ends (same graph): within 0.1 sigma."""
    sim, rec, _ = recording
    batch, online = smooth_scan(rec), smooth_scan(rec, online=True)
    assert np.all(np.abs(online.theta - batch.theta) < 0.1 * batch.theta_sigma)
    assert len(online.solution.history) == len(sim.sphere_centers)


def test_missing_ins_is_a_recording_error(recording, tmp_path):
    _, _, path = recording
    copy = tmp_path / "rec"
    shutil.copytree(path, copy)
    shutil.rmtree(copy / "ins0")
    with pytest.raises(RecordingError, match="ins0"):
        smooth_scan(read_recording(copy))


def test_no_sphere_is_a_clear_error(tmp_path):
    sim = simulate_scan(ScanScenario(length_m=3.0, n_spheres=0, pixel_step=16), seed=1)
    path = write_scan_recording(sim, tmp_path / "rec")
    with pytest.raises(DegenerateDataError, match="no sphere"):
        smooth_scan(read_recording(path))


def test_nonfinite_points_are_dropped(recording, tmp_path):
    _, _, path = recording
    copy = tmp_path / "rec"
    shutil.copytree(path, copy)
    first = sorted((copy / "scan0").glob("*.npy"))[0]
    p = np.load(first)
    p[:5] = np.nan
    np.save(first, p)
    data = read_scan(read_recording(copy))
    assert np.isfinite(data.points_V[0]).all() and len(data.points_V[0]) == len(p) - 5


def test_patent_baseline_runs_and_is_not_better(recording):
    """The patent's two-stage procedure on the same set B: a real estimate (moves the terms off zero), and
    the joint graph's sphere spacing is at least as good."""
    from selfcal.baselines.scan import patent_two_stage
    sim, rec, _ = recording
    data = read_scan(rec)
    problem = scan_problem(data)
    clocks = problem.b_clocks()
    row = {m: i for i, m in enumerate(clocks)}
    R, r, Phi, _ = gs.clock_inputs(problem, clocks)
    obs = [(row[o.clock], o.sphere, o.vision_p) for o in problem.observations]
    pat = patent_two_stage(R, r, Phi[:, :, :15], obs, problem.imu_R_vision, problem.imu_t_vision, problem.centers0,
                           problem.radius_m, problem.prior_sigmas, problem.jitter_sigmas)
    graph = gs.solve_batch(problem, covariance=False)

    def spacing_rms(theta):
        Rc, rc = gs.corrected_clock_poses(problem, gs.ScanSolution(theta, None, None, None))
        P = data.world_points(Rc, rc)[0]
        return np.sqrt(np.mean(spacing_errors(cloud_centers(P, sim.sphere_centers, 0.1), sim.sphere_centers) ** 2))

    assert np.abs(pat.theta / problem.prior_sigmas).max() > 0.1
    assert spacing_rms(graph.theta) <= spacing_rms(pat.theta)


def test_cli_simulate_and_smooth_scan(tmp_path, capsys):
    """`selfcal simulate scan --out REC` then `selfcal smooth scan REC --out corrected.ply --estimates e.yaml`."""
    import yaml

    from selfcal.cli.main import main
    from selfcal.io.pointcloud import read_point_cloud
    rec = tmp_path / "rec"
    assert main(["simulate", "scan", "--out", str(rec), "--length", "4", "--spheres", "2", "--seed", "2"]) == 0
    out, est = tmp_path / "corrected.ply", tmp_path / "est.yaml"
    assert main(["smooth", "scan", str(rec), "--out", str(out), "--estimates", str(est)]) == 0
    n = sum(int(float(line.split(",")[1])) for line in (rec / "scan0" / "data.csv").read_text().splitlines()[1:])
    assert read_point_cloud(out).n_read == n
    doc = yaml.safe_load(est.read_text())
    assert len(doc["error_terms"]) == 15 and all(v["sigma"] > 0 for v in doc["error_terms"].values())
    assert main(["smooth", "scan", str(tmp_path / "missing")]) == 1
    assert "error" in capsys.readouterr().err
