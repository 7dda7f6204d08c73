"""Every accuracy figure the README quotes is a distribution over seeds, read from a results JSON a benchmark wrote
(issue 19): the helper's levels (median, 90th percentile on the bad side, worst; per-seed ratio), and each README
table line parsed back and compared with its JSON, which must hold >= 20 seeds unless it is marked quick or its
population is not seeds (real datasets: all there are)."""
import importlib
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"


@pytest.fixture(scope="module")
def schema():
    sys.path.insert(0, str(BENCHMARKS))
    try:
        yield importlib.import_module("_schema")
    finally:
        sys.path.remove(str(BENCHMARKS))


def test_distribution_levels_by_hand(schema):
    # errors 1..20 (lower is better): median 10.5; 90th percentile by linear interpolation 1 + 0.9 * 19 = 18.1
    lib = np.arange(1.0, 21.0)
    base = lib[::-1] * 2.0  # baseline 40, 38, ..., 2: per-seed ratio 40/1 ... 2/20
    r = schema.distribution("angle error", "deg", lib, base)
    d = r["distribution"]
    assert d["n"] == 20 and d["missing"] == 0 and d["population"] == "seeds"
    assert d["library"] == {"median": 10.5, "p90": pytest.approx(18.1), "worst": 20.0}
    assert d["baseline"] == {"median": 21.0, "p90": pytest.approx(2.0 + 0.9 * 38.0), "worst": 40.0}
    ratio = 2.0 * (21.0 - lib) / lib  # (2 (21 - k)) / k for k = 1..20
    # a ratio (> 1: the library better) is worst at its minimum and its p90 is the 10th percentile
    assert d["ratio"]["worst"] == pytest.approx(0.1)  # seed 20: 2 / 20
    assert d["ratio"]["p90"] == pytest.approx(np.percentile(ratio, 10))
    assert d["ratio"]["median"] == pytest.approx(np.median(ratio))
    assert r["library"] == 10.5 and r["baseline"] == 21.0 and r["ratio"] == pytest.approx(np.median(ratio))


def test_distribution_higher_is_better_and_missing_seeds(schema):
    # detection rates (higher is better): worst is the minimum, p90 the 10th percentile; a failed seed (None or
    # NaN on either side) is left out and counted
    r = schema.distribution("rate", "1", [0.5, 1.0, None, 0.9, 0.8], [0.4, 0.5, 0.5, float("nan"), 0.4],
                            better="higher")
    d = r["distribution"]
    assert d["n"] == 3 and d["missing"] == 2
    assert d["library"]["worst"] == 0.5 and d["library"]["median"] == 0.8
    assert d["ratio"]["worst"] == pytest.approx(1.25) and d["ratio"]["median"] == pytest.approx(2.0)
    with pytest.raises(ValueError):
        schema.distribution("x", "1", [1.0, 2.0], [1.0])


LEVELS = re.compile(r"^\s*(\S+) / (\S+) / (\S+)(?: (.+?))?\s*$")


def quoted_rows(text: str):
    """README table lines that quote a distribution: | metric | `name.json` | n | ours | baseline | ratio |."""
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 6 and re.fullmatch(r"`[\w.-]+\.json`", cells[1]):
            yield line, cells


def same_at_shown_digits(shown: str, value: float) -> bool:
    """The README shows 3 significant digits of the JSON's value."""
    return float(shown) == float(f"{value:.3g}")


def test_readme_quotes_distributions_equal_to_their_json():
    readme = (ROOT / "README.md").read_text()
    rows = list(quoted_rows(readme))
    assert len(rows) >= 8, "the README's measured figures table quotes the benchmarks' distributions"
    for line, (metric, json_cell, n_cell, ours, base, ratio) in rows:
        path = BENCHMARKS / "results" / json_cell.strip("`")
        assert path.is_file(), line
        doc = json.loads(path.read_text())
        found = [r for r in doc["rows"] if r["metric"] == metric and "distribution" in r]
        assert len(found) == 1, f"{path.name} has no distribution row {metric!r}"
        row = found[0]
        d = row["distribution"]
        n, *population = n_cell.split(" ", 1)
        assert int(n) == d["n"], line
        assert (population[0] if population else "seeds") == d["population"], line
        if d["population"] == "seeds" and not doc["quick"]:
            assert d["n"] >= 20, f"{path.name}: {metric!r} from {d['n']} seeds (a full run needs >= 20)"
        for cell, key, unit in ((ours, "library", row["unit"]), (base, "baseline", row["unit"]),
                                (ratio, "ratio", None)):
            if cell == "–":
                assert key not in d, line
                continue
            m = LEVELS.match(cell)
            assert m, f"unparsed cell {cell!r} in {line}"
            assert m.group(4) == unit, line
            for shown, level in zip(m.groups()[:3], ("median", "p90", "worst")):
                assert same_at_shown_digits(shown, d[key][level]), f"{line}: {key} {level} {shown} vs {d[key][level]}"


def test_the_json_files_the_readme_names_exist():
    readme = (ROOT / "README.md").read_text()
    for name in set(re.findall(r"benchmarks/results/([\w.-]+\.json)", readme)):
        assert (BENCHMARKS / "results" / name).is_file(), name
