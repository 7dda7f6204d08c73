"""Cost of ``selfcal audit --system encoder`` at the default simulation size: this tree against the revision
before the score tests moved to the normal equations, in the same run, alternating (issue 19 item 4).

Target: the default simulation (``selfcal simulate encoder``: 240 positions x 1024 diodes, 51 cells per image)
audited in <= 30 s and <= 1 GB; also the issue's ``--positions 40``.  Each audit runs in a fresh interpreter
(``selfcal audit REC --system encoder --json ...``); its wall time is taken here, its CPU time (user + system)
and peak resident memory from the kernel's accounting of that one child (``os.wait4``), so memory is per run.
The machine is shared: CPU time is the figure to compare, wall time is what a user waits.  The older revision
is exported with ``git archive`` into a temporary folder and imported through ``PYTHONPATH``; the audits'
findings of both revisions are compared.

Measured (this script, one run each, shared 2-core machine at load average ~12): default size 93.6 -> 8.8 s CPU,
639 -> 29.8 s wall, 1899 -> 625 MB; ``--positions 40`` 71.5 -> 7.0 s CPU, 235 -> 23.4 s wall, 1590 -> 546 MB;
findings unchanged (none: the default simulation holds no effect the audit's catalog or library names).

    .venv/bin/python benchmarks/encoder_audit_cost.py [--quick] [--json out.json] [--before REV] [--repeats N]
        [--prnu SIGMA]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from io import BytesIO
from pathlib import Path

import numpy as np

import _schema

ROOT = Path(__file__).resolve().parents[1]
BEFORE = "4990058"  # encperf: both crash fixes of the default size in, score tests still on the dense Jacobian
WALL_BUDGET_S, MEMORY_BUDGET_MB = 30.0, 1024.0


def export(revision: str, folder: Path) -> Path:
    """The package tree of ``revision`` in ``folder`` (``git archive``: no worktree registered)."""
    archive = subprocess.run(["git", "archive", revision, "selfcal"], cwd=ROOT, check=True, capture_output=True).stdout
    with tarfile.open(fileobj=BytesIO(archive)) as tar:
        tar.extractall(folder, filter="data")
    return folder


def run_cli(pythonpath: Path, argv: list[str], cwd: Path) -> dict:
    """Wall s, CPU s and peak RSS (MB) of one ``selfcal`` command in a fresh interpreter.

    ``cwd`` must hold no ``selfcal`` folder: ``python -c`` puts the working directory before ``PYTHONPATH``."""
    code = f"import sys; from selfcal.cli.main import main; sys.exit(main({argv!r}))"
    start = time.perf_counter()
    child = subprocess.Popen([sys.executable, "-c", code], cwd=cwd, env={"PYTHONPATH": str(pythonpath), "PATH": ""},
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    stderr = child.stderr.read()
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - start
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode != 0:
        raise RuntimeError(stderr.decode()[-2000:])
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _schema.add_arguments(parser, "encoder_audit_cost")
    parser.add_argument("--before", default=BEFORE, help=f"the older revision (default {BEFORE})")
    parser.add_argument("--repeats", type=int, default=None, help="runs per revision and size (default 2, quick 1)")
    parser.add_argument("--prnu", type=float, default=0.0, help="simulate a per-diode gain (1 sigma, default 0)")
    args = parser.parse_args()
    repeats = args.repeats or (1 if args.quick else 2)
    sizes = {"positions 40": ["--positions", "40"]} if args.quick else \
        {"default (240 positions)": [], "positions 40": ["--positions", "40"]}
    start = time.perf_counter()
    runs: dict = {size: {"before": [], "now": []} for size in sizes}
    findings: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        old_tree = export(args.before, Path(tmp) / "before")
        for size, options in sizes.items():
            rec = Path(tmp) / f"rec {size}"
            run_cli(ROOT, ["simulate", "encoder", "--out", str(rec), "--prnu", str(args.prnu), *options], Path(tmp))
            for _ in range(repeats):
                for name, tree in (("before", old_tree), ("now", ROOT)):
                    out = Path(tmp) / f"{name}.json"
                    runs[size][name].append(run_cli(tree, ["audit", str(rec), "--system", "encoder", "--json",
                                                           str(out)], Path(tmp)))
                    audit = json.loads(out.read_text())
                    findings.setdefault(size, {})[name] = [(f["effect"], f.get("driver"), f.get("form"))
                                                           for f in audit["findings"]]
                    print(f"{size:24s} {name:6s} " + "  ".join(f"{k} {v:.1f}" for k, v in runs[size][name][-1].items())
                          + f"  findings {findings[size][name]}", flush=True)
    rows = []
    for size in sizes:
        med = {name: {k: float(np.median([r[k] for r in runs[size][name]])) for k in ("wall_s", "cpu_s", "peak_rss_mb")}
               for name in ("before", "now")}
        same = findings[size]["before"] == findings[size]["now"]
        rows += [_schema.row(f"{size}: audit CPU time, median", "s", med["now"]["cpu_s"], med["before"]["cpu_s"]),
                 _schema.row(f"{size}: audit wall time, median", "s", med["now"]["wall_s"], med["before"]["wall_s"],
                             note=f"budget {WALL_BUDGET_S:.0f} s at the default size; shared machine: see CPU"),
                 _schema.row(f"{size}: audit peak RSS, median", "MB", med["now"]["peak_rss_mb"],
                             med["before"]["peak_rss_mb"], note=f"budget {MEMORY_BUDGET_MB:.0f} MB at the default size"),
                 _schema.row(f"{size}: findings unchanged", "bool", float(same), None, "higher")]
        print(f"{size}: CPU {med['before']['cpu_s']:.1f} -> {med['now']['cpu_s']:.1f} s "
              f"(x{med['before']['cpu_s'] / med['now']['cpu_s']:.1f}), wall {med['before']['wall_s']:.1f} -> "
              f"{med['now']['wall_s']:.1f} s, peak RSS {med['before']['peak_rss_mb']:.0f} -> "
              f"{med['now']['peak_rss_mb']:.0f} MB; findings unchanged: {same}")
    _schema.write(args.json, "encoder_audit_cost", "encoder", args.quick, time.perf_counter() - start, rows,
                  extra={"before": args.before, "prnu": args.prnu, "repeats": repeats, "runs": runs,
                         "findings": findings, "budget": {"wall_s": WALL_BUDGET_S, "peak_rss_mb": MEMORY_BUDGET_MB}})


if __name__ == "__main__":
    main()
