"""Importers of the public datasets in ../shared/data, and the recordings shipped in data/.

These tests read the real datasets (see each SOURCE.md); they are skipped where that folder is absent.
Tolerances come from the sensors' datasheets or the recording itself, as stated at each check.
"""
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

from selfcal.io.importers import (IMPORTERS, MPU6050_ACCEL_COUNTS_PER_M_S2, import_ansfl_quadrotor,
                                  import_imu_tk_xsens, import_mpu6050_tomisuarez)
from selfcal.io.recording import RecordingError, read_recording, write_recording
from shared_data import SHARED_DATA

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = SHARED_DATA
XSENS = SHARED / "imu_tk_xsens_multiposition"
MPU = SHARED / "mpu6050_tedaldi_calib_tomisuarez"
ANSFL = SHARED / "ansfl_quadrotor_4xsensdot_rtk"

needs_shared = pytest.mark.skipif(not SHARED.is_dir(),
                                  reason=f"real datasets not available at {SHARED} (set SELFCAL_SHARED_DATA)")

IMU_UNITS = {"w_RS_S_x": "rad s^-1", "w_RS_S_y": "rad s^-1", "w_RS_S_z": "rad s^-1",
             "a_RS_S_x": "m s^-2", "a_RS_S_y": "m s^-2", "a_RS_S_z": "m s^-2"}
KALIBR_KEYS = ("accelerometer_noise_density", "gyroscope_noise_density",
               "accelerometer_random_walk", "gyroscope_random_walk")


def first_seconds(data, seconds):
    return data.t_s < seconds


# -------------------------------------------------------------------------------------------- imu_tk Xsens

@needs_shared
def test_xsens_import():
    rec = import_imu_tk_xsens(XSENS)
    assert list(rec.sensors) == ["imu0"]
    s = rec.sensors["imu0"]
    assert s.units == IMU_UNITS
    imu = rec.imu("imu0")
    assert len(imu.t_ns) == 51175  # SOURCE.md
    assert imu.t_ns.dtype == np.int64 and imu.t_ns[0] == 29_840_000  # t = 0.0298400 s, kept as recorded
    dt_ns = np.diff(imu.t_ns)
    assert dt_ns.min() > 0 and np.median(dt_ns) == 10_000_000  # jittered 9.0 .. 10.4 ms, 100 Hz
    assert imu.rate_hz == 100 and s.meta["gravity_m_s2"] == 9.81744
    for key in (*KALIBR_KEYS, "sensor_type", "noise_source", "source"):
        assert key in s.meta, key

    static = first_seconds(imu, 30.0)
    # factory scale/offset: the norm of the static specific force equals local g to within the factory model's
    # residual errors (misalignment not applied, ~1 %); 2 % is the stated acceptance
    assert abs(np.linalg.norm(imu.accel_m_s2[static].mean(axis=0)) - 9.81) < 0.02 * 9.81
    # static gyro: Earth rate (7e-5 rad/s) + bias; a units error (counts, deg/s) would be orders larger
    assert np.linalg.norm(imu.gyro_rad_s[static].mean(axis=0)) < 0.02
    # white noise from SOURCE.md: acc std ~3.3 counts, gyro std ~27 counts over the first 30 s
    assert s.meta["accelerometer_noise_density"] == pytest.approx(3.3 / 415 / 10, rel=0.1)
    assert s.meta["gyroscope_noise_density"] == pytest.approx(27 / 4770 / 10, rel=0.1)

    # raw_counts reproduces the upstream integers exactly: counts = offset + counts_per_unit * value
    raw = np.loadtxt(XSENS / "xsens_acc.mat.gz")[:, 1:]
    acc = s.meta["raw_counts"]["accelerometer"]
    counts = np.asarray(acc["offset_counts"]) + np.asarray(acc["counts_per_unit"]) * imu.accel_m_s2
    assert np.max(np.abs(counts - raw)) < 1e-8


# ---------------------------------------------------------------------------------------- MPU-6050 tomisuarez

@needs_shared
def test_mpu6050_import_calibration_log():
    rec = import_mpu6050_tomisuarez(MPU / "example_data_calibration.csv.gz")
    imu = rec.imu("imu0", gyro_saturation_allowed=True)  # its gyro clips at 250 deg/s in two moves (test_sanity)
    meta = rec.sensors["imu0"].meta
    assert rec.sensors["imu0"].units == IMU_UNITS
    assert len(imu.t_ns) == 10245  # SOURCE.md
    assert np.array_equal(imu.t_ns, np.arange(10245, dtype=np.int64) * 10_000_000)
    assert imu.rate_hz == 100 and meta["upstream_settings"]["initialization_time_s"] == 36.5
    for key in (*KALIBR_KEYS, "raw_counts", "gravity_m_s2", "source"):
        assert key in meta, key

    static = first_seconds(imu, 30.0)
    counts = imu.accel_m_s2[static] * MPU6050_ACCEL_COUNTS_PER_M_S2
    assert np.allclose(counts, np.round(counts), atol=1e-9)  # the nominal conversion is exactly invertible
    # Nominal model: |f| is NOT 1 g on this unit (0.91 g): the datasheet allows +-3 % sensitivity and +-80 mg
    # zero-g offset on z, so |f| may be off by up to ~11 %.
    norm_nominal = np.linalg.norm(imu.accel_m_s2[static].mean(axis=0))
    assert abs(norm_nominal - 9.80665) < 0.11 * 9.80665
    # With the upstream calibration (README: f = scale * (counts + bias)) it is 1 g to within 1 %: the counts
    # survived the conversion and the upstream numbers describe this unit.
    scale = np.array([6.020083400010406817e-04, 5.968449488725015338e-04, 5.859241382355084718e-04])
    bias = np.array([-7.115163422327075295e+02, 3.585054836108664063e+02, 1.840128451085784491e+03])
    calibrated = scale * (counts.mean(axis=0) + bias)
    assert abs(np.linalg.norm(calibrated) - 9.80665) < 0.01 * 9.80665
    # white noise: datasheet accel 400 ug/sqrt(Hz) = 3.9e-3 m s^-2 Hz^-1/2 (sampled with DLPF 0 at 100 Hz)
    assert 1e-3 < meta["accelerometer_noise_density"] < 1e-2
    assert 5e-5 < meta["gyroscope_noise_density"] < 5e-4


@needs_shared
def test_mpu6050_import_static_log():
    imu = import_mpu6050_tomisuarez(MPU / "example_data_tinit_calc.csv.gz").imu("imu0")
    assert len(imu.t_ns) == 44930 and imu.t_ns[-1] == 44929 * 10_000_000
    norm = np.linalg.norm(imu.accel_m_s2, axis=1).mean()
    assert abs(norm - 9.80665) < 0.11 * 9.80665  # datasheet tolerance, as above
    # static for 449 s: mean rate = gyro bias, within the datasheet's +-20 deg/s zero-rate output
    assert np.all(np.abs(imu.gyro_rad_s.mean(axis=0)) < math.radians(20))


@needs_shared
def test_mpu6050_noise_window_stops_at_motion():
    meta = import_mpu6050_tomisuarez(MPU / "imu_90_x_rot.csv.gz").sensors["imu0"].meta
    # the rotation starts ~15 s in: the noise estimate must not include it
    assert "first 15 s" in meta["noise_source"]
    assert meta["gyroscope_noise_density"] < 5e-4


# ----------------------------------------------------------------------------------------------- ANSFL

@needs_shared
def test_ansfl_import():
    rec = import_ansfl_quadrotor(ANSFL / "StraightLine" / "path_1")
    assert rec.imu_names() == ["imu0", "imu1", "imu2", "imu3"]
    assert list(rec.sensors) == ["imu0", "imu1", "imu2", "imu3", "reference0"]
    imus = [rec.imu(n) for n in rec.imu_names()]
    for imu in imus:
        assert len(imu.t_ns) == 2880 and np.array_equal(imu.t_ns, imus[0].t_ns)  # one shared time base
        assert imu.rate_hz == 120
        assert set(np.diff(imu.t_ns)) == {8_333_000}  # upstream steps 0.008333 s, not 1/120 s
        assert imu.channel_units == {"euler_x": "deg", "euler_y": "deg", "euler_z": "deg"}
        # gyro in rad/s: the flight turns at up to ~1 rad/s (57 deg/s), far inside the 2000 deg/s range
        assert 0.5 < np.abs(imu.gyro_rad_s).max() < math.radians(2000)
        assert 0.05 < np.median(np.linalg.norm(imu.gyro_rad_s, axis=1)) < 1.0
        # mean specific force over a flight is ~g; the four DOTs disagree by up to 10 % among themselves here
        assert abs(np.linalg.norm(imu.accel_m_s2.mean(axis=0)) - 9.8) < 0.1 * 9.8
        for key in (*KALIBR_KEYS, "noise_source", "sensor_type", "source"):
            assert key in rec.sensors[imu.name].meta, key
    # unit check from the data themselves: d(roll)/dt (deg/s, on-board filter) against gyro x (rad/s); near level
    # flight the roll rate equals the body x rate, so the slope is 1 when the gyro really is in rad/s
    imu = imus[0]
    roll_rate_rad_s = np.gradient(np.radians(imu.channels["euler_x"]), imu.t_s)
    slope = np.dot(roll_rate_rad_s, imu.gyro_rad_s[:, 0]) / np.dot(roll_rate_rad_s, roll_rate_rad_s)
    assert slope == pytest.approx(1.0, abs=0.05)

    ref = rec.sensors["reference0"]
    assert ref.units == {"distance": "m", "speed": "m s^-1", "compass_heading": "deg", "pitch": "deg",
                         "roll": "deg", "height_above_takeoff": "m", "north": "m", "east": "m", "down": "m"}
    assert len(ref.t_ns) == 239 and set(np.diff(ref.t_ns)) == {100_000_000}
    assert ref.values["north"][0] == 0.0 and ref.meta["rate_hz"] == 10
    # StraightLine path_1: 24 s at an average 5.4 m/s over the four straight lines (README) -> ~100 m covered
    travelled_m = np.hypot(ref.values["north"][-1], ref.values["east"][-1])
    assert 50 < travelled_m < 250


# ------------------------------------------------------------------------------------------- bad sources

@pytest.mark.parametrize("kind", sorted(IMPORTERS))
def test_bad_source_path(tmp_path, kind):
    missing = tmp_path / "nowhere"
    with pytest.raises(RecordingError) as info:
        IMPORTERS[kind](missing)
    assert str(missing) in str(info.value) and "\n" not in str(info.value)


def test_bad_source_content(tmp_path):
    (tmp_path / "xsens_acc.mat.gz").write_bytes(b"not gzip")
    with pytest.raises(RecordingError, match="xsens_acc.mat.gz"):
        import_imu_tk_xsens(tmp_path)
    bad = tmp_path / "log.csv"
    bad.write_text("Fs,100\nLogging Type,0\nInitialization time,1\nWaiting time,1\nax,ay,az,gx,gy,gz\n1,2,3\n")
    with pytest.raises(RecordingError, match="log.csv"):
        import_mpu6050_tomisuarez(bad)
    with pytest.raises(RecordingError, match="no IMU_1"):
        import_ansfl_quadrotor(tmp_path)


# -------------------------------------------------------------------------------------- shipped data/

def load_make_data():
    spec = importlib.util.spec_from_file_location("make_data", REPO_ROOT / "data" / "make_data.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


make_data = load_make_data()


@needs_shared
@pytest.mark.parametrize("name", sorted(make_data.DATASETS))
def test_shipped_data_regenerates_byte_for_byte(tmp_path, name):
    shipped = REPO_ROOT / "data" / name
    assert shipped.is_dir(), f"{shipped} missing: run python data/make_data.py"
    out = write_recording(make_data.build(name, SHARED), tmp_path / name)
    sensors = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert sensors == sorted(p.name for p in shipped.iterdir() if p.is_dir())
    for sensor in sensors:
        for file in ("data.csv", "sensor.yaml"):
            assert (out / sensor / file).read_bytes() == (shipped / sensor / file).read_bytes(), f"{sensor}/{file}"
    assert (shipped / "SOURCE.md").read_text(encoding="utf-8") == make_data.source_md(name, SHARED)
    for file in make_data.DATASETS[name]["copy"]:
        assert (shipped / file).is_file()
    assert read_recording(shipped).imu_names()  # and it reads back as a recording with IMUs


def test_shipped_data_size_is_reasonable():
    total_bytes = sum(f.stat().st_size for f in (REPO_ROOT / "data").rglob("*") if f.is_file())
    assert total_bytes < 25e6


@needs_shared
def test_sunsided_axes_form_one_frame_with_specific_force():
    """Level, the accelerometer must read +g up (specific force), and the gyro must turn the accelerometer's
    vector as the data do: df/dt = -w x f.  Of the 8 gyro sign choices, the importer's must fit best on the
    full-sphere sweep (a wrong sign on a rotated axis roughly doubles the misfit there)."""
    from scipy.signal import savgol_filter

    from selfcal.io.importers import import_sunsided_mpu6050
    folder = SHARED / "sunsided_mpu6050_hmc5883l_marg"
    level = import_sunsided_mpu6050(folder / "unmoved-with-x-pointing-forward").imu("imu0")
    assert np.mean(level.accel_m_s2[:, 2]) > 9.0
    d = import_sunsided_mpu6050(folder / "full-sphere").imu("imu0", gyro_saturation_allowed=True)  # clips at 250 deg/s
    t = np.arange(d.t_s[0], d.t_s[-1], 0.02)  # the samples arrive in bursts: a uniform grid for the derivative
    f = savgol_filter(np.column_stack([np.interp(t, d.t_s, c) for c in d.accel_m_s2.T]), 15, 2, axis=0)
    w = savgol_filter(np.column_stack([np.interp(t, d.t_s, c) for c in d.gyro_rad_s.T]), 15, 2, axis=0)
    w -= w[:50].mean(axis=0)  # the first 0.5 s are still: the gyro bias (4.5 deg/s on x) out
    df = np.gradient(f, 0.02, axis=0)
    misfit = {signs: float(np.sqrt(np.mean((df + np.cross(w * signs, f)) ** 2)))
              for signs in [(a, b, c) for a in (1, -1) for b in (1, -1) for c in (1, -1)]}
    assert min(misfit, key=misfit.get) == (1, 1, 1)


def test_every_dataset_kind_is_a_command():
    """The CLI lists the kinds without importing numpy (``selfcal --help`` stays light): the list must match."""
    from selfcal.cli.importers import DATASET_KINDS
    assert sorted(DATASET_KINDS) == sorted(IMPORTERS)
