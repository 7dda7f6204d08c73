"""QC of a scan that carries its predicted accuracy (PLY property sigma_m): the points whose bound exceeds the
point tolerance are counted, and a scan that cannot be vouched for says so before any measured figure counts."""
import json

import numpy as np
import pytest
import yaml
from scipy import stats

from selfcal.io.pointcloud import write_point_cloud
from selfcal.pipelines.qc.checks import VOUCH_CHECK, run_qc
from selfcal.pipelines.qc.spec import QCSpec, QCSpecError
from test_qc import ART, SIGMA, loaded, spec_dict


@pytest.fixture(scope="module")
def scan():
    pts, _ = ART.scan(60_000, sigma_m=SIGMA, seed=7)
    # a sigma map growing along x (as drift grows along a track): 0.1 mm at one end, 1.1 mm at the other
    x = (pts[:, 0] - pts[:, 0].min()) / np.ptp(pts[:, 0])
    return pts, 1e-4 + 1e-3 * x


def test_fraction_unvouched_counts_the_points_whose_bound_exceeds_the_tolerance(scan):
    pts, sigma = scan
    spec = QCSpec.from_dict({**spec_dict(sphere_spacing_m=1e-4, flatness_m=0.002, point_error_m=1e-3),
                             "prediction": {"confidence": 0.99, "max_fraction_unvouched": 0.05}})
    result = run_qc(loaded(pts), spec, point_sigma_m=sigma)
    check = next(c for c in result.checks if c.name == VOUCH_CHECK)
    z = stats.norm.ppf(0.995)  # 2.576
    # sigma is uniform in x over [0.1, 1.1] mm only where the points are uniform in x: count them directly
    assert check.value == pytest.approx(np.mean(z * sigma > 1e-3))
    assert check.value > 0.5 and check.passed is False
    assert result.verdict == "cannot be vouched for"  # although every measured figure passes
    assert all(c.passed for c in result.checks if c.name != VOUCH_CHECK and c.tolerance is not None)
    assert result.to_json()["prediction"]["fraction_unvouched"] == check.value


def test_a_scan_within_its_predicted_accuracy_is_judged_by_its_figures(scan):
    pts, sigma = scan
    spec = QCSpec.from_dict(spec_dict(sphere_spacing_m=1e-4, flatness_m=0.002, point_error_m=2 * 1.96 * sigma.max()))
    result = run_qc(loaded(pts), spec, point_sigma_m=sigma)
    assert next(c for c in result.checks if c.name == VOUCH_CHECK).value == 0.0
    assert result.verdict == "pass"


def test_a_point_tolerance_without_a_sigma_map_is_incomplete(scan):
    pts, _ = scan
    result = run_qc(loaded(pts), QCSpec.from_dict(spec_dict(sphere_spacing_m=1e-4, point_error_m=1e-3)))
    assert next(c for c in result.checks if c.name == VOUCH_CHECK).status == "not checked"
    assert result.verdict == "incomplete"


def test_bad_prediction_spec_is_refused():
    with pytest.raises(QCSpecError, match="confidence"):
        QCSpec.from_dict({"prediction": {"confidence": 1.5}})


def test_cli_reads_the_sigma_property_and_exits_5(tmp_path, scan):
    from selfcal.cli.main import main
    pts, sigma = scan
    write_point_cloud(tmp_path / "scan.ply", pts, attributes={"sigma_m": sigma})
    (tmp_path / "qc.yaml").write_text(yaml.safe_dump(spec_dict(sphere_spacing_m=1e-4, point_error_m=1e-3)))
    out = tmp_path / "out"
    code = main(["qc", str(tmp_path / "scan.ply"), "--spec", str(tmp_path / "qc.yaml"), "--json", str(out / "qc.json"),
                 "--markdown", str(out / "qc.md"), "--report", str(out / "qc.html")])
    assert code == 5
    js = json.loads((out / "qc.json").read_text())
    assert js["verdict"] == "cannot be vouched for"
    assert js["prediction"]["fraction_unvouched"] == pytest.approx(np.mean(1.959964 * sigma > 1e-3), abs=1e-4)
    assert (out / "qc.sigma.png").read_bytes()[:4] == b"\x89PNG" and "qc.sigma.png" in (out / "qc.md").read_text()
    assert "Predicted accuracy" in (out / "qc.html").read_text()
