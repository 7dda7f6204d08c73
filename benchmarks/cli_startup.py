"""Start-up of the command line: ``selfcal --help`` against ``python -c "import selfcal.cli"`` in the same run.

``selfcal --help`` builds the whole parser (every system's verbs, found through the registry); it must not pay
for an estimator (gtsam, scipy) it does not run.  The floor is importing the bare ``selfcal.cli`` package in a
fresh interpreter: the interpreter's own start-up plus the package.  Each command runs ``--repeats`` times in
alternation (this machine is shared: alternating spreads its load over both), and the table reports median,
90th percentile and worst wall time, the ratio of the medians, and which heavy modules the help run imported.

    .venv/bin/python benchmarks/cli_startup.py [--quick] [--json out.json] [--repeats N]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time

import numpy as np

import _schema

HELP = [sys.executable, "-c", "import sys; from selfcal.cli.main import main; sys.argv[0] = 'selfcal'; main(['--help'])"]
FLOOR = [sys.executable, "-c", "import selfcal.cli"]
HEAVY = ("gtsam", "scipy", "numpy", "open3d", "matplotlib", "dask")


def wall_s(command: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def heavy_modules_of_help() -> list[str]:
    code = ("import sys; from selfcal.cli.main import build_parser; build_parser().format_help(); "
            f"print(' '.join(m for m in {HEAVY!r} if m in sys.modules))")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()


def distribution(times: list[float]) -> dict:
    t = np.asarray(times)
    return {"median": float(np.median(t)), "p90": float(np.percentile(t, 90)), "worst": float(t.max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _schema.add_arguments(parser, "cli_startup")
    parser.add_argument("--repeats", type=int, default=None, help="runs of each command (default 30, quick 10)")
    args = parser.parse_args()
    repeats = args.repeats or (10 if args.quick else 30)
    start = time.perf_counter()
    help_s, floor_s = [], []
    for _ in range(repeats):
        help_s.append(wall_s(HELP))
        floor_s.append(wall_s(FLOOR))
    h, f = distribution(help_s), distribution(floor_s)
    heavy = heavy_modules_of_help()
    print(f"{'command':<34} {'median':>8} {'p90':>8} {'worst':>8}   ({repeats} runs each, wall s)")
    print(f"{'selfcal --help':<34} {h['median']:8.3f} {h['p90']:8.3f} {h['worst']:8.3f}")
    floor_name = 'python -c "import selfcal.cli"'
    print(f"{floor_name:<34} {f['median']:8.3f} {f['p90']:8.3f} {f['worst']:8.3f}")
    print(f"help / bare import (medians): {h['median'] / f['median']:.2f}; heavy modules imported by --help: "
          f"{', '.join(heavy) or 'none'}")
    rows = [_schema.row("selfcal --help, median wall time", "s", h["median"], f["median"], "lower",
                        "baseline: python -c 'import selfcal.cli' (the floor); ratio = floor / help"),
            _schema.row("selfcal --help, 90th percentile", "s", h["p90"], f["p90"], "lower"),
            _schema.row("selfcal --help, worst", "s", h["worst"], f["worst"], "lower"),
            _schema.row("heavy modules imported by --help", "count", len(heavy), None, "lower",
                        "gtsam, scipy, numpy, open3d, matplotlib, dask: none expected")]
    _schema.write(args.json, "cli_startup", "cli", args.quick, time.perf_counter() - start, rows,
                          extra={"help_s": help_s, "floor_s": floor_s, "heavy": heavy})


if __name__ == "__main__":
    main()
