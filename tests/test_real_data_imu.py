"""The IMU pipelines on real recordings, against published reference values (see each SOURCE.md).

Shipped recordings are read from data/; the public datasets in place from ../shared/data (skipped, with the
reason, where absent).  Run with ``-s`` to see the measured figures.
"""
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from selfcal.io.importers import import_ansfl_quadrotor
from selfcal.io.recording import ACCEL_COLUMNS, read_recording
from selfcal.pipelines.imu import calibrate_imu
from selfcal.pipelines.imu_pair import calibrate_imu_pair
from shared_data import SHARED_DATA

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA = REPO_ROOT / "data"
SHARED = SHARED_DATA

# data/xsens_mti_multiposition/SOURCE.md: the Xsens factory ("datasheet") calibration of this unit, counts per SI unit
XSENS_ACCEL_COUNTS_PER_M_S2 = np.array([415.0, 413.0, 415.0])
XSENS_GYRO_COUNTS_PER_RAD_S = np.array([4778.0, 4758.0, 4766.0])
ISSUE_ACCEL_RESIDUAL_TARGET_M_S2 = 0.0015  # static |f| - g RMS the issue asks for on this recording


@pytest.fixture(scope="module")
def xsens():
    return calibrate_imu(read_recording(DATA / "xsens_mti_multiposition"), "imu0")


# --- (a) Xsens MTi against its factory calibration ---------------------------------------------------------------

def test_xsens_sensitivities_match_the_factory_calibration(xsens):
    d = xsens.to_dict()
    accel = np.asarray(d["raw_counts"]["accelerometer_counts_per_unit"])
    gyro = np.asarray(d["raw_counts"]["gyroscope_counts_per_unit"])
    print(f"\nxsens accel counts per m/s^2 {np.round(accel, 2)} vs factory {XSENS_ACCEL_COUNTS_PER_M_S2} "
          f"({np.round(100 * (accel / XSENS_ACCEL_COUNTS_PER_M_S2 - 1), 3)} %)")
    print(f"xsens gyro counts per rad/s {np.round(gyro, 2)} vs factory {XSENS_GYRO_COUNTS_PER_RAD_S} "
          f"({np.round(100 * (gyro / XSENS_GYRO_COUNTS_PER_RAD_S - 1), 3)} %)")
    print(f"xsens residual |f| - g RMS {d['residual_rms']['accel']:.4g} m/s^2 over {d['static_poses']} poses; "
          f"gyro direction residual {np.degrees(d['residual_rms']['gyro']):.3g} deg")
    # 1 % (the issue's figure): the factory values are rounded to 3 digits (+-0.12 % at 415) and come from another
    # calibration of this unit (the factory's, with its own misalignment model, at another time and temperature)
    assert np.all(np.abs(accel / XSENS_ACCEL_COUNTS_PER_M_S2 - 1) < 0.01)
    assert np.all(np.abs(gyro / XSENS_GYRO_COUNTS_PER_RAD_S - 1) < 0.01)


def test_xsens_static_gravity_residual_meets_the_issue_target(xsens):
    assert xsens.to_dict()["residual_rms"]["accel"] <= ISSUE_ACCEL_RESIDUAL_TARGET_M_S2


# --- (b) the result does not come from the nominal transfer function ---------------------------------------------

SCALE = 1.03


def rescaled_xsens():
    """The Xsens recording with the nominal accelerometer transfer function changed by 3 %: SI values x 1.03 and
    counts_per_unit / 1.03, i.e. the very same raw counts under another nominal model."""
    rec = read_recording(DATA / "xsens_mti_multiposition")
    sensor = rec.sensors["imu0"]
    for column in ACCEL_COLUMNS:
        sensor.values[column] = sensor.values[column] * SCALE
    nominal = sensor.meta["raw_counts"]["accelerometer"]
    nominal["counts_per_unit"] = [c / SCALE for c in nominal["counts_per_unit"]]
    return rec


@pytest.fixture(scope="module")
def xsens_rescaled():
    return calibrate_imu(rescaled_xsens(), "imu0")


def counts_per_unit(cal):
    return np.asarray(cal.to_dict()["raw_counts"]["accelerometer_counts_per_unit"])


def test_sensitivity_is_not_the_nominal_transfer_function(xsens, xsens_rescaled):
    """A result echoing the nominal would move by 3 %; an estimate from the data must not move by a statistically
    visible amount: less than its own reported 1-sigma (relative sigma = sigma of the diagonal of M)."""
    a, b = counts_per_unit(xsens), counts_per_unit(xsens_rescaled)
    relative_sigma = np.diag(np.asarray(xsens.to_dict()["accelerometers"]["M_sigma"]))
    change = b / a - 1
    print(f"\ncounts per unit after a 3 % nominal change: relative change {change}, "
          f"i.e. {np.round(np.abs(change) / relative_sigma, 3)} of its reported sigma")
    assert np.all(np.abs(change) < relative_sigma)


def test_sensitivity_is_exactly_invariant_to_the_nominal_transfer_function(xsens, xsens_rescaled):
    """Same counts, another nominal: the problem is the same up to a change of variables (M -> M / 1.03,
    b -> 1.03 b, every residual and sigma unchanged), so the counts per unit must agree to the solver's precision.
    LM stops when the cost changes by < 1e-10 relative, i.e. within ~sqrt(2 * 350 * 1e-10) ~ 3e-4 sigma of the
    optimum; with a relative sigma ~1e-5 that is ~3e-9, so 1e-8 (tighter than the 1e-6 of the issue brief)."""
    a, b = counts_per_unit(xsens), counts_per_unit(xsens_rescaled)
    assert np.all(np.abs(b / a - 1) < 1e-8), b / a - 1


# --- (c) ANSFL quadrotor: rotation and clock loops over three IMUs -------------------------------------------------

ANSFL_VERTICAL = SHARED / "ansfl_quadrotor_4xsensdot_rtk" / "Vertical" / "path_1"
ISSUE_LOOP_TARGET_DEG = 0.5
LOOP = (("imu0", "imu1"), ("imu1", "imu2"), ("imu2", "imu0"))


def ansfl_recording(name):
    if name == "vertical_1":
        if not ANSFL_VERTICAL.is_dir():
            pytest.skip(f"public dataset not available at {ANSFL_VERTICAL} (set SELFCAL_SHARED_DATA)")
        return import_ansfl_quadrotor(ANSFL_VERTICAL)
    return read_recording(DATA / f"ansfl_quadrotor_{name}")


@pytest.mark.parametrize("path", ["horizontal_1", "straightline_1", "vertical_1"])
def test_ansfl_rotation_and_time_offset_loops_close(path):
    rec = ansfl_recording(path)
    cals = [calibrate_imu_pair(rec, a, b).estimate for a, b in LOOP]
    # v_imu0 = R01 v_imu1 = R01 R12 v_imu2 = R01 R12 R20 v_imu0: the product must be the identity
    loop = cals[0].R_imu0_imu1 @ cals[1].R_imu0_imu1 @ cals[2].R_imu0_imu1
    loop_deg = np.degrees(np.linalg.norm(Rotation.from_matrix(loop).as_rotvec()))
    angles = [np.degrees(np.linalg.norm(Rotation.from_matrix(c.R_imu0_imu1).as_rotvec())) for c in cals]
    print(f"\nANSFL {path}: pair rotations {np.round(angles, 3)} deg; loop R01 R12 R20 = {loop_deg:.4f} deg")
    assert loop_deg < ISSUE_LOOP_TARGET_DEG

    dts = [c.time_offset_s for c in cals]
    if any(dt is None for dt in dts):
        print(f"  time offset not estimated for every pair: {[c.notes for c in cals]}")
        return
    sigmas = np.array([c.time_offset_sigma_s for c in cals])
    # t0 = t1 + dt01, t1 = t2 + dt12, t2 = t0 + dt20: the sum is 0.  Combined sigma as if the three estimates were
    # independent (they share IMUs, so this is an approximation of the closure's sigma).
    closure, sigma = float(np.sum(dts)), float(np.sqrt(np.sum(sigmas**2)))
    print(f"  time offsets {np.round(np.array(dts) * 1e3, 3)} ms (1-sigma {np.round(sigmas * 1e3, 4)} ms); "
          f"loop {closure * 1e3:.4f} ms = {closure / sigma:.2f} combined sigma")
    assert abs(closure) < 3 * sigma


# --- (d) MPU-6050 against the upstream Tedaldi-style calibration -----------------------------------------------------

# data/mpu6050_multiposition/SOURCE.md, upstream result on the same recording (reference values, not ground truth)
MPU_UPSTREAM_ACCEL_M_S2_PER_COUNT = np.array([6.020e-4, 5.968e-4, 5.859e-4])
MPU_UPSTREAM_GYRO_RAD_S_PER_COUNT = np.array([1.374e-4, 1.329e-4, 1.339e-4])


def test_mpu6050_accelerometer_scale_matches_upstream():
    cal = calibrate_imu(read_recording(DATA / "mpu6050_multiposition"), "imu0").to_dict()
    counts = cal["raw_counts"]
    accel_per_count = 1.0 / np.asarray(counts["accelerometer_counts_per_unit"])
    gyro_per_count = 1.0 / np.asarray(counts["gyroscope_counts_per_unit"])
    accel_diff = accel_per_count / MPU_UPSTREAM_ACCEL_M_S2_PER_COUNT - 1
    gyro_diff = gyro_per_count / MPU_UPSTREAM_GYRO_RAD_S_PER_COUNT - 1
    print(f"\nMPU-6050 accel scale {accel_per_count} m/s^2 per count vs upstream "
          f"{MPU_UPSTREAM_ACCEL_M_S2_PER_COUNT}: {np.round(100 * accel_diff, 3)} %")
    print(f"MPU-6050 gyro scale {gyro_per_count} rad/s per count vs upstream "
          f"{MPU_UPSTREAM_GYRO_RAD_S_PER_COUNT}: {np.round(100 * gyro_diff, 3)} % (reported, not asserted)")
    print(f"MPU-6050 residual |f| - g RMS {cal['residual_rms']['accel']:.4g} m/s^2 over {cal['static_poses']} poses")
    # 0.5 %: a similar scale/non-orthogonality model (Tedaldi et al.), but upstream fits ~10 poses found by its own
    # detector, several only 2-12 samples long (SOURCE.md); one sample has sigma ~0.036 m/s^2 (sensor.yaml noise
    # density x sqrt(100 Hz)), so a 2-sample pose mean is uncertain by ~0.026 m/s^2 = 0.26 % of g, which bounds the
    # upstream scale to a few 0.1 %; upstream values are given to 4 digits (<= 0.01 %).
    assert np.all(np.abs(accel_diff) < 0.005)
