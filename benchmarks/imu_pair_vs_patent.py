"""Inter-IMU rotation: the library's factor graph against the patent's method (seed 002), same data, one run.

Prints, per scenario, the rotation error of both methods over N seeded noise realisations (median, 90th
percentile and worst, and of their per-seed ratio; RMS too), the time per calibration and its ratio, the Cramér–Rao efficiency of the graph (RMS error / bound) and the mean
NEES of its reported covariance (3 when honest); then the real-data figures.  Usage:

    .venv/bin/python benchmarks/imu_pair_vs_patent.py [--quick] [--runs 200] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from selfcal.io.recording import read_recording
from selfcal.core import so3
from selfcal.pipelines.imu import calibrate_imu
from selfcal.pipelines.imu_pair import calibrate_imu_pair
from selfcal.pipelines.imu_pair import imu_pair_rotation_study, pair_scenario
from selfcal.core.inertial import ImuNoise
from selfcal.sim.imu import ImuPairScenario, random_intrinsics
from selfcal.sim.trajectories import MultiPositionTrajectory

import _schema  # benchmarks/_schema.py: the results schema every benchmark writes

ROOT = Path(__file__).resolve().parents[1]


def biased_pair_scenario(n_poses: int, seed: int = 7) -> ImuPairScenario:
    """Each IMU has accelerometer and gyro biases (no scale errors): the patent's residual a0 - R a1 has no
    term for them, the graph's relative offsets absorb them.  Over poses spread evenly on the sphere the
    offsets average out of the patent's sums; over the patent's minimum (level and two sides) they do not."""
    noise = ImuNoise(accelerometer_random_walk=0.0, gyroscope_random_walk=0.0)
    kwargs = {}
    for suffix, sub_seed in (("0", seed + 1), ("1", seed + 2)):
        accel, gyro = random_intrinsics(sub_seed, scale=(0.0, 0.0), misalignment_rad=0.0, gyro_axis_rotation_rad=0.0)
        kwargs["accel" + suffix], kwargs["gyro" + suffix] = accel, gyro
    trajectory = MultiPositionTrajectory(n_poses=n_poses, static_s=3.0, move_s=2.0, seed=seed)
    return ImuPairScenario.random(trajectory, seed=seed, intrinsics=False, noise0=noise, noise1=noise,
                                  rate_hz=100.0, **kwargs)


def real_data() -> dict:
    out = {}
    start = time.perf_counter()
    cal = calibrate_imu(read_recording(ROOT / "data/xsens_mti_multiposition"), "imu0")
    d = cal.to_dict()
    out["xsens_intrinsics"] = {"seconds": time.perf_counter() - start,
                               "accel_counts_per_unit": d["raw_counts"]["accelerometer_counts_per_unit"],
                               "datasheet_counts_per_unit": [415, 413, 415],
                               "static_gravity_residual_m_s2": d["residual_rms"]["accel"]}
    rec = read_recording(ROOT / "data/ansfl_quadrotor_horizontal_1")
    start = time.perf_counter()
    R = [calibrate_imu_pair(rec, a, b).estimate.R_imu0_imu1 for a, b in (("imu0", "imu1"), ("imu1", "imu2"),
                                                                         ("imu2", "imu0"))]
    out["ansfl_horizontal_pairs"] = {
        "seconds_for_3_pairs": time.perf_counter() - start,
        "loop_closure_deg": float(np.degrees(np.linalg.norm(so3.log(R[0] @ R[1] @ R[2])))),
        "patent": "not applicable: a flight has no static poses, the patent's residual needs them"}
    return out


def study(args, scenario):
    """The seeded Monte Carlo study, in this process or on dask (selfcal.pipelines.fleet.run_study)."""
    if not args.workers:
        return imu_pair_rotation_study(args.runs, scenario)
    from selfcal.pipelines.fleet import run_study
    return run_study("imu-pair-rotation", args.runs, first_seed=1000, workers=args.workers, scenario=scenario)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=None, help="noise realisations per scenario (default 200; "
                                                                    "30 with --quick)")
    parser.add_argument("--workers", type=int, default=0,
                        help="run the seeded runs on a local dask cluster of this many workers (same estimates, "
                             "bit for bit; default 0: in this process)")
    _schema.add_arguments(parser, "imu_pair_vs_patent")
    args = parser.parse_args()
    args.runs = args.runs or (30 if args.quick else 200)
    started = time.perf_counter()
    results = {}
    scenarios = (("ideal sensors, 8 poses", pair_scenario()),
                 ("sensor biases, 8 poses spread over the sphere", biased_pair_scenario(8)),
                 ("sensor biases, 3 poses (the patent's minimum)", biased_pair_scenario(3)))
    for name, scenario in scenarios:
        result = study(args, scenario)
        summary = result.summary()
        summary["rotation_error_per_seed_deg"] = {  # seeds 1000, 1001, ...: |log(R_true^T R_est)|
            "graph": np.degrees(np.linalg.norm(result.errors_graph, axis=1)),
            "patent": np.degrees(np.linalg.norm(result.errors_patent, axis=1))}
        results[name] = summary
        print(f"\n== {name} + moves between them, 100 Hz, {summary['runs']} runs")
        print("  " + _schema.describe(error_row(name, summary)))
        print(f"  RMS rotation error  graph {summary['rms_rotation_error_graph_deg']:.5f} deg   "
              f"patent {summary['rms_rotation_error_patent_deg']:.5f} deg   "
              f"patent/graph = {summary['accuracy_ratio_patent_over_graph']:.2f}")
        print(f"  time per run        graph {summary['seconds_per_run_graph'] * 1e3:.1f} ms   "
              f"patent {summary['seconds_per_run_patent'] * 1e3:.2f} ms   "
              f"graph/patent = {summary['time_ratio_graph_over_patent']:.1f}")
        print(f"  graph efficiency    RMS/bound = {summary['efficiency_ratio']:.3f} (target <= 1.15)   "
              f"mean NEES = {summary['mean_nees']:.2f} (expected 3)")
    results["real data"] = real_data()
    print("\n== real data")
    print(json.dumps(results["real data"], indent=1))
    _schema.write(args.json, "imu_pair_vs_patent", "imu-pair", args.quick, time.perf_counter() - started,
                  schema_rows(results), {"runs": args.runs, "scenarios": results})
    print(f"results: {args.json}")


def error_row(name: str, s: dict) -> dict:
    """The rotation error per seed, graph vs patent 002: median, p90, worst and the per-seed ratio."""
    per_seed = s["rotation_error_per_seed_deg"]
    return _schema.distribution(f"rotation error, {name}", "deg", per_seed["graph"], per_seed["patent"])


def schema_rows(results: dict) -> list[dict]:
    """The printed figures as schema rows: graph vs patent 002 per scenario, then the real data."""
    rows = []
    for name, s in results.items():
        if name == "real data":
            continue
        rows += [
            error_row(name, s),
            _schema.row(f"rotation RMSE over the seeds, {name}", "deg", s["rms_rotation_error_graph_deg"],
                        s["rms_rotation_error_patent_deg"]),
            _schema.row(f"time per calibration, {name}", "s", s["seconds_per_run_graph"],
                        s["seconds_per_run_patent"]),
            _schema.row(f"efficiency RMS/CRB, {name}", "x", s["efficiency_ratio"],
                        note="graph RMS rotation error / Cramér–Rao bound; 1 is efficient"),
            _schema.row(f"mean NEES, {name}", "-", s["mean_nees"],
                        note="graph's reported covariance; 3 when honest")]
    real = results["real data"]
    counts = np.asarray(real["xsens_intrinsics"]["accel_counts_per_unit"], dtype=float)
    sheet = np.asarray(real["xsens_intrinsics"]["datasheet_counts_per_unit"], dtype=float)
    rows += [
        _schema.row("Xsens accel sensitivity, max |estimate - factory| / factory", "%",
                    100 * float(np.max(np.abs(counts - sheet) / sheet)), note="real data; no baseline"),
        _schema.row("Xsens static gravity residual", "m s^-2",
                    real["xsens_intrinsics"]["static_gravity_residual_m_s2"], note="real data; no baseline"),
        _schema.row("ANSFL horizontal flight, rotation loop closure R01 R12 R20", "deg",
                    real["ansfl_horizontal_pairs"]["loop_closure_deg"],
                    note="real data; patent not applicable (no static poses in flight)")]
    return rows


if __name__ == "__main__":
    main()
