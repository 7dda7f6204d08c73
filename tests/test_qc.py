"""Scan quality control (VDI/VDE 2634-2 figures) on a simulated plate-with-spheres artefact: known errors are
found with the right size, bad input gets a clear message and the checkable parts are still checked."""
import json

import numpy as np
import open3d as o3d
import pytest

from selfcal.io.pointcloud import LoadedCloud, cloud_from_points, write_point_cloud, write_triangle_mesh
from selfcal.pipelines.qc.checks import run_qc
from selfcal.pipelines.qc.figures import signed_distances_to_mesh, trimmed_range
from selfcal.pipelines.qc.report import deviation_png, render_html, render_markdown
from selfcal.pipelines.qc.spec import QCSpec, QCSpecError
from selfcal.sim.qc import PlateWithSpheres

SIGMA = 0.0002  # point noise of the simulated scans, m
ART = PlateWithSpheres()


def spec_dict(**tolerances):
    return {"spheres": {"nominal_radius_m": ART.radius_m, "count": 3, "ransac_threshold_m": 5 * SIGMA,
                        "targets": [{"name": n, "centre_m": c.tolist()} for n, c in zip(ART.names, ART.centres_m)],
                        "match_radius_m": 0.02},
            "planes": {"threshold_m": 5 * SIGMA, "min_points": 500},
            "detection": {"voxel_m": 0.004, "normal_radius_m": 0.012, "dbscan_eps_m": 0.012},
            "tolerances": tolerances}


def mesh():
    v, t = ART.mesh_arrays()
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))


def loaded(points, n_nonfinite=0):
    return LoadedCloud(cloud_from_points(points), "sim.ply", len(points) + n_nonfinite, n_nonfinite)


def by_name(result):
    return {c.name: c for c in result.checks}


@pytest.fixture(scope="module")
def reference():
    return mesh()


@pytest.fixture(scope="module")
def clean_result(reference):
    pts, _ = ART.scan(120_000, sigma_m=SIGMA, seed=1)
    spec = QCSpec.from_dict(spec_dict(sphere_spacing_m=1e-4, probing_form_m=6 * 2 * SIGMA, probing_size_m=1e-4,
                                      flatness_m=6 * 2 * SIGMA, deviation_rms_m=1.5 * SIGMA))
    return run_qc(loaded(pts), spec, reference, "artefact")


def test_clean_scan_passes_with_figures_at_the_noise_level(clean_result):
    r = clean_result
    assert r.verdict == "pass", [c for c in r.checks if c.passed is not True]
    assert [s.name for s in r.spheres] == ["A", "B", "C"]
    for s in r.spheres:
        # centre and radius within 5 reported sigmas of the truth
        truth = ART.centres_m[ART.names.index(s.name)]
        assert np.all(np.abs(s.centre_fit.center_m - truth) < 5 * s.centre_fit.center_sigma_m)
        assert abs(s.fit.radius_m - ART.radius_m) < 5 * s.fit.radius_sigma_m
        # PF of ~5000 Gaussian residuals: the range of N(0, sigma) samples is ~2 x 3.7 sigma (0.3 % trimmed)
        assert 5 * SIGMA < s.form_error_m < 9 * SIGMA
    # deviation RMS is the point noise (chord error of the tessellated spheres < 2e-6 m is negligible)
    assert r.deviation.rms_m == pytest.approx(SIGMA, rel=0.05)
    assert abs(r.deviation.mean_m) < 5 * SIGMA / np.sqrt(r.deviation.n_evaluated)
    assert r.planes[0].rms_m == pytest.approx(SIGMA, rel=0.05)
    np.testing.assert_allclose(np.abs(r.planes[0].normal), [0, 0, 1], atol=1e-4)


def test_scale_error_shows_as_sphere_spacing_error_of_s_times_L(reference):
    scale = 4e-4
    pts, _ = ART.scan(120_000, sigma_m=SIGMA, seed=2, scale_error=scale)
    r = run_qc(loaded(pts), QCSpec.from_dict(spec_dict(sphere_spacing_m=1e-4)), reference)
    checks = by_name(r)
    for a, b, length in ART.distances():
        c = checks[f"sphere-spacing error SD {a}-{b}"]
        sigma = float(c.note.split("1-sigma ")[1].split(" m")[0])
        # SD = s L exactly for a pure scale; tolerance 5 sigma of the two centres' covariance
        assert c.value == pytest.approx(scale * length, abs=5 * sigma)
        assert c.passed is False
    assert r.verdict == "fail"


def test_bump_in_the_plate_fails_flatness_and_shows_in_the_deviation(reference):
    bump = 0.002
    pts, _ = ART.scan(120_000, sigma_m=SIGMA, seed=3, bump_m=bump)
    spec = spec_dict(flatness_m=0.001, deviation_p95_m=0.001)
    spec["planes"]["threshold_m"] = 0.003  # the plane must take the bump in to measure it
    r = run_qc(loaded(pts), QCSpec.from_dict(spec), reference)
    flat = by_name(r)["flatness F P1"]
    # the best-fit plane splits the bump: range between bump_m / 2 and bump_m + 6 sigma
    assert bump / 2 < flat.value < bump + 6 * SIGMA and flat.passed is False
    above = r.deviation.distances_m > 3 * SIGMA
    assert above.mean() > 0.05 and (r.deviation.distances_m < -3 * SIGMA).mean() < 0.01  # bump is outside (+)


def test_signed_distance_sign_and_size_on_the_artefact(reference):
    c = ART.centres_m[0]
    pts = np.array([c + [0, 0, ART.radius_m + 0.003], c + [ART.radius_m - 0.002, 0, 0], [0.5, 0.3, -0.004],
                    [0.5, 0.3, 0.001]])
    d = signed_distances_to_mesh(pts, reference)
    # tessellation error of the 90 x 180 UV sphere: R (1 - cos(pi / 90)) = 3e-5 m
    np.testing.assert_allclose(d, [0.003, -0.002, -0.004, 0.001], atol=3.1e-5)


def test_no_sphere_still_checks_flatness_and_deviation(reference):
    pts, labels = ART.scan(60_000, sigma_m=SIGMA, seed=4)
    plate = pts[labels == -1]
    r = run_qc(loaded(plate), QCSpec.from_dict(spec_dict(probing_form_m=0.001, flatness_m=0.002,
                                                         deviation_rms_m=0.001)), reference)
    checks = by_name(r)
    assert checks["probing error of form PF"].passed is None
    assert "no sphere found" in checks["probing error of form PF"].note
    assert checks["flatness F P1"].passed is True and checks["deviation RMS"].passed is True
    assert all(checks[f"sphere-spacing error SD {a}-{b}"].passed is None for a, b, _ in ART.distances())
    assert r.verdict == "incomplete"


def test_sphere_seen_from_one_side_gets_no_size_check_but_a_centre_from_the_nominal_radius(reference):
    pts, _ = ART.scan(120_000, sigma_m=SIGMA, seed=5, cap_deg=35.0, sphere_point_share=0.2)
    r = run_qc(loaded(pts), QCSpec.from_dict(spec_dict(probing_size_m=1e-4, sphere_spacing_m=1e-4)), reference)
    checks = by_name(r)
    assert len(r.spheres) == 3
    for s in r.spheres:
        assert s.one_sided and s.fit.coverage.cap_half_angle_deg == pytest.approx(35, abs=2)
        assert checks[f"probing error of size PS {s.name}"].passed is None
        assert "one side" in checks[f"probing error of size PS {s.name}"].note
        truth = ART.centres_m[ART.names.index(s.name)]
        assert s.centre_fit.radius_known
        assert np.all(np.abs(s.centre_fit.center_m - truth) < 5 * s.centre_fit.center_sigma_m)
        # the free fit's radius is much less certain than the known-radius centre (the reason for the flag)
        assert s.fit.radius_sigma_m > 3 * s.centre_fit.center_sigma_m[2]
    assert all(checks[f"sphere-spacing error SD {a}-{b}"].passed is True for a, b, _ in ART.distances())
    assert any("one side" in w for w in r.warnings)


def test_nonfinite_points_are_reported_and_no_tolerance_means_figures_only(reference):
    pts, _ = ART.scan(50_000, sigma_m=SIGMA, seed=6)
    r = run_qc(loaded(pts, n_nonfinite=17), QCSpec.from_dict(spec_dict()), reference)
    assert r.n_nonfinite == 17 and any("17 of" in w and "non-finite" in w for w in r.warnings)
    assert r.verdict == "reported"
    assert {c.status for c in r.checks} == {"no tolerance"}


def test_trimmed_range_leaves_out_the_largest_residuals():
    e = np.r_[np.linspace(-1, 1, 997), [50.0, -40.0, 30.0]]
    assert trimmed_range(e, 0.003) == pytest.approx(2.0)
    assert trimmed_range(e, 0.0) == pytest.approx(90.0)


def test_reports_hold_the_verdict_every_check_and_the_image(clean_result):
    png = deviation_png(clean_result)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    html = render_html(clean_result, png)
    md = render_markdown(clean_result, "dev.png")
    for text in (html, md):
        assert "PASS" in text and "sphere-spacing error SD A-B" in text and "flatness F P1" in text
    assert "data:image/png;base64," in html and "![deviation map](dev.png)" in md
    js = json.loads(json.dumps(clean_result.to_json()))
    assert js["verdict"] == "pass" and len(js["spheres"]) == 3


@pytest.mark.parametrize("bad, message", [
    ({"tolerances": {"flatnes_m": 0.001}}, "unknown key"),
    ({"sphere": {}}, "unknown section"),
    ({"spheres": {"radius_bounds_m": [0.3, 0.2]}}, "radius_bounds_m"),
    ({"spheres": {"targets": [{"name": "A"}]}}, "centre_m"),
    ({"spheres": {"targets": [{"name": "A", "centre_m": [0, 0, 0]}], "distances": [
        {"between": ["A", "Z"], "distance_m": 1}]}}, "not among targets"),
    ({"tolerances": {"flatness_m": -1}}, "must be > 0"),
])
def test_bad_spec_is_refused_with_the_reason(bad, message):
    with pytest.raises(QCSpecError, match=message):
        QCSpec.from_dict(bad)


def test_spec_yaml_reads_exponent_numbers(tmp_path):
    path = tmp_path / "qc.yaml"
    path.write_text("tolerances:\n  flatness_m: 5e-4\nspheres:\n  nominal_radius_m: 0.05\n")
    spec = QCSpec.from_yaml(path)
    assert spec.tolerances.flatness_m == 5e-4 and spec.spheres.bounds() == pytest.approx((0.04, 0.06))


def test_cli_qc_writes_every_report(tmp_path, reference):
    from selfcal.cli.main import main
    import yaml
    pts, _ = ART.scan(60_000, sigma_m=SIGMA, seed=7)
    pts[:5] = np.nan
    write_point_cloud(tmp_path / "scan.ply", pts)
    write_triangle_mesh(tmp_path / "ref.ply", reference)
    (tmp_path / "qc.yaml").write_text(yaml.safe_dump(spec_dict(sphere_spacing_m=1e-4, flatness_m=0.002)))
    out = tmp_path / "out"
    code = main(["qc", str(tmp_path / "scan.ply"), "--reference", str(tmp_path / "ref.ply"), "--spec",
                 str(tmp_path / "qc.yaml"), "--report", str(out / "qc.html"), "--markdown", str(out / "qc.md"),
                 "--json", str(out / "qc.json")])
    assert code == 0
    js = json.loads((out / "qc.json").read_text())
    assert js["verdict"] == "pass" and js["n_nonfinite"] == 5
    assert (out / "qc.png").read_bytes()[:4] == b"\x89PNG" and "qc.png" in (out / "qc.md").read_text()


def test_cli_qc_exit_status_follows_the_verdict(tmp_path, reference):
    """A failed part exits 3 (a CI job stops on it) and still gets its report; an unjudged run exits 0."""
    from selfcal.cli.main import main
    import yaml
    pts, _ = ART.scan(60_000, sigma_m=SIGMA, seed=7)
    write_point_cloud(tmp_path / "scan.ply", pts)
    # 1 nm flatness cannot be met by a scan with 0.2 mm noise
    (tmp_path / "tight.yaml").write_text(yaml.safe_dump(spec_dict(sphere_spacing_m=1e-4, flatness_m=1e-9)))
    out = tmp_path / "fail.json"
    assert main(["qc", str(tmp_path / "scan.ply"), "--spec", str(tmp_path / "tight.yaml"), "--json", str(out)]) == 3
    assert json.loads(out.read_text())["verdict"] == "fail"
    assert main(["qc", str(tmp_path / "scan.ply"), "--json", str(tmp_path / "figures.json")]) == 0
    assert json.loads((tmp_path / "figures.json").read_text())["verdict"] == "reported"


def test_cli_qc_bad_input_is_one_line_exit_1(tmp_path, capsys):
    from selfcal.cli.main import main
    (tmp_path / "empty.ply").write_text("")
    assert main(["qc", str(tmp_path / "empty.ply"), "--json", str(tmp_path / "o.json")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("selfcal: error:") and "empty" in err[-1]
    write_point_cloud(tmp_path / "s.ply", np.random.default_rng(0).random((100, 3)))
    (tmp_path / "bad.yaml").write_text("tolerances: {flatnes_m: 1}\n")
    assert main(["qc", str(tmp_path / "s.ply"), "--spec", str(tmp_path / "bad.yaml"), "--json",
                 str(tmp_path / "o.json")]) == 1
    assert "unknown key" in capsys.readouterr().err
    assert not (tmp_path / "o.json").exists()


def test_deviation_map_labels_of_neighbouring_spheres_point_to_different_corners():
    from selfcal.pipelines.qc.report import LABEL_OFFSETS_PT, label_offsets_pt
    centres = np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.012], [1.0, 1.0]])  # three within 2 cm, one far
    offsets = label_offsets_pt(centres, near=0.05)
    assert len(set(offsets[:3])) == 3  # the three neighbours: three different corners
    assert offsets[3] == LABEL_OFFSETS_PT[0]  # alone: the default corner
