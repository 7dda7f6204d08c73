"""``selfcal import imu-table``: an IMU from text tables through a YAML column/unit map.

The tables are written here from a simulated IMU in the units a user's logger would use (ms, deg/s, g, raw
counts); importing must give back the simulated SI samples (to the last bit or two of the unit conversion) at
the exact nanosecond, and every map mistake must be refused in one line naming the map and the key.
"""
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from selfcal.cli.main import main
from selfcal.io.importers import XSENS_MAP, import_imu_tk_xsens
from selfcal.io.imu_table import import_imu_table, read_imu_map
from selfcal.io.recording import RecordingError, read_recording
from selfcal.sim.imu import ImuScenario
from selfcal.sim.trajectories import MultiPositionTrajectory
from shared_data import SHARED_DATA

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = SHARED_DATA
G = 9.80665
DEG = math.pi / 180.0
# a float64 conversion x * c or x / c is correctly rounded; the text written here is the shortest repr of the
# converted value, so two roundings separate the imported number from the simulated one: <= 2 ulp (2.2e-16 rel)
TWO_ULP = 4.5e-16


@pytest.fixture(scope="module")
def imu():
    trajectory = MultiPositionTrajectory(n_poses=3, static_s=1.0, move_s=1.0, initial_static_s=10.0, seed=1)
    return ImuScenario(trajectory, rate_hz=100.0).perturbed_measurements(2).imu("imu0")


def write_map(path: Path, spec: dict) -> Path:
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def csv_map(**changes) -> dict:
    spec = {"delimiter": ",", "header": True, "skip_rows": 1,
            "time": {"column": "time_s", "unit": "s"},
            "gyro": {a: {"column": f"g{a}_dps", "unit": "deg/s"} for a in "xyz"},
            "accel": {a: {"column": f"a{a}_g", "unit": "g"} for a in "xyz"}}
    spec.update(changes)
    return spec


@pytest.fixture
def logger_csv(tmp_path, imu):
    """A logger's CSV: a comment line, a header, epoch time in s with 9 decimals, gyro deg/s, accel in g."""
    rows = [f"{t // 10**9}.{t % 10**9:09d},{w[0] / DEG!r},{w[1] / DEG!r},{w[2] / DEG!r},"
            f"{a[0] / G!r},{a[1] / G!r},{a[2] / G!r},21.5"
            for t, w, a in zip(imu.t_ns.tolist(), imu.gyro_rad_s.tolist(), imu.accel_m_s2.tolist())]
    file = tmp_path / "log.csv"
    file.write_text("\n".join(["logger v1.2, unit 7", "time_s,gx_dps,gy_dps,gz_dps,ax_g,ay_g,az_g,temp_c", *rows])
                    + "\n")
    return file


def test_csv_with_header_in_deg_s_and_g(tmp_path, imu, logger_csv, capsys):
    out = tmp_path / "rec"
    map_file = write_map(tmp_path / "map.yaml", csv_map(rate_hz=100, noise={"gyroscope_noise_density": 1.7e-4}))
    assert main(["import", "imu-table", str(logger_csv), str(out), "--map", str(map_file)]) == 0
    got = read_recording(out).imu("imu0")
    # epoch seconds with 9 decimals: float64 would miss them by up to 119 ns (238 ns spacing at 1.7e9 s)
    assert np.array_equal(got.t_ns, imu.t_ns)
    np.testing.assert_allclose(got.gyro_rad_s, imu.gyro_rad_s, rtol=TWO_ULP, atol=0)
    np.testing.assert_allclose(got.accel_m_s2, imu.accel_m_s2, rtol=TWO_ULP, atol=0)
    assert got.meta["rate_hz"] == 100 and got.meta["gyroscope_noise_density"] == 1.7e-4
    assert "raw_counts" not in got.meta


def test_two_whitespace_files_in_counts_as_imu_tk_writes_them(tmp_path, imu):
    """imu_tk's layout: acc and gyro files, 't x y z' without header, time in s; here raw counts, the gyro's
    scale given per deg/s (131 LSB per deg/s, as an MPU-6050 datasheet states it)."""
    accel_counts = np.round(imu.accel_m_s2 / G * 16384.0) + [12.0, -7.0, 30.0]  # 16384 LSB/g, offsets
    gyro_counts = np.round(imu.gyro_rad_s / DEG * 131.0) + [-3.0, 5.0, 1.0]
    t_s = (imu.t_ns - imu.t_ns[0]) / 1e9
    np.savetxt(tmp_path / "acc.txt", np.column_stack([t_s, accel_counts]), fmt="%.6f %d %d %d")
    np.savetxt(tmp_path / "gyro.txt", np.column_stack([t_s, gyro_counts]), fmt="%.6f %d %d %d")
    spec = {"files": {"accel": "acc.txt", "gyro": "gyro.txt"}, "time": {"column": 0, "unit": "s"},
            "accel": {a: {"column": k + 1, "unit": "counts", "scale": 16384.0, "per": "g",
                          "offset": [12.0, -7.0, 30.0][k]} for k, a in enumerate("xyz")},
            "gyro": {a: {"column": k + 1, "unit": "counts", "scale": 131.0, "per": "deg/s",
                         "offset": [-3.0, 5.0, 1.0][k]} for k, a in enumerate("xyz")}}
    rec = import_imu_table(tmp_path, read_imu_map(write_map(tmp_path / "map.yaml", spec)))
    got = rec.imu("imu0")
    assert np.array_equal(got.t_ns, imu.t_ns - imu.t_ns[0])  # 10 ms steps: exact in 6 decimals
    # quantisation: half an LSB, i.e. 0.5 / 16384 g and 0.5 / 131 deg/s
    assert np.max(np.abs(got.accel_m_s2 - imu.accel_m_s2)) <= 0.5 / 16384.0 * G * (1 + 1e-12)
    assert np.max(np.abs(got.gyro_rad_s - imu.gyro_rad_s)) <= 0.5 / 131.0 * DEG * (1 + 1e-12)
    raw = got.meta["raw_counts"]
    assert raw["accelerometer"]["counts_per_unit"] == pytest.approx([16384.0 / G] * 3, rel=1e-15)
    assert raw["gyroscope"]["counts_per_unit"] == pytest.approx([131.0 / DEG] * 3, rel=1e-15)
    # the stored transfer function gives the counts back: counts = offset + counts_per_unit * value
    counts = np.asarray(raw["gyroscope"]["offset_counts"]) + np.asarray(raw["gyroscope"]["counts_per_unit"]) * \
        got.gyro_rad_s
    np.testing.assert_allclose(counts, gyro_counts, atol=1e-8)
    assert got.meta["rate_hz"] == 100.0  # from the median step


def test_the_documented_imu_tk_map_is_the_one_the_xsens_importer_uses():
    assert read_imu_map(REPO_ROOT / "docs" / "import_maps" / "imu_tk_xsens.yaml") == XSENS_MAP


@pytest.mark.skipif(not (SHARED / "imu_tk_xsens_multiposition").is_dir(), reason=f"no public data at {SHARED}")
def test_imu_table_on_imu_tk_files_equals_the_xsens_importer():
    source = SHARED / "imu_tk_xsens_multiposition"
    table = import_imu_table(source, read_imu_map(REPO_ROOT / "docs" / "import_maps" / "imu_tk_xsens.yaml"))
    xsens = import_imu_tk_xsens(source)
    a, b = table.sensors["imu0"], xsens.sensors["imu0"]
    assert np.array_equal(a.t_ns, b.t_ns)
    for column in b.values:
        assert np.array_equal(a.values[column], b.values[column]), column
    assert a.meta["raw_counts"] == b.meta["raw_counts"]


# ------------------------------------------------------------------------------------------- map mistakes

@pytest.mark.parametrize("change, words", [
    ({"gyro": {"x": {"column": "gx_dps", "unit": "dps"}, "y": {"column": "gy_dps", "unit": "deg/s"},
               "z": {"column": "gz_dps", "unit": "deg/s"}}}, ["gyro.x", "unknown unit 'dps'", "deg/s"]),
    ({"time": {"column": "time_s", "unit": "sec"}}, ["time", "unknown unit 'sec'", "ms"]),
    ({"delimeter": ","}, ["unknown key 'delimeter'"]),
    ({"accel": {"x": {"column": "ax_g", "unit": "counts"}, "y": {"column": "ay_g", "unit": "g"},
                "z": {"column": "az_g", "unit": "g"}}}, ["accel.x", "needs 'scale'"]),
    ({"header": False}, ["is a name but the map says header: false"]),
    ({"accel": {"x": {"column": "ax_g", "unit": "g"}}}, ["accel must map x, y and z"]),
])
def test_bad_map_is_refused_in_one_line(tmp_path, logger_csv, capsys, change, words):
    spec = csv_map(**change)
    map_file = write_map(tmp_path / "map.yaml", spec)
    assert main(["import", "imu-table", str(logger_csv), str(tmp_path / "o"), "--map", str(map_file)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(map_file) in err, err
    for w in words:
        assert w in err, err
    assert not (tmp_path / "o").exists()


def test_missing_column_names_the_file_and_its_columns(tmp_path, logger_csv):
    spec = csv_map()
    spec["gyro"]["z"]["column"] = "gz"
    with pytest.raises(RecordingError) as info:
        import_imu_table(logger_csv, spec)
    msg = str(info.value)
    assert f"{logger_csv}:2" in msg and "gyro.z" in msg and "no column 'gz'" in msg and "gz_dps" in msg

    spec = csv_map(header=False, time={"column": 0, "unit": "s"},
                   gyro={a: {"column": k + 1, "unit": "deg/s"} for k, a in enumerate("xyz")},
                   accel={a: {"column": k + 4, "unit": "g"} for k, a in enumerate("xy")} | {"z": {"column": 9,
                                                                                              "unit": "g"}})
    spec["skip_rows"] = 2
    with pytest.raises(RecordingError, match=r"accel.z: column 9 does not exist \(8 columns"):
        import_imu_table(logger_csv, spec)


def test_wrong_unit_in_the_map_is_caught_by_physics(tmp_path, logger_csv):
    """A map that calls g 'm/s^2': the recording's sanity check refuses it at import, saying what to do."""
    spec = csv_map(accel={a: {"column": f"a{a}_g", "unit": "m/s^2"} for a in "xyz"})
    with pytest.raises(RecordingError, match="9.80665"):
        import_imu_table(logger_csv, spec).imu("imu0")


def test_files_whose_times_differ_are_refused(tmp_path):
    t = np.arange(200) * 0.01
    np.savetxt(tmp_path / "acc.txt", np.column_stack([t, np.zeros(200), np.zeros(200), np.full(200, 9.81)]))
    np.savetxt(tmp_path / "gyro.txt", np.column_stack([t + 0.001, np.zeros((200, 3))]))
    spec = {"files": {"accel": "acc.txt", "gyro": "gyro.txt"}, "time": {"column": 0, "unit": "s"},
            "accel": {a: {"column": k + 1, "unit": "m/s^2"} for k, a in enumerate("xyz")},
            "gyro": {a: {"column": k + 1, "unit": "rad/s"} for k, a in enumerate("xyz")}}
    with pytest.raises(RecordingError, match="gyro.txt: time column differs from acc.txt"):
        import_imu_table(tmp_path, spec)
