"""Regenerate the recordings shipped in ``data/`` from the public datasets in ``../shared/data``.

Usage::

    python data/make_data.py [SOURCE_ROOT]      # default SOURCE_ROOT: <repo>/../shared/data

Each recording is written with :func:`selfcal.io.recording.write_recording` (atomically, replacing the old one),
then its ``SOURCE.md`` (upstream provenance + how it was converted + license) and the upstream license text.
Only permissively licensed datasets are shipped (BSD, MIT, CC BY 4.0).  The output is deterministic:
``tests/test_importers.py`` regenerates every recording and compares it byte for byte with ``data/``.
"""
from __future__ import annotations

import shutil
import sys
from pathlib import Path

DATA_DIR = Path(__file__).resolve().parent
REPO_ROOT = DATA_DIR.parent
DEFAULT_SOURCE_ROOT = REPO_ROOT.parent / "shared" / "data"

if str(REPO_ROOT) not in sys.path:  # runnable as a plain script from a source checkout
    sys.path.insert(0, str(REPO_ROOT))

from selfcal.io.atomic import atomic_write_text  # noqa: E402
from selfcal.io.importers import IMPORTERS  # noqa: E402
from selfcal.io.recording import Recording, RecordingError, write_recording  # noqa: E402

_XSENS_CONVERSION = """\
- Converted with `selfcal import imu-tk-xsens` (`selfcal.io.importers.import_imu_tk_xsens`); regenerate with
  `python data/make_data.py`. One sensor, `imu0` (EuRoC/ASL layout, see the project README).
- Time base: the recorded `t [s]` x 1e9, rounded to int64 ns. The stamps are kept as recorded (jittered: steps
  9.0 .. 10.4 ms, median 10.0 ms; they are multiples of 1 us); rounding produced no duplicate or decreasing stamp.
- Units: nominal SI through the factory transfer function of this unit (the "datasheet" values above):
  accelerometer `a [m s^-2] = (counts - (33123, 33276, 32360)) / (415, 413, 415)`,
  gyroscope `w [rad s^-1] = (counts - (32768, 32466, 32485)) / (4778, 4758, 4766)`.
  The factory misalignment is *not* applied, so the recording still holds this unit's scale, misalignment and
  bias errors relative to that nominal model (what a calibration should find). The numbers are stored in
  `imu0/sensor.yaml` under `raw_counts` (`counts = offset_counts + counts_per_unit * value`).
- `gravity_m_s2: 9.81744` is the local gravity used by the upstream imu_tk test app. Noise densities: std of the
  first 30 s (static) / sqrt(100 Hz), mean over axes; random walks are assumed values (see `noise_source`).
- Floats are written with the shortest repr that reads back to the identical float64.
"""

_XSENS_LICENSE = """\
BSD (IMU-TK by Alberto Pretto; the license is stated in the upstream README, copied here as
`UPSTREAM_README.md`). If you use these data, cite D. Tedaldi, A. Pretto, E. Menegatti, "A Robust and Easy to
Implement Method for IMU Calibration without External Equipments", ICRA 2014.
"""

_MPU_CONVERSION = """\
- Converted with `selfcal import mpu6050-tomisuarez` (`selfcal.io.importers.import_mpu6050_tomisuarez`) from
  `{file}`; regenerate with `python data/make_data.py`. One sensor, `imu0`.
- Time base: none upstream; uniform at the header's `Fs` = 100 Hz from t = 0: `t_ns = i * 10_000_000`.
- Units: nominal SI with the MPU-6050 datasheet sensitivity of the configured ranges and zero offset:
  accelerometer `a [m s^-2] = counts / (16384 / 9.80665)`, gyroscope `w [rad s^-1] = counts / (131 * 180 / pi)`.
  Stored in `imu0/sensor.yaml` under `raw_counts` (`counts = offset_counts + counts_per_unit * value`).
  Under this nominal model the static specific-force norm is about 0.91 g (8.9-9.0 m s^-2), not 1 g: the unit
  has a large z offset (upstream estimate 1840 counts = 0.11 g) and scale errors - what a calibration should find.
- `gravity_m_s2` is standard gravity (the recording site is not stated upstream). Noise densities: std of the
  leading static part (first 30 s) / sqrt(100 Hz), mean over axes; random walks are assumed values.
  The upstream header values (logging type, initialization and waiting times) are kept under `upstream_settings`.
- Floats are written with the shortest repr that reads back to the identical float64.
"""

_MPU_LICENSE = """\
MIT (tomisuarez2/ImuCalibration, Copyright (c) 2025 tomisuarez2); the license text is copied here as
`UPSTREAM_LICENSE.txt` and must accompany copies of these data.
"""

_ANSFL_CONVERSION = """\
- Converted with `selfcal import ansfl-quadrotor` (`selfcal.io.importers.import_ansfl_quadrotor`) from
  `{flight}`; regenerate with `python data/make_data.py`.
- Sensors `imu0..imu3` from `IMU_1..IMU_4.csv`: `Gyr` deg/s -> `w_RS_S_* [rad s^-1]` (x pi/180), `Acc` m/s^2 ->
  `a_RS_S_* [m s^-2]` unchanged, `Euler_X/Y/Z` kept as auxiliary channels `euler_x/y/z [deg]` (on-board filter).
- Time base: the upstream `time` column (s) x 1e9, rounded to int64 ns. Note that it advances by exactly
  0.008333 s per sample (8 333 000 ns, i.e. 120.0048 Hz), not by 1/120 s; it is kept as recorded.
  `rate_hz: 120` in sensor.yaml is the nominal rate. The four IMUs share the identical time base.
- Sensor `reference0` from `GT.csv` (10 Hz, DJI flight log), columns renamed: `distance(meters)` -> `distance [m]`,
  `speed(m/s)` -> `speed [m s^-1]`, `compass_heading(degrees)` -> `compass_heading [deg]`, `pitch [deg]`,
  `roll [deg]`, `height_above_takeoff [m]`, `North/East/Down` -> `north/east/down [m]` (unit from the description
  above). Attitude and heading are the drone's own estimate. `GTExtended.csv` is not converted.
- IMU noise keys: Xsens DOT spec-sheet-class values (not measured: there is no static segment); random walks
  are assumed values (see `noise_source` in each sensor.yaml).
- Floats are written with the shortest repr that reads back to the identical float64.
"""

_ANSFL_LICENSE = """\
Creative Commons Attribution 4.0 International (https://creativecommons.org/licenses/by/4.0/legalcode), as
stated in the upstream README (copied here as `UPSTREAM_README.md`). Attribution: dataset by the Autonomous
Navigation and Sensor Fusion Lab (ANSFL), University of Haifa, repository
`ansfl/Quadrotor-Dead-Reckoning-with-Multiple-Inertial-Sensors`; cite D. Hurwitz, I. Klein, "Quadrotor Dead
Reckoning with Multiple Inertial Sensors", arXiv:2310.13452 (2023). Changes: converted to the recording layout
as described above (units, column names, time base); values otherwise unchanged.
"""

# name -> importer kind, dataset folder, source path inside it, texts, upstream files copied beside SOURCE.md
DATASETS = {
    "xsens_mti_multiposition": {
        "kind": "imu-tk-xsens", "dataset": "imu_tk_xsens_multiposition", "source": ".",
        "conversion": _XSENS_CONVERSION, "license": _XSENS_LICENSE, "copy": ["UPSTREAM_README.md"],
    },
    "mpu6050_multiposition": {
        "kind": "mpu6050-tomisuarez", "dataset": "mpu6050_tedaldi_calib_tomisuarez",
        "source": "example_data_calibration.csv.gz",
        "conversion": _MPU_CONVERSION, "license": _MPU_LICENSE, "copy": ["UPSTREAM_LICENSE.txt"],
    },
    "mpu6050_static": {
        "kind": "mpu6050-tomisuarez", "dataset": "mpu6050_tedaldi_calib_tomisuarez",
        "source": "example_data_tinit_calc.csv.gz",
        "conversion": _MPU_CONVERSION, "license": _MPU_LICENSE, "copy": ["UPSTREAM_LICENSE.txt"],
    },
    "ansfl_quadrotor_straightline_1": {
        "kind": "ansfl-quadrotor", "dataset": "ansfl_quadrotor_4xsensdot_rtk", "source": "StraightLine/path_1",
        "conversion": _ANSFL_CONVERSION, "license": _ANSFL_LICENSE, "copy": ["UPSTREAM_README.md"],
    },
    "ansfl_quadrotor_horizontal_1": {
        "kind": "ansfl-quadrotor", "dataset": "ansfl_quadrotor_4xsensdot_rtk", "source": "Horizontal/path_1",
        "conversion": _ANSFL_CONVERSION, "license": _ANSFL_LICENSE, "copy": ["UPSTREAM_README.md"],
    },
}


def build(name: str, source_root=DEFAULT_SOURCE_ROOT) -> Recording:
    """The in-memory recording ``data/<name>`` is made from (no file written)."""
    spec = DATASETS[name]
    return IMPORTERS[spec["kind"]](Path(source_root) / spec["dataset"] / spec["source"])


def source_md(name: str, source_root=DEFAULT_SOURCE_ROOT) -> str:
    """Upstream SOURCE.md followed by the sections Conversion and License and attribution."""
    spec = DATASETS[name]
    upstream = (Path(source_root) / spec["dataset"] / "SOURCE.md").read_text(encoding="utf-8").rstrip("\n")
    source = spec["source"]
    conversion = spec["conversion"].format(file=source, flight=source)
    return (f"{upstream}\n\n## Conversion\n\nThis folder `data/{name}` is a converted recording made from\n"
            f"`{spec['dataset']}/{source}` (upstream description above).\n\n{conversion}\n"
            f"## License and attribution\n\n{spec['license']}")


def write_dataset(name: str, source_root=DEFAULT_SOURCE_ROOT, out_root=DATA_DIR) -> Path:
    """Write ``out_root/<name>``: the recording, SOURCE.md and the upstream license/README files."""
    spec = DATASETS[name]
    out = write_recording(build(name, source_root), Path(out_root) / name, overwrite=True)
    atomic_write_text(out / "SOURCE.md", source_md(name, source_root))
    for file in spec["copy"]:
        shutil.copyfile(Path(source_root) / spec["dataset"] / file, out / file)
    return out


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) > 1 or (args and args[0] in ("-h", "--help")):
        print(__doc__)
        return 0 if args and args[0] in ("-h", "--help") else 1
    source_root = Path(args[0]) if args else DEFAULT_SOURCE_ROOT
    if not source_root.is_dir():
        print(f"make_data: error: {source_root}: no such folder (pass the shared data root)", file=sys.stderr)
        return 1
    for name in DATASETS:
        try:
            out = write_dataset(name, source_root)
        except (RecordingError, OSError) as err:
            print(f"make_data: error: {' '.join(str(err).split())}", file=sys.stderr)
            return 1
        size_mb = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 1e6
        print(f"wrote {out.relative_to(REPO_ROOT) if out.is_relative_to(REPO_ROOT) else out} ({size_mb:.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
