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
