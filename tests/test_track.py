"""``selfcal track`` plumbing: source -> estimator.push -> TUM + JSON lines, appended and flushed as they come.

The estimator here is a trivial consumer (a pose per tracker sample), so these tests check the plumbing, not the
tracker's estimates; those are tested with the tracker system.
"""
import json
import sys
import types

import numpy as np
import pytest
import serial

from selfcal import registry
from selfcal.cli.main import main
from selfcal.io.recording import write_recording
from selfcal.io.streams import SerialLineSource, format_sentence, merge_live, replay
from selfcal.pipelines.track import TrackError, run_track, tum_line

from test_streams import _stop_after, small_recording


class EchoEstimator:
    """Emits the tracker position as the pose, identity attitude; checks the timestamp order it is promised."""

    def __init__(self, meta=None):
        self.meta = meta
        self.last_t = None
        self.seen = []

    def push(self, sensor_name, t_ns, values):
        assert self.last_t is None or t_ns >= self.last_t, "samples out of timestamp order"
        self.last_t = t_ns
        self.seen.append(sensor_name)
        if sensor_name != "tracker0":
            return []
        return [{"t_ns": t_ns, "position": np.array([values["x"], values["y"], values["z"]]),
                 "quaternion": np.array([0.0, 0.0, 0.0, 1.0]), "covariance": np.eye(6) * 1e-6,
                 "faults": {"incl0": False, "tracker0": False}}]


def test_tum_line_keeps_nanoseconds_and_the_quaternion_xyzw():
    line = tum_line({"t_ns": 1_700_000_000_123_456_789, "position": [1.0, 2.0, 3.0],
                     "quaternion": [0.1, 0.2, 0.3, 0.5]})
    assert line.split() == ["1700000000.123456789", "1.0", "2.0", "3.0", "0.1", "0.2", "0.3", "0.5"]
    assert tum_line({"t_ns": 5, "position": [0, 0, 0], "quaternion": [0, 0, 0, 1]}).split()[0] == "0.000000005"


def test_replay_through_estimator_writes_every_pose_and_counts(tmp_path):
    rec = small_recording()
    est = EchoEstimator()
    result = run_track(replay(rec), est, out_tum=tmp_path / "p.tum", out_jsonl=tmp_path / "p.jsonl")
    trk = rec.sensors["tracker0"]
    assert result.samples == sum(s.t_ns.size for s in rec.sensors.values())
    assert result.outputs == trk.t_ns.size
    tum = np.loadtxt(tmp_path / "p.tum")
    np.testing.assert_allclose(tum[:, 0], trk.t_ns * 1e-9, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(tum[:, 1], trk.values["x"])
    lines = (tmp_path / "p.jsonl").read_text().splitlines()
    first = json.loads(lines[0])
    assert len(lines) == trk.t_ns.size and first["t_ns"] == int(trk.t_ns[0])
    assert np.array(first["covariance"]).shape == (6, 6) and first["faults"] == {"incl0": False, "tracker0": False}
    assert len(result.latencies_s) == result.samples and result.realtime_factor > 1
    assert result.per_sensor == {n: s.t_ns.size for n, s in rec.sensors.items()}


def test_outputs_are_refused_if_present_and_appended_with_append(tmp_path):
    rec = small_recording()
    run_track(replay(rec), EchoEstimator(), out_tum=tmp_path / "p.tum")
    n = len((tmp_path / "p.tum").read_text().splitlines())
    with pytest.raises(FileExistsError):
        run_track(replay(rec), EchoEstimator(), out_tum=tmp_path / "p.tum")
    with open(tmp_path / "p.tum", "a") as f:
        f.write("1.0 2.0")  # a killed run's partial line
    run_track(replay(rec), EchoEstimator(), out_tum=tmp_path / "p.tum", append=True)
    lines = (tmp_path / "p.tum").read_text().splitlines()
    assert len(lines) == 2 * n + 1 and lines[n] == "1.0 2.0" and len(lines[n + 1].split()) == 8


def test_lines_are_flushed_as_they_come(tmp_path):
    """A reader sees each pose before the run ends (what a killed tracker leaves behind)."""
    rec = small_recording()
    seen_during_run = []

    class Watching(EchoEstimator):
        def push(self, sensor_name, t_ns, values):
            if sensor_name == "tracker0" and (tmp_path / "p.tum").exists():
                seen_during_run.append(len((tmp_path / "p.tum").read_text().splitlines()))
            return super().push(sensor_name, t_ns, values)

    run_track(replay(rec), Watching(), out_tum=tmp_path / "p.tum")
    assert seen_during_run == list(range(len(seen_during_run)))


def test_live_serial_ports_feed_the_estimator_in_order(tmp_path):
    a = SerialLineSource(serial.serial_for_url("loop://", timeout=0.01), sensors={"IMU": "imu0"})
    b = SerialLineSource(serial.serial_for_url("loop://", timeout=0.01), sensors={"TRK": "tracker0"})
    b.port.write(b"".join(format_sentence("TRK", t, [t * 1e-9, 0, 0]) for t in range(1_000_000, 200_000_000, 20_000_000)))
    b.port.write(b"$TRK,1,2*00\r\n")  # malformed: skipped, counted
    a.port.write(b"".join(format_sentence("IMU", t, [0] * 6) for t in range(0, 200_000_000, 5_000_000)))
    samples = merge_live([a, b], reorder_window_s=1.0, stop=_stop_after(50, [a, b]))
    est = EchoEstimator()
    result = run_track(samples, est, out_tum=tmp_path / "p.tum")
    assert result.samples == 50 and b.stats.malformed == 1
    assert result.outputs == 10


def test_cli_track_replay_with_a_registered_estimator(tmp_path, monkeypatch, capsys):
    write_recording(small_recording(), tmp_path / "rec")
    # a new online system is one registry line, its pipeline module with `online_estimator` and its cli module
    monkeypatch.setattr(registry, "SYSTEMS", registry.SYSTEMS + (registry.System("echo", "test", online=True),))
    monkeypatch.setitem(sys.modules, "selfcal.pipelines.echo",
                        types.SimpleNamespace(online_estimator=lambda meta: EchoEstimator()))
    monkeypatch.setitem(sys.modules, "selfcal.cli.echo", types.SimpleNamespace(VERBS=()))
    assert main(["track", "--replay", str(tmp_path / "rec"), "--system", "echo",
                 "--out-tum", str(tmp_path / "p.tum"), "--out-jsonl", str(tmp_path / "p.jsonl")]) == 0
    out = capsys.readouterr().out
    assert "real time" in out and "p99" in out
    assert len((tmp_path / "p.tum").read_text().splitlines()) == 50
    assert main(["track", "--replay", str(tmp_path / "rec"), "--system", "nope", "--out-tum", "x.tum"]) == 1
    assert "no online estimator" in capsys.readouterr().err


def test_estimator_output_without_pose_is_an_error(tmp_path):
    class Bad:
        def push(self, *a):
            return [{"t_ns": 1}]

    with pytest.raises(TrackError, match="pose"):
        run_track(replay(small_recording()), Bad(), out_tum=tmp_path / "p.tum")


def test_latency_statistics_take_bounded_memory_and_keep_their_percentiles():
    """Issue 16: one latency kept per sample grew the RSS 1.8 KB per pose.  The histogram's memory is fixed and
    its percentiles are within its 1 % bin width of numpy's on the same samples."""
    from selfcal.pipelines.track import LatencyHistogram
    rng = np.random.default_rng(0)
    seconds = rng.lognormal(np.log(2e-4), 0.8, 200_000)
    hist = LatencyHistogram()
    size = hist.counts.nbytes
    for x in seconds:
        hist.add(float(x))
    assert hist.counts.nbytes == size and len(hist) == seconds.size
    for q in (50, 99):
        assert abs(hist.percentile_s(q) / np.percentile(seconds, q) - 1) < 0.011
    assert hist.percentile_s(100) == seconds.max()


def test_ctrl_c_ends_a_run_with_its_counters(tmp_path):
    """Issue 16: Ctrl-C on ``track`` printed no counters.  The run returns them, marked interrupted."""
    from selfcal.pipelines.track import run_track

    class Quiet:
        def push(self, name, t_ns, values):
            return []

    def samples():
        for k in range(5):
            yield "incl0", 1_000_000_000 + k * 10_000_000, {"roll": 0.0, "pitch": 0.0}
        raise KeyboardInterrupt

    result = run_track(samples(), Quiet(), out_tum=tmp_path / "p.tum")
    assert result.interrupted and result.samples == 5 and abs(result.data_span_s - 0.04) < 1e-12
    assert "5 samples" in result.summary()
