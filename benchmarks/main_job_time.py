"""The main job (the README's audit of the shipped Xsens recording) timed side by side: this tree against a
revision before the generic term library, in the same run, alternating.

The library adds a search after the catalog; the budget is 2x the old wall time.  Each revision runs
``selfcal audit data/xsens_mti_multiposition --system imu --json ... --report ...`` in a fresh interpreter
(``--repeats`` times, alternating, so the machine's load falls on both alike).  The older revision is checked
out with ``git worktree`` into a temporary folder and imported through ``PYTHONPATH`` (it needs the same
dependencies, which it has: they did not change).  Also printed: whether the catalog findings are the same,
and the library's share of the new run (from its progress lines).

    .venv/bin/python benchmarks/main_job_time.py [--quick] [--json out.json] [--before REV] [--repeats N]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import _schema

ROOT = Path(__file__).resolve().parents[1]
BEFORE = "ec602bf"  # main after the restructure (issue 17), before the generic term library (issue 15)
RECORDING = "data/xsens_mti_multiposition"


def run_job(pythonpath: Path, out: Path) -> tuple[float, dict, list[str]]:
    """(wall s, audit JSON, progress lines) of one main-job run with the package found at ``pythonpath``."""
    code = ("import sys; from selfcal.cli.main import main; "
            f"sys.exit(main(['-v', 'audit', {str(ROOT / RECORDING)!r}, '--system', 'imu', '--json', "
            f"{str(out / 'a.json')!r}, '--report', {str(out / 'a.html')!r}]))")
    start = time.perf_counter()
    # `python -c` puts its working folder first on sys.path: run inside the tree being timed, or every run would
    # import this tree whatever PYTHONPATH says (the figures before 2026-11-26 compared this tree with itself)
    done = subprocess.run([sys.executable, "-c", code], cwd=pythonpath, env={"PYTHONPATH": str(pythonpath), "PATH": ""},
                          capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(done.stderr[-2000:])
    progress = [line for line in done.stderr.splitlines() if "step " in line]
    return wall, json.loads((out / "a.json").read_text()), progress


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _schema.add_arguments(parser, "main_job_time")
    parser.add_argument("--before", default=BEFORE, help=f"the older revision (default {BEFORE})")
    parser.add_argument("--repeats", type=int, default=None, help="runs per revision (default 5, quick 2)")
    args = parser.parse_args()
    repeats = args.repeats or (2 if args.quick else 5)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        old_tree = Path(tmp) / "before"
        subprocess.run(["git", "worktree", "add", "--detach", str(old_tree), args.before], cwd=ROOT, check=True,
                       capture_output=True)
        try:
            times = {"before": [], "now": []}
            for _ in range(repeats):
                for name, tree in (("before", old_tree), ("now", ROOT)):
                    out = Path(tmp) / name
                    out.mkdir(exist_ok=True)
                    wall, contract, progress = run_job(tree, out)
                    times[name].append(wall)
                    if name == "before":
                        old_contract = contract
                    else:
                        new_contract, new_progress = contract, progress
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(old_tree)], cwd=ROOT, capture_output=True)
    med = {k: float(np.median(v)) for k, v in times.items()}
    same = ([f["effect"] for f in old_contract["findings"]] ==
            [f["effect"] for f in new_contract["findings"] if f["effect"] != "unlisted"])
    library_steps = sum(1 for line in new_progress if "(library)" in line)
    print(f"main job ({repeats} runs each, wall s): before {args.before}: median {med['before']:.1f} "
          f"(worst {max(times['before']):.1f}); now: median {med['now']:.1f} (worst {max(times['now']):.1f}); "
          f"ratio {med['now'] / med['before']:.2f} (budget 2.0)")
    print(f"catalog findings unchanged: {same}; library steps: {library_steps}; unlisted findings: "
          f"{sum(f['effect'] == 'unlisted' for f in new_contract['findings'])}; rejected: "
          f"{len(new_contract.get('rejected', []))}")
    rows = [_schema.row("main job wall time, median", "s", med["now"], med["before"], "lower",
                        f"baseline: {args.before} (before the library); budget: ratio >= 0.5"),
            _schema.row("main job wall time, worst", "s", max(times["now"]), max(times["before"]), "lower"),
            _schema.row("catalog findings unchanged", "bool", float(same), None, "higher")]
    _schema.write(args.json, "main_job_time", "audit", args.quick, time.perf_counter() - start, rows,
                  extra={"times": times, "library_steps": library_steps})


if __name__ == "__main__":
    main()
