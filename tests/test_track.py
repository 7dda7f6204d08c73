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
    """Issue 16: ``--append`` after a replay re-emitted every pose.  It resumes after the last whole pose in the
    file: a run killed mid-line (its partial line ended, not parsed) and replayed again adds only the poses after
    it, and says how many it skipped."""
    rec = small_recording()
    run_track(replay(rec), EchoEstimator(), out_tum=tmp_path / "p.tum")
    lines = (tmp_path / "p.tum").read_text().splitlines()
    n = len(lines)
    with pytest.raises(FileExistsError):
        run_track(replay(rec), EchoEstimator(), out_tum=tmp_path / "p.tum")
    kept = 20  # a run killed after 20 poses, in the middle of the 21st line
    (tmp_path / "p.tum").write_text("".join(line + "\n" for line in lines[:kept]) + lines[kept][:11])
    result = run_track(replay(rec), EchoEstimator(), out_tum=tmp_path / "p.tum", append=True)
    again = (tmp_path / "p.tum").read_text().splitlines()
    assert again[:kept] == lines[:kept] and again[kept] == lines[kept][:11]  # the partial line, ended
    assert again[kept + 1:] == lines[kept:]  # every later pose once, none before
    assert result.outputs == n and result.skipped == {str(tmp_path / "p.tum"): kept}
    result = run_track(replay(rec), EchoEstimator(), out_tum=tmp_path / "p.tum", append=True)  # nothing new
    assert (tmp_path / "p.tum").read_text().splitlines() == again and result.skipped == {str(tmp_path / "p.tum"): n}


def test_append_resumes_each_output_after_its_own_last_pose(tmp_path):
    """A kill between the TUM and the JSON line of one pose leaves the JSON file a pose behind: each file resumes
    after its own last pose, so neither loses nor repeats one.  The CLI says what it skipped in one line."""
    rec = small_recording()
    write_recording(rec, tmp_path / "rec")
    run_track(replay(rec), EchoEstimator(), out_tum=tmp_path / "p.tum", out_jsonl=tmp_path / "p.jsonl")
    tum, jsonl = ((tmp_path / f"p.{ext}").read_text().splitlines() for ext in ("tum", "jsonl"))
    (tmp_path / "p.tum").write_text("".join(line + "\n" for line in tum[:10]))
    (tmp_path / "p.jsonl").write_text("".join(line + "\n" for line in jsonl[:9]))
    result = run_track(replay(rec), EchoEstimator(), out_tum=tmp_path / "p.tum", out_jsonl=tmp_path / "p.jsonl",
                       append=True)
    assert (tmp_path / "p.tum").read_text().splitlines() == tum
    assert (tmp_path / "p.jsonl").read_text().splitlines() == jsonl
    assert result.skipped == {str(tmp_path / "p.tum"): 10, str(tmp_path / "p.jsonl"): 9}


def test_cli_track_append_after_a_replay_writes_no_duplicate(tmp_path, monkeypatch, capsys):
    write_recording(small_recording(), tmp_path / "rec")
    monkeypatch.setattr(registry, "SYSTEMS", registry.SYSTEMS + (registry.System("echo", "test", online=True),))
    monkeypatch.setitem(sys.modules, "selfcal.pipelines.echo",
                        types.SimpleNamespace(online_estimator=lambda meta: EchoEstimator()))
    monkeypatch.setitem(sys.modules, "selfcal.cli.echo", types.SimpleNamespace(VERBS=()))
    args = ["track", "--replay", str(tmp_path / "rec"), "--system", "echo", "--out-tum", str(tmp_path / "p.tum")]
    assert main(args) == 0
    first = (tmp_path / "p.tum").read_text()
    capsys.readouterr()
    assert main(args + ["--append"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert (tmp_path / "p.tum").read_text() == first
    assert len(err) == 1 and "50 poses already in" in err[0] and "skipped" in err[0]


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
