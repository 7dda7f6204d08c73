"""Append-safe recorder: line-by-line flush, SIGKILL loses at most the last partial line, restart appends."""
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from selfcal.cli.main import main
from selfcal.io.recorder import Recorder, record_stream
from selfcal.io.recording import RecordingError, read_recording, write_recording
from selfcal.io.streams import replay

from test_streams import small_recording

REPO = Path(__file__).resolve().parents[1]


def test_recorded_samples_read_back_identically(tmp_path):
    rec = small_recording()
    counts = record_stream(replay(rec), tmp_path / "rec")
    back = read_recording(tmp_path / "rec")
    assert set(back.sensors) == set(rec.sensors)
    for name, s in rec.sensors.items():
        assert counts[name]["written"] == s.t_ns.size
        np.testing.assert_array_equal(back.sensors[name].t_ns, s.t_ns)
        for col, v in s.values.items():
            np.testing.assert_array_equal(back.sensors[name].values[col], v)  # repr floats: exact
        assert back.sensors[name].units == s.units
    assert back.sensors["imu0"].meta["sensor_type"] == "imu"
    assert back.sensors["incl0"].meta["sensor_type"] == "inclinometer"


def test_restart_appends_cuts_a_partial_line_and_keeps_timestamps_increasing(tmp_path):
    folder = tmp_path / "rec"
    with Recorder(folder) as r:
        for k in range(10):
            r.write("incl0", 1000 + k, {"roll": 0.001 * k, "pitch": -0.001 * k})
    path = folder / "incl0" / "data.csv"
    full = path.read_bytes()
    path.write_bytes(full + b"1010,0.01")  # a kill mid-line
    with Recorder(folder) as r:
        assert not r.write("incl0", 1005, {"roll": 0.0, "pitch": 0.0})  # not after the last on file: dropped
        for k in range(10, 15):
            assert r.write("incl0", 1000 + k, {"roll": 0.001 * k, "pitch": -0.001 * k})
        assert r.counts()["incl0"] == {"written": 5, "dropped": 1, "repaired_bytes": len(b"1010,0.01")}
    text = path.read_bytes()
    assert text.startswith(full)  # never overwritten
    back = read_recording(folder).sensors["incl0"]
    assert back.t_ns.tolist() == list(range(1000, 1015))
    assert text.count(b"#timestamp") == 1


def test_restart_refuses_a_stream_with_other_columns(tmp_path):
    with Recorder(tmp_path) as r:
        r.write("tracker0", 1, {"x": 1.0, "y": 2.0, "z": 3.0})
    with Recorder(tmp_path) as r, pytest.raises(RecordingError, match="columns"):
        r.write("tracker0", 2, {"roll": 1.0, "pitch": 2.0})


def test_header_killed_mid_write_is_restarted(tmp_path):
    (tmp_path / "incl0").mkdir()
    (tmp_path / "incl0" / "data.csv").write_bytes(b"#timestamp [ns],ro")
    with Recorder(tmp_path) as r:
        r.write("incl0", 5, {"roll": 0.5, "pitch": 0.25})
    assert read_recording(tmp_path).sensors["incl0"].values["roll"].tolist() == [0.5]


_CHILD = textwrap.dedent("""
    import sys, threading, time
    import serial
    from selfcal.io.recorder import record_stream
    from selfcal.io.streams import SerialLineSource, format_sentence
    port = serial.serial_for_url("loop://", timeout=0.01)
    def feed():  # a sensor on the loop port: IMU lines as fast as the recorder takes them, host-clock stamps
        while True:
            port.write(b"".join(format_sentence("IMU", time.time_ns() + k, [0.001 * k, 0, 0, 0, 0, 9.81])
                                for k in range(50)))
            time.sleep(0.002)
    threading.Thread(target=feed, daemon=True).start()
    record_stream(SerialLineSource(port).samples(), sys.argv[1])
""")


def _start_child(folder):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.Popen([sys.executable, "-c", _CHILD, str(folder)], env=env, cwd=REPO)


def _wait_lines(path, n, timeout_s=60):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if path.exists() and path.read_bytes().count(b"\n") >= n:
            return
        time.sleep(0.05)
    raise AssertionError(f"{path}: fewer than {n} lines after {timeout_s} s")


def test_sigkill_loses_at_most_the_last_partial_line_and_restart_appends(tmp_path):
    folder = tmp_path / "rec"
    path = folder / "imu0" / "data.csv"
    child = _start_child(folder)
    try:
        _wait_lines(path, 2000)
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == -signal.SIGKILL
    data = path.read_bytes()
    complete, _, partial = data.rpartition(b"\n")
    full_line = len(data.split(b"\n")[1])
    assert len(partial) < full_line + 5  # at most one (partial) line beyond the last newline
    # everything up to the last newline is a valid recording
    intact = tmp_path / "intact"
    (intact / "imu0").mkdir(parents=True)
    (intact / "imu0" / "data.csv").write_bytes(complete + b"\n")
    first = read_recording(intact).sensors["imu0"]
    assert first.t_ns.size >= 2000

    child = _start_child(folder)  # restart: appends to the killed file
    try:
        _wait_lines(path, data.count(b"\n") + 1000)
    finally:
        child.send_signal(signal.SIGINT)  # Ctrl-C: the recorder closes its files cleanly
        try:
            child.wait(timeout=10)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
    after = path.read_bytes()
    assert after.startswith(complete + b"\n")  # the killed run's complete lines are kept as they were
    after = after[:after.rfind(b"\n") + 1]
    (intact / "imu0" / "data.csv").write_bytes(after)
    both = read_recording(intact).sensors["imu0"]  # parses: one header, increasing timestamps
    assert both.t_ns.size >= first.t_ns.size + 1000
    np.testing.assert_array_equal(both.t_ns[:first.t_ns.size], first.t_ns)


def test_cli_record_from_a_replay_then_appends(tmp_path, capsys):
    rec = small_recording()
    write_recording(rec, tmp_path / "src")
    assert main(["record", str(tmp_path / "out"), "--replay", str(tmp_path / "src"), "--max-samples", "100"]) == 0
    first = read_recording(tmp_path / "out")
    n1 = sum(s.t_ns.size for s in first.sensors.values())
    assert n1 == 100
    # the same replay again: its samples are not after those on file, so they are dropped, the rest appended
    assert main(["record", str(tmp_path / "out"), "--replay", str(tmp_path / "src")]) == 0
    out = capsys.readouterr().out
    assert "dropped" in out
    second = read_recording(tmp_path / "out")
    for name, s in rec.sensors.items():
        np.testing.assert_array_equal(second.sensors[name].t_ns, s.t_ns)


def test_cli_record_without_source_is_a_one_line_error(tmp_path, capsys):
    assert main(["record", str(tmp_path / "out")]) == 1
    assert "no source" in capsys.readouterr().err


class _Source:
    """A live source for the merger: ``n`` samples 1 ms apart as fast as it can, then silence until stopped."""

    def __init__(self, n: int):
        from selfcal.io.streams import StreamStats
        self.n, self.stats = n, StreamStats("fake")

    def samples(self, stop):
        for k in range(self.n):
            self.stats.samples += 1
            yield "incl0", 1_000_000_000 + k * 1_000_000, {"roll": 0.001 * k, "pitch": 0.0}
        while not stop.is_set():
            stop.wait(0.01)


@pytest.mark.parametrize("n", [0, 200])
def test_duration_ends_a_silent_stream_and_keeps_the_reorder_window(tmp_path, n):
    """Issue 16: ``record --duration`` never ended on a silent port, and every live run lost the samples its
    50 ms reordering window held (190 of 200).  Now the duration stops the stream itself and the merger's
    flush is written: all n samples, in a bounded time."""
    import threading
    import time
    from selfcal.io.streams import merge_live
    stop = threading.Event()
    source = _Source(n)
    started = time.monotonic()
    counts = record_stream(merge_live([source], 0.05, stop), tmp_path / "rec", duration_s=0.5, stop=stop)
    assert time.monotonic() - started < 3.0
    assert counts.get("incl0", {"written": 0})["written"] == n
