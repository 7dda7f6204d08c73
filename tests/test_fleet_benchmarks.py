"""The one benchmark command (benchmarks/run_all.py) and the results schema helper (benchmarks/_schema.py):
discovery, a benchmark run in a subprocess and its JSON collected, a failing one reported without stopping the
others, ratios oriented so that > 1 means the library is better, and the comparison with an earlier run."""
import importlib
import json
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCHMARKS))
    try:
        yield importlib.import_module("run_all"), importlib.import_module("_schema")
    finally:
        sys.path.remove(str(BENCHMARKS))


def test_ratio_orientation(bench):
    _, schema = bench
    error = schema.row("roll RMSE", "deg", 0.01, 0.03)  # library error 3x smaller: library better
    assert error["ratio"] == pytest.approx(3.0)
    rate = schema.row("real-time factor", "x", 50.0, 100.0, better="higher")  # library half as fast
    assert rate["ratio"] == pytest.approx(0.5)
    assert schema.row("recall", "fraction", 1.0, better="higher")["ratio"] is None
    assert schema.row("x", "s", float("nan"), 1.0)["library"] is None  # JSON has no NaN


def test_the_adapted_benchmarks_are_discovered(bench):
    run_all, _ = bench
    found, _ = run_all.discover()
    names = {p.name for p in found}
    assert {"imu_pair_vs_patent.py", "audit_recall.py", "ship_vs_patent.py"} <= names
    assert "run_all.py" not in names and "_schema.py" not in names


FAKE = '''
import argparse, sys, time
import _schema
parser = argparse.ArgumentParser()
_schema.add_arguments(parser, "fake")
args = parser.parse_args()
if {fail}:
    sys.exit("fake: broken on purpose")
_schema.write(args.json, "fake", "encoder", args.quick, 0.1,
              [_schema.row("angle RMSE", "arcsec", 0.5, 2.0), _schema.row("time", "s", 2.0, 1.0),
               _schema.row("real-time factor (online)", "x", 40.0, None, better="higher"),
               _schema.row("efficiency RMS/CRB", "x", 1.05)])
'''


def test_run_one_collects_json_and_reports_failures(bench, tmp_path):
    run_all, _ = bench
    (tmp_path / "_schema.py").write_text((BENCHMARKS / "_schema.py").read_text())
    good, bad = tmp_path / "fake.py", tmp_path / "broken.py"
    good.write_text(FAKE.format(fail=False))
    bad.write_text(FAKE.format(fail=True))
    doc = run_all.run_one(good, True, 60, tmp_path / "results")
    assert "error" not in doc, doc
    assert doc["quick"] is True and doc["system"] == "encoder" and doc["peak_memory_mb"] > 0
    assert [run_all.kind(r) for r in doc["rows"]] == ["accuracy", "time", "rtf", "crb"]
    failed = run_all.run_one(bad, True, 60, tmp_path / "results")
    assert "broken on purpose" in failed["error"]
    line = run_all.summary_rows([doc, failed])
    encoder = next(row for row in line if row[1].startswith("fake"))
    assert encoder[2] == "4" and encoder[3] == "0.5" and encoder[4] == "40" and encoder[5] == "1.05"
    assert any(row[2].startswith("FAILED") for row in line)


def test_compare_prints_the_change_per_metric(bench):
    run_all, schema = bench
    old = {"benchmarks": [{"benchmark": "b", "quick": True, "seconds": 10.0, "peak_memory_mb": 100.0,
                           "rows": [schema.row("roll RMSE", "deg", 0.02, 0.04)]}]}
    new = {"benchmarks": [{"benchmark": "b", "quick": True, "seconds": 5.0, "peak_memory_mb": 100.0,
                           "rows": [schema.row("roll RMSE", "deg", 0.01, 0.04),
                                    schema.row("new metric", "deg", 1.0)]}]}
    lines = {row[1]: row for row in run_all.compare(new, old)}
    assert lines["roll RMSE"][5] == "-50.0 %" and lines["roll RMSE"][6] == "2" and lines["roll RMSE"][7] == "4"
    assert lines["seconds"][5] == "-50.0 %" and lines["peak_memory_mb"][5] == "+0.0 %"
    assert "new metric" not in lines
    json.dumps(run_all.compare(new, old))  # plain data
