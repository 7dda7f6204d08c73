"""Every benchmark in one command: run them, print one side-by-side table, save the results, compare with a run.

Discovers every ``benchmarks/*.py`` script (except this one and ``_*.py`` helpers) that follows the results
schema (it accepts ``--quick`` and ``--json PATH``; see ``benchmarks/_schema.py`` and ``docs/benchmarks.md``),
runs each in its own subprocess, one after the other (this machine has 2 cores; a benchmark may use both),
collects their JSON and prints

* per system: the library against the patent baseline (accuracy ratio and time ratio: > 1 means the library
  is better), the real-time factor of the online paths, the efficiency against the Cramér–Rao bound
  (RMS error / bound: 1 is efficient), peak memory and run time;
* every row of every benchmark.

The combined results go to ``benchmarks/results/latest.json``; ``--compare OLD.json`` prints the change of every
metric against an earlier combined file.  Usage:

    .venv/bin/python benchmarks/run_all.py [--quick] [--only TEXT] [--compare OLD.json] [--out latest.json]
        [--collect]
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import _schema
from selfcal.io.atomic import atomic_write_text

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SCHEMA_KEYS = ("benchmark", "system", "quick", "seconds", "peak_memory_mb", "rows")


def discover(folder: Path = HERE) -> tuple[list[Path], list[Path]]:
    """(scripts following the schema, other scripts) in name order."""
    follow, other = [], []
    for path in sorted(folder.glob("*.py")):
        if path.name == Path(__file__).name or path.name.startswith("_"):
            continue
        text = path.read_text(errors="replace")
        uses_helper = "_schema.add_arguments" in text
        (follow if uses_helper or ('"--quick"' in text and '"--json"' in text) else other).append(path)
    return follow, other


def run_one(script: Path, quick: bool, timeout_s: float, results: Path = _schema.RESULTS) -> dict:
    """Run one benchmark in a subprocess; its schema JSON, or ``{"benchmark", "system", "error"}`` if it failed."""
    failure = _failure(script.stem, results / f"{script.stem}.json")
    name = script.stem
    json_path = results / f"{name}.json"
    log_path = results / f"{name}.log"
    results.mkdir(parents=True, exist_ok=True)
    before = json_path.stat().st_mtime_ns if json_path.exists() else None
    command = [sys.executable, str(script), "--json", str(json_path)] + (["--quick"] if quick else [])
    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(var, "2")  # 2 cores: no BLAS oversubscription inside one benchmark
    env["MPLBACKEND"] = "Agg"
    start = time.perf_counter()
    try:
        proc = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired as err:  # its partial output is bytes, whatever text=True said
        partial = [x.decode(errors="replace") if isinstance(x, bytes) else (x or "") for x in (err.stdout, err.stderr)]
        log_path.write_text(f"$ {' '.join(command)}\n# timed out after {timeout_s:.0f} s\n{partial[0]}\n"
                            f"--- stderr ---\n{partial[1]}")
        return failure(f"timed out after {timeout_s:.0f} s", timeout_s)
    wall = time.perf_counter() - start
    log_path.write_text(f"$ {' '.join(command)}\n# exit {proc.returncode}, {wall:.1f} s\n{proc.stdout}\n"
                        f"--- stderr ---\n{proc.stderr}")
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        return failure(f"exit {proc.returncode}: {last}", wall)
    if not json_path.exists() or json_path.stat().st_mtime_ns == before:
        return failure(f"wrote no {json_path.name}", wall)
    try:
        doc = json.loads(json_path.read_text())
    except json.JSONDecodeError as err:
        return failure(f"{json_path.name}: invalid JSON ({err})", wall)
    missing = [k for k in SCHEMA_KEYS if k not in doc]
    if missing:
        return failure(f"{json_path.name}: missing schema keys {missing}", wall)
    doc["wall_seconds"] = wall
    return doc


def _failure(name: str, previous: Path):
    """A failure record; the system is taken from the benchmark's previous results, where there are some."""
    try:
        system = json.loads(previous.read_text()).get("system", "?")
    except (OSError, ValueError):
        system = "?"
    return lambda error, wall: {"benchmark": name, "system": system, "error": error, "wall_seconds": wall}


# --- reading the rows -----------------------------------------------------------------------------------------

def kind(row: dict) -> str:
    """What a row measures, from its metric name and unit: rtf, crb, time, accuracy or other."""
    metric = row.get("metric", "").lower()
    if "real-time" in metric or "realtime" in metric or "rtf" in metric.split():
        return "rtf"
    if "crb" in metric or "cramér" in metric or "cramer" in metric or "/bound" in metric.replace(" ", ""):
        return "crb"
    if row.get("baseline") is None:
        return "other"
    if metric.startswith(("time", "seconds", "latency", "runtime")) or row.get("unit") in ("s", "ms", "us"):
        return "time"
    return "accuracy"


def geomean(values: list[float]) -> float | None:
    values = [v for v in values if v is not None and v > 0 and math.isfinite(v)]
    return math.exp(sum(map(math.log, values)) / len(values)) if values else None


def _fmt(x, digits: int = 3) -> str:
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    if x == 0:
        return "0"
    if abs(x) >= 1e4 or abs(x) < 1e-3:
        return f"{x:.{digits - 1}e}"
    return f"{x:.{digits}g}"


def _spread(rows: list[dict], key: str = "ratio") -> str:
    values = [r[key] for r in rows if r.get(key) is not None]
    if not values:
        return "-"
    g = geomean(values) if key == "ratio" else None
    if len(values) == 1:
        return _fmt(values[0])
    centre = _fmt(g) if g is not None else _fmt(sum(values) / len(values))
    return f"{centre} ({_fmt(min(values))}..{_fmt(max(values))}, n={len(values)})"


def summary_rows(docs: list[dict]) -> list[list[str]]:
    """One line per benchmark: the side-by-side figures the issue asks for."""
    lines = []
    for doc in sorted(docs, key=lambda d: (d.get("system", "?"), d["benchmark"])):
        if "error" in doc:
            lines.append([doc.get("system", "?"), doc["benchmark"], "FAILED: " + doc["error"], "", "", "", "", ""])
            continue
        rows = doc["rows"]
        by = {k: [r for r in rows if kind(r) == k] for k in ("accuracy", "time", "rtf", "crb")}
        lines.append([doc["system"], doc["benchmark"] + (" (quick)" if doc.get("quick") else ""),
                      _spread(by["accuracy"]), _spread(by["time"]), _spread(by["rtf"], "library"),
                      _spread(by["crb"], "library"), _fmt(doc.get("peak_memory_mb"), 4),
                      _fmt(doc.get("seconds"), 3)])
    return lines


def table_text(header: list[str], lines: list[list[str]]) -> str:
    widths = [max(len(str(x)) for x in col) for col in zip(header, *lines)] if lines else [len(h) for h in header]
    out = ["  ".join(str(h).ljust(w) for h, w in zip(header, widths)),
           "  ".join("-" * w for w in widths)]
    out += ["  ".join(str(x).ljust(w) for x, w in zip(line, widths)) for line in lines]
    return "\n".join(out)


def print_tables(docs: list[dict]) -> None:
    print("\nPer system (ratio > 1: the library is better; geometric mean over rows, min..max, n rows):")
    print(table_text(["system", "benchmark", "accuracy ratio (baseline/library)", "time ratio (baseline/library)",
                      "real-time factor", "RMS/CRB", "peak MB", "seconds"], summary_rows(docs)))
    lines = []
    for doc in sorted(docs, key=lambda d: (d.get("system", "?"), d["benchmark"])):
        for r in doc.get("rows", []):
            lines.append([doc["system"], r["metric"][:70], r.get("unit", ""), _fmt(r.get("library")),
                          _fmt(r.get("baseline")), _fmt(r.get("ratio")), kind(r)])
    print("\nEvery row:")
    print(table_text(["system", "metric", "unit", "library", "baseline", "ratio", "kind"], lines))


# --- comparing with an earlier run ----------------------------------------------------------------------------

def compare(new: dict, old: dict) -> list[list[str]]:
    """Per (benchmark, metric) in both runs: library value before -> after, relative change, ratio before -> after."""
    lines = []
    old_docs = {d["benchmark"]: d for d in old.get("benchmarks", [])}
    for doc in new["benchmarks"]:
        prev = old_docs.get(doc["benchmark"])
        if prev is None or "error" in doc or "error" in prev:
            continue
        note = " [quick vs full]" if bool(prev.get("quick")) != bool(doc.get("quick")) else ""
        for key, unit in (("seconds", "s"), ("peak_memory_mb", "MB")):
            lines.append([doc["benchmark"] + note, key, unit, _fmt(prev.get(key)), _fmt(doc.get(key)),
                          _change(prev.get(key), doc.get(key)), "", ""])
        prev_rows = {r["metric"]: r for r in prev.get("rows", [])}
        for r in doc["rows"]:
            p = prev_rows.get(r["metric"])
            if p is None:
                continue
            lines.append([doc["benchmark"] + note, r["metric"][:60], r.get("unit", ""), _fmt(p.get("library")),
                          _fmt(r.get("library")), _change(p.get("library"), r.get("library")),
                          _fmt(p.get("ratio")), _fmt(r.get("ratio"))])
    return lines


def _change(old, new) -> str:
    if old is None or new is None:
        return "-"
    if old == 0:
        return "0" if new == 0 else "new"
    return f"{100 * (new - old) / abs(old):+.1f} %"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="every benchmark in its --quick mode (< 1 min each)")
    parser.add_argument("--only", help="run only the benchmarks whose name contains this text")
    parser.add_argument("--out", default=str(_schema.RESULTS / "latest.json"), help="combined results JSON")
    parser.add_argument("--compare", help="an earlier combined JSON: print the change of every metric")
    parser.add_argument("--collect", action="store_true",
                        help="do not run: combine the benchmarks' existing benchmarks/results/<name>.json")
    parser.add_argument("--markdown", action="store_true",
                        help="no run: print every distribution row of the existing results as README table lines")
    parser.add_argument("--timeout", type=float, help="seconds per benchmark (default 600 quick, 7200 full)")
    args = parser.parse_args()
    if args.markdown:
        print(_schema.MARKDOWN_HEADER)
        for path in sorted(_schema.RESULTS.glob("*.json")):
            doc = json.loads(path.read_text())
            if args.only and args.only not in path.stem:
                continue
            for r in doc.get("rows", []):
                if "distribution" in r:
                    print(_schema.markdown_row(path.name, r))
        return 0
    scripts, skipped = discover()
    if args.only:
        scripts = [s for s in scripts if args.only in s.stem]
    if skipped:
        print(f"not following the results schema (skipped): {', '.join(s.name for s in skipped)}")
    timeout = args.timeout or (600.0 if args.quick else 7200.0)
    start = time.perf_counter()
    docs = []
    for i, script in enumerate(scripts, start=1):
        if args.collect:
            path = _schema.RESULTS / f"{script.stem}.json"
            doc = json.loads(path.read_text()) if path.exists() else {"benchmark": script.stem,
                                                                       "error": "no results file"}
        else:
            print(f"[{i}/{len(scripts)}] {script.name}{' --quick' if args.quick else ''} ...", end=" ", flush=True)
            doc = run_one(script, args.quick, timeout)
            print(f"{doc.get('wall_seconds', 0):.0f} s" + (f"  FAILED: {doc['error']}" if "error" in doc else ""),
                  flush=True)
        docs.append(doc)
    combined = {"created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                "quick": args.quick, "total_seconds": time.perf_counter() - start,
                "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                            "platform": platform.platform()},
                "benchmarks": docs}
    print_tables(docs)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(_schema.clean(combined), indent=1) + "\n")
    print(f"\ncombined results: {out} ({combined['total_seconds']:.0f} s)")
    if args.compare:
        old = json.loads(Path(args.compare).read_text())
        lines = compare(combined, old)
        print(f"\nChange against {args.compare} ({old.get('created', '?')}):")
        print(table_text(["benchmark", "metric", "unit", "before", "after", "change", "ratio before",
                          "ratio after"], lines) if lines else "  no metric in common")
    return 1 if any("error" in d for d in docs) else 0


if __name__ == "__main__":
    sys.exit(main())
