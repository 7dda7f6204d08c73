"""Recording read/write: exact round trip, atomic writes, and one test per class of bad input.

Every RecordingError must be one line naming the file and, where there is one, the 1-based line number.
"""
import io
import os
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from selfcal.io import atomic
from selfcal.io.atomic import atomic_directory, atomic_write_text
from selfcal.io.recording import (ACCEL_COLUMNS, GYRO_COLUMNS, Recording, RecordingError, SensorData, imu_sensor,
                                  read_recording, read_truth, write_recording)

IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
              "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
T0_NS = 1_700_000_000_000_000_001  # odd ns epoch: not representable in float64 (spacing 256 ns there)


def rows(n=5, t0=T0_NS, step=10_000_000):
    return [f"{t0 + i * step},0.001,-0.002,0.003,0.1,-0.2,9.81" for i in range(n)]


def write_csv(tmp_path, header, body, sensor="imu0"):
    """A recording folder with one sensor whose data.csv holds ``header`` and the ``body`` lines."""
    folder = tmp_path / "rec" / sensor
    folder.mkdir(parents=True, exist_ok=True)
    csv = folder / "data.csv"
    text = "\n".join(([header] if header is not None else []) + list(body))
    csv.write_text(text + ("\n" if text else ""))
    return tmp_path / "rec", csv


def read_error(rec, file, line=None) -> str:
    """The RecordingError of read_recording(rec): one line, naming ``file`` (and ``file:line``)."""
    with pytest.raises(RecordingError) as info:
        read_recording(rec)
    msg = str(info.value)
    assert "\n" not in msg
    assert str(file) in msg
    if line is not None:
        assert f"{file}:{line}:" in msg, msg
    return msg


def random_imu(n=200, seed=0):
    rng = np.random.default_rng(seed)
    t_ns = T0_NS + np.cumsum(rng.integers(9_000_000, 11_000_000, n)).astype(np.int64)
    gyro = rng.normal(scale=0.3, size=(n, 3))
    accel = rng.normal(scale=9.8, size=(n, 3))
    # values that a fixed-digit format would not round-trip: tiny, huge, subnormal, negative zero
    special = [1e-300, -0.0, 5e-324, 1.7976931348623157e308, 0.1 + 0.2]
    gyro[:5, 0] = special[:min(n, 5)]
    return t_ns, gyro, accel


# ------------------------------------------------------------------------------------------------ round trip

def test_round_trip_is_exact(tmp_path):
    t_ns, gyro, accel = random_imu()
    temperature = np.linspace(20.0, 25.0, len(t_ns)) + 1e-13
    imu = imu_sensor("imu0", t_ns, gyro, accel, channels={"temperature": (temperature, "degC")},
                     meta={"rate_hz": np.float64(100.0), "T_BS": np.eye(4), "count": np.int64(3), "tag": (1, 2)})
    tracker = SensorData("tracker0", t_ns[::10].copy(), {"x": np.arange(20) / 3.0, "y": -np.arange(20) / 7.0},
                         {"x": "m", "y": "m"})
    rec = Recording(None, {"imu0": imu, "tracker0": tracker})
    truth = {"accel_bias": np.array([0.1, 0.2, 0.3]), "seed": np.int64(7)}
    out = write_recording(rec, tmp_path / "rec", truth=truth)
    assert out == tmp_path / "rec"

    back = read_recording(out)
    assert back.path == out
    assert list(back.sensors) == ["imu0", "tracker0"]  # truth/ is not a sensor
    s = back.sensors["imu0"]
    assert s.t_ns.dtype == np.int64 and np.array_equal(s.t_ns, t_ns)
    assert list(s.values) == [*GYRO_COLUMNS, *ACCEL_COLUMNS, "temperature"]
    for name, v in imu.values.items():
        assert s.values[name].dtype == np.float64
        assert np.array_equal(s.values[name].view(np.int64), v.view(np.int64)), name  # bit for bit (-0.0 too)
    assert s.units["temperature"] == "degC" and s.units["w_RS_S_x"] == "rad s^-1"
    assert s.meta == {"rate_hz": 100.0, "T_BS": np.eye(4).tolist(), "count": 3, "tag": [1, 2]}
    assert np.array_equal(back.sensors["tracker0"].values["x"], tracker.values["x"])
    assert back.sensors["tracker0"].units == {"x": "m", "y": "m"}

    assert back.imu_names() == ["imu0"]
    assert np.array_equal(np.column_stack([s.values[c] for c in GYRO_COLUMNS]), gyro)
    assert np.array_equal(np.column_stack([s.values[c] for c in ACCEL_COLUMNS]), accel)
    # the stored bits round-trip; as a measurement (the estimators' view) a gyro reading 1.8e308 rad/s is refused
    with pytest.raises(RecordingError, match="beyond any sensor's range"):
        back.imu("imu0")
    view = read_recording(write_recording(Recording(None, {"imu0": imu_sensor(
        "imu0", t_ns, np.where(np.abs(gyro) > 1e3, 0.0, gyro), accel + [0.0, 0.0, 9.81],
        channels={"temperature": (temperature, "degC")}, meta={"rate_hz": 100.0})}), tmp_path / "plausible")).imu("imu0")
    assert list(view.channels) == ["temperature"] and view.channel_units == {"temperature": "degC"}
    assert view.rate_hz == 100.0
    assert read_truth(out) == {"accel_bias": [0.1, 0.2, 0.3], "seed": 7}

    # written text is a fixed point: write(read(write(x))) is byte-identical
    write_recording(back, tmp_path / "again")
    for rel in ("imu0/data.csv", "imu0/sensor.yaml", "tracker0/data.csv"):
        assert (tmp_path / "again" / rel).read_bytes() == (out / rel).read_bytes()
    assert (out / "imu0/data.csv").read_text().splitlines()[0] == IMU_HEADER + ",temperature [degC]"


def test_unknown_columns_are_channels(tmp_path):
    header = IMU_HEADER + ",temperature [degC],supply_voltage [V],my weird channel [counts]"
    # a dead (constant) IMU channel is refused by the measurement view: give the gyro its noise
    body = [f"{T0_NS + i * 10_000_000},{0.001 + 1e-5 * i},{-0.002 + 1e-5 * i},{0.003 - 1e-5 * i},{0.1 + 1e-4 * i},"
            f"{-0.2 - 1e-4 * i},{9.81 + 1e-4 * i},{20 + i},3.3,{i}" for i in range(4)]
    rec_dir, _ = write_csv(tmp_path, header, body)
    view = read_recording(rec_dir).imu("imu0")
    assert view.channel_units == {"temperature": "degC", "supply_voltage": "V", "my weird channel": "counts"}
    assert np.array_equal(view.channels["temperature"], [20.0, 21.0, 22.0, 23.0])


def test_non_imu_sensor_and_optional_yaml(tmp_path):
    rec_dir, _ = write_csv(tmp_path, "#timestamp [ns],x [m],y [m]", ["1,0.5,0.25", "2,0.75,1"], sensor="tracker0")
    rec = read_recording(rec_dir)
    assert rec.sensors["tracker0"].meta == {}
    assert rec.imu_names() == []
    with pytest.raises(RecordingError, match="not an IMU"):
        rec.imu("tracker0")
    with pytest.raises(RecordingError, match="no sensor 'imu7'"):
        rec.imu("imu7")


def test_reading_51k_rows_is_fast(tmp_path):
    t_ns, gyro, accel = random_imu(n=51_175, seed=1)
    write_recording(Recording(None, {"imu0": imu_sensor("imu0", t_ns, gyro, accel)}), tmp_path / "rec")
    start = time.process_time()  # CPU time: the machine is shared (other tests, other jobs)
    rec = read_recording(tmp_path / "rec")
    elapsed_s = time.process_time() - start
    assert np.array_equal(rec.sensors["imu0"].t_ns, t_ns)
    assert elapsed_s < 1.0, f"read took {elapsed_s:.2f} s"


# --------------------------------------------------------------------------------------------- bad headers

def test_header_must_start_with_timestamp(tmp_path):
    rec, csv = write_csv(tmp_path, IMU_HEADER.replace("#timestamp [ns]", "time [ns]"), rows())
    assert "#timestamp [ns]" in read_error(rec, csv, 1)


def test_timestamp_unit_must_be_ns(tmp_path):
    rec, csv = write_csv(tmp_path, IMU_HEADER.replace("#timestamp [ns]", "#timestamp [s]"), rows())
    msg = read_error(rec, csv, 1)
    assert "ns" in msg and "'s'" in msg


def test_header_field_without_unit(tmp_path):
    rec, csv = write_csv(tmp_path, IMU_HEADER + ",temperature", [r + ",20" for r in rows()])
    msg = read_error(rec, csv, 1)
    assert "'temperature'" in msg and "name [unit]" in msg


def test_misnamed_imu_column(tmp_path):
    rec, csv = write_csv(tmp_path, IMU_HEADER.replace("w_RS_S_x", "w_RS_S_X"), rows())
    msg = read_error(rec, csv, 1)
    assert "w_RS_S_x [rad s^-1]" in msg and "'w_RS_S_X'" in msg


def test_missing_imu_column(tmp_path):
    header = IMU_HEADER.replace(",a_RS_S_z [m s^-2]", "")
    rec, csv = write_csv(tmp_path, header, [r.rsplit(",", 1)[0] for r in rows()])
    msg = read_error(rec, csv, 1)
    assert "a_RS_S_z" in msg and "missing" in msg


@pytest.mark.parametrize("column, wrong, right", [("w_RS_S_y", "deg s^-1", "rad s^-1"), ("a_RS_S_z", "g", "m s^-2")])
def test_wrong_imu_unit(tmp_path, column, wrong, right):
    rec, csv = write_csv(tmp_path, IMU_HEADER.replace(f"{column} [{right}]", f"{column} [{wrong}]"), rows())
    msg = read_error(rec, csv, 1)
    assert column in msg and f"[{wrong}]" in msg and f"[{right}]" in msg


# ---------------------------------------------------------------------------------------------- bad values

@pytest.mark.parametrize("token, kind", [("nan", "NaN"), ("NaN", "NaN"), ("inf", "inf"), ("-inf", "-inf"),
                                         ("1e999", "inf")])
def test_non_finite_value(tmp_path, token, kind):
    body = rows(6)
    fields = body[3].split(",")
    fields[4] = token  # a_RS_S_x
    body[3] = ",".join(fields)
    rec, csv = write_csv(tmp_path, IMU_HEADER, body)
    msg = read_error(rec, csv, 5)  # header is line 1, body[3] is line 5
    assert f"{kind} in column a_RS_S_x" in msg


def test_non_numeric_value(tmp_path):
    body = rows(6)
    body[1] = body[1].replace(",0.003,", ",abc,")
    body[4] = body[4].replace(",0.003,", ",nan,")  # a later NaN must not hide the earlier error
    rec, csv = write_csv(tmp_path, IMU_HEADER, body)
    msg = read_error(rec, csv, 3)
    assert "'abc'" in msg and "w_RS_S_z" in msg


def test_empty_field(tmp_path):
    body = rows(4)
    body[2] = body[2].replace(",0.1,", ",,")
    rec, csv = write_csv(tmp_path, IMU_HEADER, body)
    assert "a_RS_S_x" in read_error(rec, csv, 4)


def test_non_integer_timestamp(tmp_path):
    body = rows(4)
    body[2] = "1.7e18" + body[2][body[2].index(","):]
    rec, csv = write_csv(tmp_path, IMU_HEADER, body)
    assert "'1.7e18'" in read_error(rec, csv, 4)


def test_truncated_last_line(tmp_path):
    body = rows(8)
    body[-1] = body[-1][:25]  # cut mid-row, as a recorder killed while writing leaves it
    rec, csv = write_csv(tmp_path, IMU_HEADER, body)
    msg = read_error(rec, csv, 9)
    assert "expected 7" in msg and "truncated" in msg


def test_row_with_too_many_fields(tmp_path):
    body = rows(8)
    body[2] += ",1.0"
    rec, csv = write_csv(tmp_path, IMU_HEADER, body)
    assert "8 fields, expected 7" in read_error(rec, csv, 4)


def test_empty_line_inside_data(tmp_path):
    body = rows(5)
    body.insert(2, "")
    rec, csv = write_csv(tmp_path, IMU_HEADER, body)
    assert "empty line" in read_error(rec, csv, 4)


def test_unsorted_timestamps(tmp_path):
    body = rows(8)
    body[4], body[5] = body[5], body[4]  # body[5] (line 6) now before body[4] (line 7)
    rec, csv = write_csv(tmp_path, IMU_HEADER, body)
    msg = read_error(rec, csv, 7)
    assert "earlier" in msg and "line 6" in msg


def test_duplicate_timestamps(tmp_path):
    body = rows(8)
    body[6] = body[5].split(",", 1)[0] + "," + body[6].split(",", 1)[1]
    rec, csv = write_csv(tmp_path, IMU_HEADER, body)
    msg = read_error(rec, csv, 8)
    assert "duplicate" in msg and "line 7" in msg


def test_empty_file(tmp_path):
    rec, csv = write_csv(tmp_path, None, [])
    assert "empty" in read_error(rec, csv)


def test_header_only(tmp_path):
    rec, csv = write_csv(tmp_path, IMU_HEADER, [])
    assert "no data rows" in read_error(rec, csv, 1)


def test_bad_sensor_yaml(tmp_path):
    rec, csv = write_csv(tmp_path, IMU_HEADER, rows())
    bad = csv.parent / "sensor.yaml"
    bad.write_text("rate_hz: 100\nnoise: [1, 2\n")
    with pytest.raises(RecordingError) as info:
        read_recording(rec)
    assert str(bad) in str(info.value) and "\n" not in str(info.value)
    bad.write_text("- just\n- a list\n")
    with pytest.raises(RecordingError, match="mapping"):
        read_recording(rec)


def test_bad_recording_folder(tmp_path):
    for path, words in [(tmp_path / "missing", "no such"), (tmp_path / "rec_file", "not a folder"),
                        (tmp_path / "empty", "no sensor")]:
        if path.name == "rec_file":
            path.write_text("x")
        elif path.name == "empty":
            (path / "scan0").mkdir(parents=True)  # a subfolder without data.csv is not a sensor
        with pytest.raises(RecordingError) as info:
            read_recording(path)
        assert str(path) in str(info.value) and words in str(info.value)


def test_truth_folder_is_not_read(tmp_path):
    rec, _ = write_csv(tmp_path, IMU_HEADER, rows())
    write_csv(tmp_path, "not a header at all", ["garbage"], sensor="truth")
    assert list(read_recording(rec).sensors) == ["imu0"]
    with pytest.raises(RecordingError, match="no ground truth"):
        read_truth(rec)


# ----------------------------------------------------------------------------------------- writing, atomic

def small_recording(n=10):
    t_ns, gyro, accel = random_imu(n)
    return Recording(None, {"imu0": imu_sensor("imu0", t_ns, gyro, accel), "imu1": imu_sensor("imu1", t_ns, gyro, accel)})


def test_write_failing_midway_leaves_nothing(tmp_path, monkeypatch):
    calls = []
    real_write_text = Path.write_text

    def failing_write_text(self, *args, **kwargs):
        calls.append(self)
        if len(calls) == 3:  # imu0 written completely, imu1 not yet
            raise OSError("disk full (simulated)")
        return real_write_text(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", failing_write_text)
    with pytest.raises(OSError, match="disk full"):
        write_recording(small_recording(), tmp_path / "rec")
    assert len(calls) == 3
    assert list(tmp_path.iterdir()) == []  # neither the recording nor its temporary sibling


def test_overwrite_failing_midway_keeps_the_old_recording(tmp_path, monkeypatch):
    write_recording(small_recording(), tmp_path / "rec")
    before = (tmp_path / "rec/imu0/data.csv").read_bytes()

    def fail(*args, **kwargs):
        raise OSError("simulated")

    monkeypatch.setattr(Path, "write_text", fail)
    with pytest.raises(OSError):
        write_recording(small_recording(n=3), tmp_path / "rec", overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]
    assert (tmp_path / "rec/imu0/data.csv").read_bytes() == before


def test_write_refuses_existing_folder_without_overwrite(tmp_path):
    write_recording(small_recording(), tmp_path / "rec")
    with pytest.raises(FileExistsError) as info:
        write_recording(small_recording(n=4), tmp_path / "rec")
    assert str(tmp_path / "rec") in str(info.value)
    assert len(read_recording(tmp_path / "rec").sensors["imu0"].t_ns) == 10
    write_recording(small_recording(n=4), tmp_path / "rec", overwrite=True)
    assert len(read_recording(tmp_path / "rec").sensors["imu0"].t_ns) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]


def test_write_refuses_non_finite_values(tmp_path):
    t_ns, gyro, accel = random_imu(10)
    accel[3, 1] = np.nan
    with pytest.raises(RecordingError, match="a_RS_S_y"):
        write_recording(Recording(None, {"imu0": imu_sensor("imu0", t_ns, gyro, accel)}), tmp_path / "rec")
    assert list(tmp_path.iterdir()) == []


def test_imu_sensor_checks_its_input():
    t_ns, gyro, accel = random_imu(10)
    with pytest.raises(RecordingError, match="accel_m_s2"):
        imu_sensor("imu0", t_ns, gyro, accel[:, :2])
    with pytest.raises(RecordingError, match="strictly increasing"):
        imu_sensor("imu0", t_ns[::-1], gyro, accel)
    with pytest.raises(RecordingError, match="integer"):
        imu_sensor("imu0", t_ns + 0.5, gyro, accel)


def test_atomic_write_text_failure_leaves_no_file(tmp_path, monkeypatch):
    target = tmp_path / "out.yaml"
    atomic_write_text(target, "old: 1\n")

    def fail(src, dst):
        raise OSError("simulated rename failure")

    monkeypatch.setattr(atomic.os, "replace", fail)
    with pytest.raises(OSError, match="simulated"):
        atomic_write_text(target, "new: 2\n")
    assert target.read_text() == "old: 1\n"
    assert [p.name for p in tmp_path.iterdir()] == ["out.yaml"]
    monkeypatch.undo()
    atomic_write_text(tmp_path / "fresh.yaml", "a: 1\n")
    assert yaml.safe_load((tmp_path / "fresh.yaml").read_text()) == {"a": 1}
    assert oct((tmp_path / "fresh.yaml").stat().st_mode & 0o777) != oct(0o600)  # not mkstemp's private mode


def test_atomic_directory_exception_removes_temporary(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_directory(tmp_path / "d") as tmp:
            (tmp / "half.txt").write_text("x")
            assert tmp.parent == tmp_path and tmp.name != "d"
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with atomic_directory(tmp_path / "d") as tmp:
        (tmp / "f.txt").write_text("ok")
    assert (tmp_path / "d/f.txt").read_text() == "ok"
    assert os.listdir(tmp_path) == ["d"]


def test_binary_payloads_are_written_inside_the_atomic_folder(tmp_path):
    frames = np.arange(12.0).reshape(3, 4)
    buffer = io.BytesIO()
    np.save(buffer, frames)
    sensor = SensorData("array0", np.array([1, 2, 3], dtype=np.int64), {"temperature": np.array([20.0, 20.5, 21.0])},
                        {"temperature": "degC"})
    write_recording(Recording(None, {"array0": sensor}), tmp_path / "rec",
                    extra_files={"array0/frames.npy": buffer.getvalue()})
    rec = read_recording(tmp_path / "rec")
    assert rec.sensors["array0"].folder == tmp_path / "rec" / "array0"
    np.testing.assert_array_equal(np.load(rec.sensors["array0"].folder / "frames.npy"), frames)
