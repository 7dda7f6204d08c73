"""Fleets and Monte Carlo on dask: the speed-up of 2 worker processes over 1, and the cost of dask itself.

Same work, same run, timed three ways (the cluster is started before the clock runs: a production line keeps
one):

* a fleet of ``calibrate-imu`` tasks on copies of the shipped Xsens multi-position recording: a plain loop in
  this process (no dask), then ``selfcal.pipelines.fleet.run_fleet`` on a local cluster of 1 and of 2 workers;
* the Monte Carlo study ``imu-pair-rotation`` (estimator error against the Cramér–Rao bound) on 1 and 2 workers;
  its results must be identical (seeded per run, not per worker).

Ratios follow the schema (> 1: the library's way is better): speed-up = time on 1 worker / time on 2.
On this machine (2 cores) the ideal speed-up is 2.  Usage:

    .venv/bin/python benchmarks/fleet_scaling.py [--quick] [--json out.json]
"""
from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

import _schema
from selfcal.pipelines import fleet

ROOT = Path(__file__).resolve().parents[1]
RECORDING = ROOT / "data" / "xsens_mti_multiposition"


def fleet_times(n_units: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(n_units):
            shutil.copytree(RECORDING, Path(tmp) / f"unit_{i:03d}")
        items = fleet.fleet_items(tmp)
        task = fleet.tasks()["calibrate-imu"]
        start = time.perf_counter()
        serial = [fleet.run_task(task, item) for item in items]
        out = {"serial_s": time.perf_counter() - start}
        tables = {}
        for workers in (1, 2):
            with fleet.dask_client(workers=workers) as client:
                start = time.perf_counter()
                result = fleet.run_fleet(tmp, "calibrate-imu", client=client)
                out[f"workers_{workers}_s"] = time.perf_counter() - start
                tables[workers] = result.table
        ok = [bool(r["ok"]) for r in serial]
        numeric = [c for c in tables[1].columns if c not in ("seconds",) and tables[1][c].dtype.kind == "f"]
        out["all_ok"] = all(ok) and bool(tables[1]["ok"].all()) and bool(tables[2]["ok"].all())
        out["identical"] = bool(np.array_equal(tables[1][numeric].to_numpy(), tables[2][numeric].to_numpy(),
                                               equal_nan=True))
        out["task_s_median"] = float(np.median([r["seconds"] for r in serial]))
    return out


def study_times(n_runs: int) -> dict:
    out, studies = {}, {}
    for workers in (1, 2):
        with fleet.dask_client(workers=workers) as client:
            start = time.perf_counter()
            studies[workers] = fleet.run_study("imu-pair-rotation", n_runs, client=client)
            out[f"workers_{workers}_s"] = time.perf_counter() - start
    out["identical"] = bool(np.array_equal(studies[1].errors_graph, studies[2].errors_graph))
    out["rms_over_bound"] = float(studies[2].rms_graph_rad / np.sqrt(np.trace(studies[2].bound_cov)))
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--units", type=int, default=None, help="recordings in the fleet (default 16; 6 quick)")
    parser.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default 32; 8 quick)")
    _schema.add_arguments(parser, "fleet_scaling")
    args = parser.parse_args()
    units = args.units or (6 if args.quick else 16)
    runs = args.runs or (8 if args.quick else 32)
    started = time.perf_counter()
    f = fleet_times(units)
    print(f"fleet of {units} x calibrate-imu: serial {f['serial_s']:.1f} s, 1 worker {f['workers_1_s']:.1f} s, "
          f"2 workers {f['workers_2_s']:.1f} s (task median {f['task_s_median']:.2f} s); "
          f"speed-up {f['workers_1_s'] / f['workers_2_s']:.2f}x; identical tables: {f['identical']}")
    s = study_times(runs)
    print(f"Monte Carlo imu-pair-rotation, {runs} runs: 1 worker {s['workers_1_s']:.1f} s, 2 workers "
          f"{s['workers_2_s']:.1f} s; speed-up {s['workers_1_s'] / s['workers_2_s']:.2f}x; identical: "
          f"{s['identical']}; RMS error / bound {s['rms_over_bound']:.3f}")
    rows = [
        _schema.row(f"fleet ({units} x calibrate-imu) wall time, 2 workers vs 1 worker (speed-up; 2 cores: ideal 2)",
                    "s", f["workers_2_s"], f["workers_1_s"]),
        _schema.row(f"fleet ({units} x calibrate-imu) wall time, 2 workers vs a serial loop without dask",
                    "s", f["workers_2_s"], f["serial_s"]),
        _schema.row(f"Monte Carlo ({runs} runs imu-pair-rotation) wall time, 2 workers vs 1 worker (speed-up)",
                    "s", s["workers_2_s"], s["workers_1_s"]),
        _schema.row("results identical on 1 and 2 workers (fleet table and Monte Carlo errors)", "bool",
                    float(f["identical"] and s["identical"]), better="higher"),
        _schema.row("Monte Carlo: graph rotation RMS error / Cramér–Rao bound", "ratio", s["rms_over_bound"],
                    note="1 is efficient"),
    ]
    _schema.write(args.json, "fleet_scaling", "fleet", args.quick, time.perf_counter() - started, rows,
                  {"fleet": f, "study": s, "units": units, "runs": runs})
    print(f"results: {args.json}")


if __name__ == "__main__":
    main()
