"""The benchmark results schema (one JSON per benchmark; ``benchmarks/run_all.py`` reads them all).

Not a benchmark itself (the leading underscore keeps ``run_all.py`` from running it).  Scripts import it as
``from _schema import ...`` (Python puts the script's folder first on ``sys.path``).

Schema, written atomically::

    {"benchmark": "<name>", "system": "encoder|scan|imu-pair|ship|tracker|audit", "quick": false,
     "seconds": 12.3, "peak_memory_mb": 410.0,
     "rows": [{"metric": "...", "unit": "deg", "library": 0.012, "baseline": 0.034, "ratio": 2.83,
               "better": "lower", "note": "..."}],
     "extra": {}}

``ratio`` is oriented so that > 1 means the library is better: baseline / library where lower is better
(errors, times), library / baseline where higher is better (rates, real-time factors); null without a baseline.

An accuracy figure is a distribution over seeds (or scenarios), never one seed: :func:`distribution` makes its
row, whose ``library``, ``baseline`` and ``ratio`` are the medians, plus (an addition to the schema)::

    "distribution": {"population": "seeds", "n": 20, "levels": "median, p90, worst",
                     "library": {"median": ..., "p90": ..., "worst": ...}, "baseline": {...}, "ratio": {...},
                     "library_per_seed": [...], "baseline_per_seed": [...], "ratio_per_seed": [...]}

``ratio`` there is the per-seed ratio (baseline / library on the same seed).  ``p90`` and ``worst`` are taken on
the bad side: for an error the 90th percentile and the maximum, for a ratio (> 1: the library better) the 10th
percentile and the minimum; 90 % of the seeds are at least as good as ``p90``.  ``DEFAULT_SEEDS`` (20) is the
fewest seeds a full run may quote.
"""
from __future__ import annotations

import argparse
import json
import math
import resource
from pathlib import Path

from selfcal.io.atomic import atomic_write_text

RESULTS = Path(__file__).resolve().parent / "results"


def add_arguments(parser: argparse.ArgumentParser, name: str) -> None:
    """``--quick`` and ``--json PATH`` (default ``benchmarks/results/<name>.json``)."""
    parser.add_argument("--quick", action="store_true", help="small run that finishes in under a minute")
    parser.add_argument("--json", default=str(RESULTS / f"{name}.json"),
                        help=f"results in the benchmark schema (default: benchmarks/results/{name}.json)")


def _number(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def row(metric: str, unit: str, library, baseline=None, better: str = "lower", note: str = "") -> dict:
    """One result row; the ratio follows the schema's orientation (> 1: the library is better)."""
    if better not in ("lower", "higher"):
        raise ValueError(f"better must be 'lower' or 'higher', not {better!r}")
    library, baseline = _number(library), _number(baseline)
    ratio = None
    if library is not None and baseline is not None:
        num, den = (baseline, library) if better == "lower" else (library, baseline)
        ratio = num / den if den != 0 else None
    if not note:
        if baseline is None:
            note = "no baseline"
        else:
            note = ("baseline / library" if better == "lower" else "library / baseline") \
                + "; > 1 means the library is better"
    return {"metric": metric, "unit": unit, "library": library, "baseline": baseline, "ratio": ratio,
            "better": better, "note": note}


DEFAULT_SEEDS = 20  # the fewest seeds (or scenarios) behind an accuracy figure of a full run


def _levels(values, better: str) -> dict:
    """Median, 90th percentile on the bad side and worst of per-seed values."""
    import numpy as np
    v = np.asarray(values, dtype=float)
    bad_side = 90.0 if better == "lower" else 10.0
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, bad_side)),
            "worst": float(v.max() if better == "lower" else v.min())}


def distribution(metric: str, unit: str, library_per_seed, baseline_per_seed=None, better: str = "lower",
                 population: str = "seeds", note: str = "") -> dict:
    """One result row for a figure measured once per seed (or scenario): medians in ``library``/``baseline``/
    ``ratio`` (so ``run_all.py`` summarises it as any row) and the distribution (median, p90, worst) of the
    library, of the baseline and of their per-seed ratio.  Seeds where either value is missing (NaN/None: the
    run failed or skipped) are left out and counted in ``missing``."""
    import numpy as np
    lib = np.array([np.nan if x is None else float(x) for x in library_per_seed])
    base = None if baseline_per_seed is None else \
        np.array([np.nan if x is None else float(x) for x in baseline_per_seed])
    if base is not None and len(base) != len(lib):
        raise ValueError(f"{metric}: {len(lib)} library values but {len(base)} baseline values")
    ok = np.isfinite(lib) if base is None else np.isfinite(lib) & np.isfinite(base)
    if not ok.any():
        return row(metric, unit, None, None, better, note or "no seed gave a value")
    lib_ok = lib[ok]
    dist = {"population": population, "n": int(ok.sum()), "missing": int((~ok).sum()),
            "levels": "median, p90, worst (p90 and worst on the bad side)",
            "library": _levels(lib_ok, better), "library_per_seed": lib_ok.tolist()}
    ratio = None
    if base is not None:
        base_ok = base[ok]
        per_seed = base_ok / lib_ok if better == "lower" else lib_ok / base_ok
        dist.update(baseline=_levels(base_ok, better), ratio=_levels(per_seed, "higher"),
                    baseline_per_seed=base_ok.tolist(), ratio_per_seed=per_seed.tolist())
        ratio = dist["ratio"]["median"]
    if not note:
        note = (f"median over {dist['n']} {population}" + ("" if base is None else
                "; ratio: per-seed " + ("baseline / library" if better == "lower" else "library / baseline")
                + ", > 1 means the library is better"))
    out = row(metric, unit, dist["library"]["median"], None if base is None else dist["baseline"]["median"],
              better, note)
    out["ratio"] = ratio
    out["distribution"] = dist
    return out


def describe(r: dict) -> str:
    """A distribution row in one line, for the scripts' printed output."""
    d = r.get("distribution")
    if d is None:
        return f"{r['metric']}: {r['library']} {r['unit']}"
    lv = lambda x: " / ".join(f"{x[k]:.4g}" for k in ("median", "p90", "worst"))  # noqa: E731
    text = f"{r['metric']} ({d['n']} {d['population']}, median / p90 / worst): {lv(d['library'])} {r['unit']}"
    if "baseline" in d:
        text += f"; baseline {lv(d['baseline'])}; per-seed ratio {lv(d['ratio'])}"
    return text


MARKDOWN_HEADER = ("| figure (the metric in the JSON) | results JSON | seeds | ours: median / p90 / worst | "
                   "baseline: median / p90 / worst | baseline / ours per seed: median / p90 / worst |\n"
                   "|---|---|---|---|---|---|")


def _sig3(x: float) -> str:
    return f"{x:.3g}"


def markdown_row(json_name: str, r: dict) -> str:
    """A distribution row as the README quotes it (3 significant digits); tests/test_benchmarks_schema.py
    parses these lines back and compares them with the JSON."""
    d = r["distribution"]
    levels = lambda x: " / ".join(_sig3(x[k]) for k in ("median", "p90", "worst"))  # noqa: E731
    n = f"{d['n']}" + ("" if d["population"] == "seeds" else f" {d['population']}")
    base = f"{levels(d['baseline'])} {r['unit']}" if "baseline" in d else "–"
    ratio = levels(d["ratio"]) if "ratio" in d else "–"
    return f"| {r['metric']} | `{json_name}` | {n} | {levels(d['library'])} {r['unit']} | {base} | {ratio} |"


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def clean(obj):
    """Plain JSON: numpy to lists and scalars, NaN/inf to null (JSON has neither), paths to strings."""
    import numpy as np
    if isinstance(obj, dict):
        return {str(k): clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return clean(obj.tolist())
    if isinstance(obj, np.generic):
        return clean(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write(path, benchmark: str, system: str, quick: bool, seconds: float, rows: list[dict],
          extra: dict | None = None) -> Path:
    """Write the schema JSON atomically (``selfcal.io.atomic``: a failed run leaves no half file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"benchmark": benchmark, "system": system, "quick": bool(quick), "seconds": float(seconds),
           "peak_memory_mb": peak_memory_mb(), "rows": rows, "extra": extra or {}}
    text = json.dumps(clean(doc), indent=1, allow_nan=False) + "\n"
    atomic_write_text(path, text)
    return path
