"""Importers: public IMU datasets (see ``../shared/data/*/SOURCE.md``) turned into in-memory Recordings.

Raw-count datasets are converted to nominal SI units with the vendor (factory/datasheet) transfer function
``value = (counts - offset_counts) / counts_per_unit``; the numbers are kept in sensor.yaml under ``raw_counts``
so that a calibration found in SI units can be converted back to counts.  Writing to disk is
:func:`selfcal.io.recording.write_recording`'s job.
"""
from __future__ import annotations

import gzip
import math
import re
from pathlib import Path

import numpy as np

from selfcal.core.inertial import STANDARD_GRAVITY_M_S2
from selfcal.io.imu_table import counts_to_si, import_imu_table, raw_counts_meta
from selfcal.io.recording import Recording, RecordingError, SensorData, imu_sensor
from selfcal.io.stationing import import_hilti_stationing


# Kalibr's keys: white-noise densities in m s^-2 Hz^-1/2 and rad s^-1 Hz^-1/2, bias random walks in
# m s^-3 Hz^-1/2 and rad s^-2 Hz^-1/2
NOISE_KEYS = ("accelerometer_noise_density", "gyroscope_noise_density",
              "accelerometer_random_walk", "gyroscope_random_walk")


# ----------------------------------------------------------------------------------------------------- helpers

def _require_dir(path) -> Path:
    path = Path(path)
    if not path.exists():
        raise RecordingError(f"{path}: no such dataset folder")
    if not path.is_dir():
        raise RecordingError(f"{path}: not a folder (expected the dataset folder)")
    return path


def _require_file(path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    return path


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _loadtxt(file: Path, n_columns: int, **kwargs) -> np.ndarray:
    """np.loadtxt (reads .gz directly) with the shape checked; errors become one-line RecordingErrors."""
    _require_file(file)
    try:
        table = np.loadtxt(file, ndmin=2, **kwargs)
    except (ValueError, OSError, EOFError) as err:
        raise RecordingError(f"{file}: cannot parse ({_one_line(err)})") from None
    if table.shape[0] == 0 or table.shape[1] != n_columns:
        raise RecordingError(f"{file}: expected {n_columns} columns of data, found shape {table.shape}")
    return table


def _seconds_to_ns(t_s: np.ndarray, file: Path, first_line: int) -> np.ndarray:
    """Timestamps in s -> int64 ns (rounded); refuse instead of repairing if rounding breaks strict order."""
    t_ns = np.round(np.asarray(t_s, dtype=np.float64) * 1e9).astype(np.int64)
    steps = np.diff(t_ns)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0)) + 1
        raise RecordingError(f"{file}:{first_line + i}: time {t_s[i]!r} s does not increase after {t_s[i - 1]!r} s "
                             f"(after rounding to ns: {t_ns[i - 1]} -> {t_ns[i]})")
    return t_ns


def _sig(x: float, digits: int = 3) -> float:
    """``x`` rounded to ``digits`` significant digits: a noise estimate carries no more, and rounding keeps the
    written sensor.yaml identical across numpy versions (the last bits of a std may differ)."""
    return float(f"{x:.{digits}g}")


def _leading_static_samples(gyro: np.ndarray, rate_hz: float, max_s: float = 30.0) -> int:
    """Number of leading samples (at most ``max_s``) before the first 1-s block that is clearly moving.

    A block is moving when its gyro std exceeds 4x the median block std of the first 5 s: white noise gives
    block stds within ~20 % of each other at these rates, hand motion gives 10-100x.
    """
    block = max(int(round(rate_hz)), 2)
    n_max = min(len(gyro), int(round(max_s * rate_hz)))
    stds = [float(np.max(np.std(gyro[i:i + block], axis=0))) for i in range(0, n_max - block + 1, block)]
    if not stds:
        return n_max
    ref = float(np.median(stds[:5]))
    for k, s in enumerate(stds):
        if s > 4.0 * ref:
            return max(k, 1) * block
    return n_max


def _white_noise_density(x: np.ndarray, rate_hz: float) -> float:
    """Kalibr noise density from static samples: mean over the axes of std / sqrt(rate).

    Kalibr's discrete-time sigma is ``density * sqrt(rate)`` (white noise sampled at ``rate``).
    """
    return _sig(float(np.mean(np.std(x, axis=0))) / math.sqrt(rate_hz))


# ------------------------------------------------------------------------------------------------ imu_tk Xsens

XSENS_ACCEL_OFFSET_COUNTS = (33123.0, 33276.0, 32360.0)
XSENS_ACCEL_COUNTS_PER_M_S2 = (415.0, 413.0, 415.0)
XSENS_GYRO_OFFSET_COUNTS = (32768.0, 32466.0, 32485.0)
XSENS_GYRO_COUNTS_PER_RAD_S = (4778.0, 4758.0, 4766.0)
XSENS_RATE_HZ = 100
XSENS_GRAVITY_M_S2 = 9.81744  # local gravity used by the upstream imu_tk test app (apps/test_imu_calib.cpp)


def _counts_axes(offsets, counts_per_unit) -> dict:
    return {axis: {"column": 1 + k, "unit": "counts", "scale": per_unit, "offset": offset}
            for k, (axis, offset, per_unit) in enumerate(zip("xyz", offsets, counts_per_unit))}


XSENS_MAP = {  # imu_tk's own files: whitespace tables "t [s] x y z", one per sensor, sharing their time column
    "files": {"accel": "xsens_acc.mat.gz", "gyro": "xsens_gyro.mat.gz"},
    "time": {"column": 0, "unit": "s"},
    "accel": _counts_axes(XSENS_ACCEL_OFFSET_COUNTS, XSENS_ACCEL_COUNTS_PER_M_S2),
    "gyro": _counts_axes(XSENS_GYRO_OFFSET_COUNTS, XSENS_GYRO_COUNTS_PER_RAD_S),
    "rate_hz": XSENS_RATE_HZ,
}


def import_imu_tk_xsens(src_dir) -> Recording:
    """The IMU-TK reference recording (Xsens MTi, raw ADC counts, multi-position) as sensor ``imu0``.

    Parameters
    ----------
    src_dir : str or Path
        Folder holding ``xsens_acc.mat.gz`` and ``xsens_gyro.mat.gz`` (whitespace ASCII: t [s], x, y, z counts).

    Returns
    -------
    Recording
        ``imu0`` in nominal SI units via the factory scale/offset of this unit (misalignment not applied),
        timestamps = the recorded (jittered) times rounded to ns.

    References
    ----------
    D. Tedaldi, A. Pretto, E. Menegatti, "A Robust and Easy to Implement Method for IMU Calibration without
    External Equipments", ICRA 2014.
    """
    src = _require_dir(src_dir)
    imu = import_imu_table(src, XSENS_MAP, where="imu-tk-xsens map").imu("imu0")
    t_ns, gyro_rad_s, accel_m_s2 = imu.t_ns, imu.gyro_rad_s, imu.accel_m_s2
    n_static = _leading_static_samples(gyro_rad_s, XSENS_RATE_HZ)
    meta = {
        "sensor_type": "imu",
        "model": "Xsens MTi",
        "rate_hz": XSENS_RATE_HZ,
        "gravity_m_s2": XSENS_GRAVITY_M_S2,
        "accelerometer_noise_density": _white_noise_density(accel_m_s2[:n_static], XSENS_RATE_HZ),
        "gyroscope_noise_density": _white_noise_density(gyro_rad_s[:n_static], XSENS_RATE_HZ),
        "accelerometer_random_walk": 1.0e-3,
        "gyroscope_random_walk": 1.0e-4,
        "noise_source": (f"noise densities: std over the first {n_static / XSENS_RATE_HZ:g} s (static) / "
                         "sqrt(rate_hz), mean over axes; random walks: assumed typical MEMS values, not measured"),
        "raw_counts": raw_counts_meta(XSENS_ACCEL_OFFSET_COUNTS, XSENS_ACCEL_COUNTS_PER_M_S2,
                                  XSENS_GYRO_OFFSET_COUNTS, XSENS_GYRO_COUNTS_PER_RAD_S),
        "raw_counts_source": "Xsens factory ('datasheet') scale and offsets of this unit, from the original "
                             "MATLAB script of Tedaldi et al.; factory misalignment not applied",
        "source": "imu_tk_xsens_multiposition",
    }
    return Recording(path=None, sensors={"imu0": imu_sensor("imu0", t_ns, gyro_rad_s, accel_m_s2, meta=meta)})


# ------------------------------------------------------------------------------------------ MPU-6050 tomisuarez

MPU6050_ACCEL_COUNTS_PER_G = 16384.0  # +-2 g full scale (datasheet, and the upstream test script)
MPU6050_GYRO_COUNTS_PER_DEG_S = 131.0  # +-250 deg/s full scale
MPU6050_ACCEL_COUNTS_PER_M_S2 = MPU6050_ACCEL_COUNTS_PER_G / STANDARD_GRAVITY_M_S2
MPU6050_GYRO_COUNTS_PER_RAD_S = MPU6050_GYRO_COUNTS_PER_DEG_S * 180.0 / math.pi
_MPU_HEADER = ("Fs", "Logging Type", "Initialization time", "Waiting time")
_MPU_COLUMNS = "ax,ay,az,gx,gy,gz"


def _read_mpu_header(file: Path) -> dict:
    try:
        with gzip.open(file, "rt", encoding="utf-8") if file.suffix == ".gz" else open(file, encoding="utf-8") as f:
            lines = [f.readline().strip() for _ in range(5)]
    except (OSError, EOFError, UnicodeDecodeError) as err:
        raise RecordingError(f"{file}: cannot read ({_one_line(err)})") from None
    settings = {}
    for k, (key, line) in enumerate(zip(_MPU_HEADER, lines), start=1):
        parts = line.split(",")
        if len(parts) != 2 or parts[0].strip() != key:
            raise RecordingError(f"{file}:{k}: expected '{key},<value>', found {line!r}")
        try:
            settings[key] = float(parts[1])
        except ValueError:
            raise RecordingError(f"{file}:{k}: {key} value {parts[1]!r} is not a number") from None
    if lines[4].replace(" ", "") != _MPU_COLUMNS:
        raise RecordingError(f"{file}:5: expected column header {_MPU_COLUMNS!r}, found {lines[4]!r}")
    if not settings["Fs"] > 0 or 1e9 % settings["Fs"] != 0:
        raise RecordingError(f"{file}:1: sample rate Fs={settings['Fs']:g} Hz is not a whole number of ns per sample")
    return settings


def import_mpu6050_tomisuarez(csv_gz_file) -> Recording:
    """An MPU-6050 raw-count log of tomisuarez2/ImuCalibration as sensor ``imu0``.

    Parameters
    ----------
    csv_gz_file : str or Path
        A ``.csv`` or ``.csv.gz`` file: 5 header lines (Fs, Logging Type, Initialization time, Waiting time,
        column names), then ``ax,ay,az,gx,gy,gz`` integer counts.

    Returns
    -------
    Recording
        ``imu0`` in nominal SI units (16384 counts per g with g = 9.80665 m/s^2, 131 counts per deg/s, zero
        offsets).  No timestamps upstream: uniform at Fs from t = 0 (``t_ns = i * 1e9 / Fs``).
    """
    file = _require_file(csv_gz_file)
    settings = _read_mpu_header(file)
    counts = _loadtxt(file, 6, delimiter=",", skiprows=5)
    rate_hz = settings["Fs"]
    step_ns = int(1e9 // rate_hz)
    t_ns = np.arange(len(counts), dtype=np.int64) * step_ns
    zero = (0.0, 0.0, 0.0)
    accel_per_unit = (MPU6050_ACCEL_COUNTS_PER_M_S2,) * 3
    gyro_per_unit = (MPU6050_GYRO_COUNTS_PER_RAD_S,) * 3
    accel_m_s2 = counts_to_si(counts[:, :3], zero, accel_per_unit)
    gyro_rad_s = counts_to_si(counts[:, 3:], zero, gyro_per_unit)
    n_static = _leading_static_samples(gyro_rad_s, rate_hz)
    stem = file.name.removesuffix(".gz").removesuffix(".csv")
    meta = {
        "sensor_type": "imu",
        "model": "InvenSense MPU-6050 (accel +-2 g, gyro +-250 deg/s, DLPF 0)",
        "rate_hz": int(rate_hz) if rate_hz.is_integer() else rate_hz,
        "gravity_m_s2": STANDARD_GRAVITY_M_S2,
        "gravity_source": "standard gravity: the recording site is not stated upstream",
        "accelerometer_noise_density": _white_noise_density(accel_m_s2[:n_static], rate_hz),
        "gyroscope_noise_density": _white_noise_density(gyro_rad_s[:n_static], rate_hz),
        "accelerometer_random_walk": 1.0e-3,
        "gyroscope_random_walk": 1.0e-4,
        "noise_source": (f"noise densities: std over the first {n_static / rate_hz:g} s (static) / "
                         "sqrt(rate_hz), mean over axes; random walks: assumed typical MEMS values, not measured"),
        "raw_counts": raw_counts_meta(zero, accel_per_unit, zero, gyro_per_unit),
        "raw_counts_source": "MPU-6050 datasheet nominal sensitivity (16384 LSB/g, 131 LSB/(deg/s)), zero offset",
        "upstream_settings": {"logging_type": int(settings["Logging Type"]),
                              "initialization_time_s": settings["Initialization time"],
                              "waiting_time_s": settings["Waiting time"]},
        "timestamps": "none upstream: uniform at rate_hz from t = 0",
        "source": f"mpu6050_tedaldi_calib_tomisuarez/{stem}",
    }
    return Recording(path=None, sensors={"imu0": imu_sensor("imu0", t_ns, gyro_rad_s, accel_m_s2, meta=meta)})


# ---------------------------------------------------------------------------------------------- ANSFL quadrotor

ANSFL_IMU_COLUMNS = ("time", "Euler_X", "Euler_Y", "Euler_Z", "Acc_X", "Acc_Y", "Acc_Z", "Gyr_X", "Gyr_Y", "Gyr_Z")
ANSFL_RATE_HZ = 120
ANSFL_GT_RATE_HZ = 10
# white noise: Xsens DOT / MTi-1 class spec sheet values (accel 120 ug/sqrt(Hz), gyro 0.007 deg/s/sqrt(Hz))
XSENS_DOT_ACCEL_NOISE_DENSITY = 120e-6 * STANDARD_GRAVITY_M_S2
XSENS_DOT_GYRO_NOISE_DENSITY = math.radians(0.007)
# header units of GT.csv -> recording units; columns without a unit in the header get theirs from SOURCE.md
_UNIT_WORDS = {"meters": "m", "m": "m", "m/s": "m s^-1", "degrees": "deg", "millisecond": "ms", "s": "s"}
_GT_UNITLESS = {"north": "m", "east": "m", "down": "m"}


def _read_csv_header(file: Path) -> list[str]:
    try:
        with gzip.open(file, "rt", encoding="utf-8") as f:
            return [h.strip() for h in f.readline().strip().split(",")]
    except (OSError, EOFError, UnicodeDecodeError) as err:
        raise RecordingError(f"{file}: cannot read ({_one_line(err)})") from None


def sanitize_column(header_field: str, file: Path, unitless: dict | None = None) -> tuple[str, str]:
    """``'speed(m/s)'`` -> ``('speed', 'm s^-1')``: lowercase name without parentheses, unit as in recordings."""
    m = re.fullmatch(r"\s*([^()]+?)\s*(?:\(([^()]*)\))?\s*", header_field)
    if m is None:
        raise RecordingError(f"{file}:1: cannot read column name {header_field!r}")
    name = re.sub(r"[^0-9a-z]+", "_", m.group(1).lower()).strip("_")
    unit_word = m.group(2)
    if unit_word is None:
        unit = (unitless or {}).get(name)
        if unit is None:
            raise RecordingError(f"{file}:1: column {header_field!r} has no unit and none is known for it")
    else:
        unit = _UNIT_WORDS.get(unit_word.strip().lower())
        if unit is None:
            raise RecordingError(f"{file}:1: unknown unit {unit_word!r} in column {header_field!r}")
    return name, unit


def import_ansfl_quadrotor(path_dir) -> Recording:
    """One ANSFL quadrotor flight: four Xsens DOT IMUs (``imu0..imu3``) and the RTK flight log (``reference0``).

    Parameters
    ----------
    path_dir : str or Path
        A path folder such as ``.../StraightLine/path_1`` with ``IMU_1..4.csv.gz`` and ``GT.csv.gz``.

    Returns
    -------
    Recording
        IMUs: gyro deg/s -> rad/s, accel m/s^2 as recorded, the on-board Euler angles kept as channels
        ``euler_x/y/z [deg]``; time s -> ns.  ``reference0``: the GT.csv columns (distance, speed, heading,
        pitch, roll, height, north/east/down) with sanitized names.

    References
    ----------
    D. Hurwitz, I. Klein, "Quadrotor Dead Reckoning with Multiple Inertial Sensors", arXiv:2310.13452, 2023.
    """
    src = _require_dir(path_dir)
    flight = f"{src.parent.name}/{src.name}"
    imu_files = [src / f"IMU_{k}.csv.gz" for k in range(1, 5) if (src / f"IMU_{k}.csv.gz").exists()]
    if not imu_files:
        raise RecordingError(f"{src}: no IMU_1.csv.gz .. IMU_4.csv.gz in this folder")
    sensors: dict[str, SensorData] = {}
    for file in imu_files:
        header = _read_csv_header(file)
        if tuple(header) != ANSFL_IMU_COLUMNS:
            raise RecordingError(f"{file}:1: expected columns {','.join(ANSFL_IMU_COLUMNS)}, found {','.join(header)}")
        table = _loadtxt(file, len(ANSFL_IMU_COLUMNS), delimiter=",", skiprows=1)
        name = f"imu{int(file.name[4]) - 1}"
        meta = {
            "sensor_type": "imu",
            "model": "Xsens DOT",
            "rate_hz": ANSFL_RATE_HZ,
            "accelerometer_noise_density": _sig(XSENS_DOT_ACCEL_NOISE_DENSITY),
            "gyroscope_noise_density": _sig(XSENS_DOT_GYRO_NOISE_DENSITY),
            "accelerometer_random_walk": 2.0e-4,
            "gyroscope_random_walk": 2.0e-5,
            "noise_source": ("noise densities: Xsens DOT / MTi-1 class spec sheet (accel 120 ug Hz^-1/2, gyro "
                             "0.007 deg s^-1 Hz^-1/2), not measured (no static data); random walks: assumed"),
            "channels": "euler_x/y/z: orientation from the Xsens on-board filter (magnetometer-based yaw)",
            "source": f"ansfl_quadrotor_4xsensdot_rtk/{flight}/{file.name.removesuffix('.gz')}",
        }
        channels = {f"euler_{axis}": (table[:, 1 + i], "deg") for i, axis in enumerate("xyz")}
        sensors[name] = imu_sensor(name, _seconds_to_ns(table[:, 0], file, first_line=2),
                                   np.deg2rad(table[:, 7:10]), table[:, 4:7], channels=channels, meta=meta)

    gt_file = src / "GT.csv.gz"
    header = _read_csv_header(_require_file(gt_file))
    if header[0].lower() != "time":
        raise RecordingError(f"{gt_file}:1: first column must be time (s), found {header[0]!r}")
    columns = [sanitize_column(h, gt_file, _GT_UNITLESS) for h in header[1:]]
    table = _loadtxt(gt_file, len(header), delimiter=",", skiprows=1)
    names = [n for n, _ in columns]
    if len(set(names)) != len(names):
        raise RecordingError(f"{gt_file}:1: column names collide after sanitizing: {', '.join(names)}")
    sensors["reference0"] = SensorData(
        name="reference0",
        t_ns=_seconds_to_ns(table[:, 0], gt_file, first_line=2),
        values={n: table[:, j + 1].copy() for j, n in enumerate(names)},
        units=dict(columns),
        meta={
            "sensor_type": "gnss_reference",
            "model": "DJI Phantom 4 RTK flight log",
            "rate_hz": ANSFL_GT_RATE_HZ,
            "frame": "north/east/down in m relative to the first sample of the flight; pitch/roll/"
                     "compass_heading are the drone's own attitude estimate, not an independent reference",
            "source": f"ansfl_quadrotor_4xsensdot_rtk/{flight}/GT.csv",
        },
    )
    return Recording(path=None, sensors=sensors)


# ------------------------------------------------------------------------------------ sunsided MPU-6050 (EUPL)

def import_sunsided_mpu6050(scenario_dir) -> Recording:
    """One scenario of sunsided/sensor-fusion set 2 (MPU-6050 with its temperature) as sensor ``imu0``.

    Parameters
    ----------
    scenario_dir : str or Path
        A scenario folder holding ``mpu6050.csv.gz`` (``sec, acc_*_g, gyro_*_dps, temp_C``).

    Returns
    -------
    Recording
        ``imu0`` in SI units (g -> 9.80665 m s^-2, deg/s -> rad/s) with the channel ``temperature [degC]``.
        Upstream's accelerometer reads -1 g on the axis pointing up (set-2 README: the gravity vector, not the
        specific force), so it is negated.  Its gyro x counts clockwise (README) and so does its y: of the eight
        sign choices, only x and y negated make the gyro turn the accelerometer's vector as the data do
        (``df/dt = -w x f``, checked on the full-sphere sweep by ``tests/test_importers.py``).  EUPL-1.2
        data: read in place, never copied into ``data/``.
    """
    folder = _require_dir(scenario_dir)
    file = folder / "mpu6050.csv.gz"
    table = _loadtxt(file, 8, delimiter=",", skiprows=1)
    t_ns = _seconds_to_ns(table[:, 0], file, first_line=2)
    accel_m_s2 = -table[:, 1:4] * STANDARD_GRAVITY_M_S2
    gyro_rad_s = np.radians(table[:, 4:7]) * np.array([-1.0, -1.0, 1.0])
    # mean rate: the samples arrive in bursts (median spacing 2 ms, gaps up to 70 ms), ~99 Hz on average
    rate_hz = (len(t_ns) - 1) * 1e9 / float(t_ns[-1] - t_ns[0])
    n_static = _leading_static_samples(gyro_rad_s, rate_hz)
    meta = {
        "sensor_type": "imu",
        "model": "InvenSense MPU-6050 breakout (sunsided/sensor-fusion set 2)",
        "rate_hz": _sig(rate_hz),
        "gravity_m_s2": STANDARD_GRAVITY_M_S2,
        "accelerometer_noise_density": _white_noise_density(accel_m_s2[:n_static], rate_hz),
        "gyroscope_noise_density": _white_noise_density(gyro_rad_s[:n_static], rate_hz),
        "accelerometer_random_walk": 1.0e-3,
        "gyroscope_random_walk": 1.0e-4,
        "noise_source": (f"noise densities: std over the first {n_static / rate_hz:.3g} s / sqrt(rate_hz); "
                         "random walks: assumed typical MEMS values, not measured"),
        "axes": "accelerometer negated (upstream reports gravity, -1 g up); gyro x and y negated (clockwise-positive "
                "upstream): one right-handed frame, x forward, y left, z up",
        "source": f"sunsided_mpu6050_hmc5883l_marg/{folder.name}",
    }
    channels = {"temperature": (table[:, 7], "degC")}
    return Recording(path=None, sensors={"imu0": imu_sensor("imu0", t_ns, gyro_rad_s, accel_m_s2, channels, meta)})


# ---------------------------------------------------------------------------------- ADIS16405 (CC BY-NC-SA)

def import_adis16405_static(npz_file) -> Recording:
    """One 2.78 h static run of imudata (SMAC-Group) as sensor ``imu0``; read in place, never shipped.

    The npz holds int16 counts with their LSBs (gyro 0.05 deg/s, accel 3.33 mg); no timestamps upstream:
    uniform 100 Hz from t = 0.
    """
    file = _require_file(npz_file)
    try:
        with np.load(file) as z:
            gyro = z["gyro_counts"] * float(z["gyro_lsb_deg_s"])
            accel = z["acc_counts"] * float(z["acc_lsb_g"])
            rate_hz = float(z["rate_hz"])
    except (OSError, KeyError, ValueError) as err:
        raise RecordingError(f"{file}: not an ADIS16405 npz ({_one_line(err)})") from None
    t_ns = np.arange(len(gyro), dtype=np.int64) * int(round(1e9 / rate_hz))
    meta = {"sensor_type": "imu", "model": "Analog Devices ADIS16405", "rate_hz": rate_hz,
            "gravity_m_s2": STANDARD_GRAVITY_M_S2, "timestamps": "none upstream: uniform at rate_hz from t = 0",
            "source": f"imudata_adis16405_static/{file.name}"}
    return Recording(path=None, sensors={"imu0": imu_sensor("imu0", t_ns, np.radians(gyro),
                                                            accel * STANDARD_GRAVITY_M_S2, meta=meta)})


SPHERECALIB_QC_SPEC = {  # docs/qc_specs/spherecalib_lidar.yaml: the detection that finds the ball in these rooms
    "spheres": {"radius_bounds_m": [0.2, 0.45], "ransac_threshold_m": 0.025, "evaluation_gate_m": 0.04,
                "min_points": 30},
    "planes": {"threshold_m": 0.03, "min_points": 1000, "remove_for_detection": 4, "evaluate": 1},
    "detection": {"voxel_m": 0, "normal_radius_m": 0.2, "dbscan_eps_m": 0.15, "dbscan_min_points": 10},
    "seed": 0}


def import_spherecalib_lidar(src_dir) -> Recording:
    """The SphereCalib LiDAR scans (an inflatable ball of about 0.3 m radius in 8 scenes) as sensor ``lidar0``.

    Parameters
    ----------
    src_dir : str or Path
        Folder holding ``L1_S1.xyz.gz`` ... (gzip of ASCII x y z in m, the scanner's frame).

    Returns
    -------
    Recording
        ``lidar0``: one row per scene, the upstream files copied unchanged as ``<timestamp>.xyz.gz``.  The scans
        carry no time: the timestamps (1 s apart) only order the scenes (``timestamps_are_scene_order``).
    """
    src = _require_dir(src_dir)
    files = sorted(src.glob("L1_S*.xyz.gz"), key=lambda f: int(f.name[4:].split(".")[0]))
    if not files:
        raise RecordingError(f"{src}: no L1_S<i>.xyz.gz scan files")
    t_ns = np.arange(1, len(files) + 1, dtype=np.int64) * 1_000_000_000
    meta = {"sensor_type": "lidar", "sphere_radius_m": 0.3, "file_pattern": "{timestamp}.xyz.gz",
            "timestamps_are_scene_order": True, "qc_spec": SPHERECALIB_QC_SPEC,
            "source": f"spherecalib_lidar_2cam_sphere/{files[0].name} .. {files[-1].name}",
            "scenes": [f.name for f in files]}
    sensor = SensorData("lidar0", t_ns, {}, {}, meta)
    return Recording(path=None, sensors={"lidar0": sensor},
                     payloads={f"lidar0/{t}.xyz.gz": f.read_bytes() for t, f in zip(t_ns, files)})


IMPORTERS = {
    "spherecalib-lidar": import_spherecalib_lidar,
    "hilti-stationing": import_hilti_stationing,
    "adis16405-static": import_adis16405_static,
    "sunsided-mpu6050": import_sunsided_mpu6050,
    "imu-tk-xsens": import_imu_tk_xsens,
    "mpu6050-tomisuarez": import_mpu6050_tomisuarez,
    "ansfl-quadrotor": import_ansfl_quadrotor,
}
