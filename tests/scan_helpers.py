"""Shared helpers of the scan tests: a simulated scan as the pipeline's ScanData without the disk round trip
(the recording round trip itself is tested in test_scan_pipeline.py)."""
import numpy as np

from selfcal.pipelines.scan import ScanData


def scan_data(sim) -> ScanData:
    sc = sim.scenario
    t0 = sim.ins_t_s[0]
    return ScanData(sim.clock_stamp_s - t0, [p.astype(np.float32).astype(float) for p in sim.points_V],
                    sim.ins_t_s - t0, sim.ins_R, sim.ins_r, sim.ins_v, sim.ins_gyro, sim.ins_accel,
                    sim.imu_R_vision, sim.imu_t_vision, (sim.left, sim.right), sc.pixel_sigma, sc.sphere_radius_m,
                    np.asarray(sc.error_sigmas, float),
                    np.r_[np.full(3, sc.ins_jitter_rad), np.full(3, sc.ins_jitter_m)])
