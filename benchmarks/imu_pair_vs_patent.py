"""Inter-IMU rotation: the library's factor graph against the patent's method (seed 002), same data, one run.

Prints, per scenario, RMS rotation error of both methods over N seeded noise realisations, their ratio, the
time per calibration and its ratio, the Cramér–Rao efficiency of the graph (RMS error / bound) and the mean
NEES of its reported covariance (3 when honest); then the real-data figures.  Usage:

    .venv/bin/python benchmarks/imu_pair_vs_patent.py [--runs 200] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from selfcal.io.recording import read_recording
from selfcal.models import so3
from selfcal.pipelines.imu_calibration import calibrate_imu, calibrate_imu_pair
from selfcal.pipelines.monte_carlo import imu_pair_rotation_study, pair_scenario
from selfcal.sim.imu_scenarios import ImuNoise, ImuPairScenario, random_intrinsics
from selfcal.sim.trajectories import MultiPositionTrajectory

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=200)
    parser.add_argument("--json", help="also write the figures as JSON")
    args = parser.parse_args()
    results = {}
    scenarios = (("ideal sensors, 8 poses", pair_scenario()),
                 ("sensor biases, 8 poses spread over the sphere", biased_pair_scenario(8)),
                 ("sensor biases, 3 poses (the patent's minimum)", biased_pair_scenario(3)))
    for name, scenario in scenarios:
        summary = imu_pair_rotation_study(args.runs, scenario).summary()
        results[name] = summary
        print(f"\n== {name} + moves between them, 100 Hz, {summary['runs']} runs")
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
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
