"""Live streams: serial line protocol over pyserial's loop://, CAN frames on python-can's virtual bus, replay.

No hardware: ``serial_for_url("loop://")`` echoes what is written, the ``virtual`` CAN interface connects buses
opened on the same channel inside this process.
"""
import math
import threading

import numpy as np
import pytest
import serial

from selfcal.io.recording import Recording, SensorData, imu_sensor
from selfcal.io.streams import (CAN_ANGLE_LSB_RAD, CanInclinometerSource, SerialLineSource, StreamError,
                                decode_inclinometer_frame, encode_inclinometer_frame, format_sentence,
                                merge_live, nmea_checksum, parse_sentence, parse_serial_spec, replay)

can = pytest.importorskip("can")


def test_checksum_is_nmea_xor():
    # a published NMEA sentence: $GPGLL,5300.97914,N,00259.98174,E,125926,A*28
    assert nmea_checksum("GPGLL,5300.97914,N,00259.98174,E,125926,A") == 0x28


@pytest.mark.parametrize("kind,values,columns", [
    ("IMU", [0.01, -0.02, 0.003, 0.1, -0.2, 9.81],
     ["w_RS_S_x", "w_RS_S_y", "w_RS_S_z", "a_RS_S_x", "a_RS_S_y", "a_RS_S_z"]),
    ("INC", [0.0123, -0.0045], ["roll", "pitch"]),
    ("TRK", [12.5, -3.25, 1.0], ["x", "y", "z"]),
    ("TRK", [12.5, -3.25, 1.0, 0.001, 0.0, -0.002], ["x", "y", "z", "vx", "vy", "vz"]),
    ("CAM", [320.5, 240.25], ["u", "v"]),
])
def test_sentence_round_trip_is_exact(kind, values, columns):
    line = format_sentence(kind, 1_700_000_000_123_456_789, values)
    sensor, t_ns, parsed = parse_sentence(line)
    assert t_ns == 1_700_000_000_123_456_789  # ns epochs beyond 2^53: parsed as int, never through float
    assert list(parsed) == columns
    assert list(parsed.values()) == values  # repr round-trips float64 exactly
    assert sensor == {"IMU": "imu0", "INC": "incl0", "TRK": "tracker0", "CAM": "cam0"}[kind]


@pytest.mark.parametrize("bad", [
    b"$INC,100,0.1,0.2*00\r\n",  # wrong checksum
    b"INC,100,0.1,0.2*47\r\n",  # no $
    b"$INC,100,0.1,0.2\r\n",  # no checksum
    b"$INC,100,0.1*",  # truncated
    b"\xff\xfe$INC\r\n",  # noise
])
def test_malformed_sentences_raise(bad):
    with pytest.raises(ValueError):
        parse_sentence(bad)


def test_bad_field_counts_and_values_raise_with_a_valid_checksum():
    for body in ("INC,100,0.1", "IMU,100,1,2,3", "TRK,100,1,2,3,4", "XYZ,100,1", "INC,1e3,0.1,0.2",
                 "INC,100,nan,0.2", "INC,100,abc,0.2"):
        line = f"${body}*{nmea_checksum(body):02X}"
        with pytest.raises(ValueError):
            parse_sentence(line)


def test_loop_port_skips_and_counts_malformed_lines_and_goes_on(caplog):
    port = serial.serial_for_url("loop://", timeout=0.01)
    source = SerialLineSource(port)
    good = [format_sentence("IMU", 1000 + k, [k, 0, 0, 0, 0, 9.81]) for k in range(5)]
    bad = [b"$IMU,1,2*00\r\n", b"garbage\r\n", b"$INC,5,0.1,0.2*FF\r\n"]
    stream = good[0] + bad[0] + good[1] + bad[1] + good[2] + bad[2] + good[3] + good[4]
    # split mid-line: the reader must reassemble lines across reads
    port.write(stream[:37])
    got = source.poll()
    port.write(stream[37:])
    while len(got) < 5:
        got += source.poll()
    assert [t for _, t, _ in got] == [1000, 1001, 1002, 1003, 1004]
    assert [v["w_RS_S_x"] for _, _, v in got] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert source.stats.samples == 5 and source.stats.malformed == 3
    assert "malformed" in caplog.text


def test_line_noise_without_newline_is_dropped_not_accumulated():
    source = SerialLineSource(serial.serial_for_url("loop://", timeout=0.01), max_line=64)
    assert source.feed(b"x" * 200) == []
    assert source.stats.malformed == 1
    assert source.feed(format_sentence("INC", 7, [0.1, 0.2]))[0][1] == 7


def test_port_mapping_routes_types_to_sensors_and_rejects_unmapped():
    port, baud, sensors = parse_serial_spec("/dev/ttyUSB0:115200,IMU=imu1,TRK=tracker0")
    assert (port, baud, sensors) == ("/dev/ttyUSB0", 115200, {"IMU": "imu1", "TRK": "tracker0"})
    assert parse_serial_spec("socket://localhost:7777")[:2] == ("socket://localhost:7777", None)
    assert parse_serial_spec("loop://")[:2] == ("loop://", None)
    with pytest.raises(StreamError):
        parse_serial_spec("/dev/ttyUSB0,IMU")
    assert parse_sentence(format_sentence("IMU", 1, [0] * 6), sensors)[0] == "imu1"
    with pytest.raises(ValueError, match="not mapped"):
        parse_sentence(format_sentence("INC", 1, [0, 0]), sensors)


# ------------------------------------------------------------------------------------------------------- CAN

def test_can_payload_quantisation_is_half_an_lsb():
    rng = np.random.default_rng(3)
    for roll, pitch in rng.uniform(-0.5, 0.5, (200, 2)):
        r, p, t = decode_inclinometer_frame(encode_inclinometer_frame(roll, pitch, 123))
        assert abs(r - roll) <= CAN_ANGLE_LSB_RAD / 2 + 1e-15 and abs(p - pitch) <= CAN_ANGLE_LSB_RAD / 2 + 1e-15
        assert t == 123


def test_can_virtual_bus_reads_frames_skips_malformed_and_unwraps_the_clock():
    channel = "selfcal_test_incl"
    tx = can.Bus(interface="virtual", channel=channel)
    rx = can.Bus(interface="virtual", channel=channel)
    source = CanInclinometerSource(bus=rx, node_id=5, sensor="incl0")
    try:
        t_us = [2**32 - 3000, 2**32 - 1000, 1000, 3000]  # the sensor clock wraps between frames 2 and 3
        angles = [(0.01, -0.02), (0.011, -0.021), (0.012, -0.022), (0.013, -0.023)]
        frames = [can.Message(arbitration_id=0x185, data=encode_inclinometer_frame(r, p, t), is_extended_id=False)
                  for (r, p), t in zip(angles, t_us)]
        tx.send(frames[0])
        tx.send(can.Message(arbitration_id=0x185, data=b"\x01\x02\x03", is_extended_id=False))  # short DLC
        tx.send(frames[1])
        tx.send(can.Message(arbitration_id=0x186, data=bytes(8), is_extended_id=False))  # another node
        tx.send(can.Message(arbitration_id=0x185, data=b"\xff\x7f" + bytes(6), is_extended_id=False))  # invalid
        tx.send(frames[2])
        tx.send(frames[3])
        stop = threading.Event()
        got = []
        for sample in source.samples(stop):
            got.append(sample)
            if len(got) == 4:
                stop.set()
        assert source.stats.malformed == 2 and source.stats.ignored == 1
        t = np.array([s[1] for s in got])
        assert np.diff(t).tolist() == [2_000_000, 2_000_000, 2_000_000]  # sensor clock spacing, across the wrap
        for (_, _, v), (r, p) in zip(got, angles):
            assert abs(v["roll"] - r) <= CAN_ANGLE_LSB_RAD / 2 + 1e-15
            assert abs(v["pitch"] - p) <= CAN_ANGLE_LSB_RAD / 2 + 1e-15
    finally:
        tx.shutdown()
        rx.shutdown()


# ------------------------------------------------------------------------------------------------ replay/merge

def small_recording(seconds=1.0):
    t_imu = np.arange(0, int(seconds * 200)) * 5_000_000 + 1_700_000_000_000_000_000
    rng = np.random.default_rng(0)
    imu = imu_sensor("imu0", t_imu, rng.normal(0, 0.01, (t_imu.size, 3)),
                     rng.normal(0, 0.01, (t_imu.size, 3)) + [0, 0, 9.81])
    t_trk = t_imu[::4] + 1_000_000
    trk = SensorData("tracker0", t_trk, {c: rng.normal(0, 1, t_trk.size) for c in ("x", "y", "z")},
                     {"x": "m", "y": "m", "z": "m"})
    t_inc = t_imu[::20] + 2_500_000
    inc = SensorData("incl0", t_inc, {"roll": rng.normal(0, 0.01, t_inc.size),
                                      "pitch": rng.normal(0, 0.01, t_inc.size)}, {"roll": "rad", "pitch": "rad"})
    return Recording(None, {"imu0": imu, "tracker0": trk, "incl0": inc})


def test_replay_merges_every_sample_in_timestamp_order_with_recording_columns():
    rec = small_recording()
    out = list(replay(rec))
    assert len(out) == sum(s.t_ns.size for s in rec.sensors.values())
    t = [s[1] for s in out]
    assert t == sorted(t)
    name, t0, values = next(s for s in out if s[0] == "tracker0")
    assert t0 == rec.sensors["tracker0"].t_ns[0] and values == {c: rec.sensors["tracker0"].values[c][0]
                                                               for c in ("x", "y", "z")}


def test_realtime_replay_paces_by_timestamps():
    rec = small_recording(0.5)
    now = [0.0]
    slept = []

    def sleep(dt):
        slept.append(dt)
        now[0] += dt

    out = list(replay(rec, realtime=True, speed=2.0, clock=lambda: now[0], sleep=sleep))
    span_s = (out[-1][1] - out[0][1]) * 1e-9
    assert now[0] == pytest.approx(span_s / 2.0, abs=1e-9)  # wall time = data time / speed


def test_merge_live_orders_samples_from_two_ports():
    a = SerialLineSource(serial.serial_for_url("loop://", timeout=0.01), sensors={"IMU": "imu0"})
    b = SerialLineSource(serial.serial_for_url("loop://", timeout=0.01), sensors={"TRK": "tracker0"})
    # port b's lines are written first although their timestamps interleave with port a's
    b.port.write(b"".join(format_sentence("TRK", t, [1, 2, 3]) for t in range(2_000_000, 100_000_000, 10_000_000)))
    a.port.write(b"".join(format_sentence("IMU", t, [0] * 6) for t in range(0, 100_000_000, 5_000_000)))
    n = 10 + 20
    out = list(merge_live([a, b], reorder_window_s=1.0, max_samples=None,
                          stop=_stop_after(n, [a, b])))
    t = [s[1] for s in out]
    assert len(out) == n and t == sorted(t)


def _stop_after(n, sources):
    """A stop event set once the sources have parsed n samples (the loop ports never close by themselves)."""
    stop = threading.Event()

    def watch():
        while sum(s.stats.samples for s in sources) < n:
            stop.wait(0.01)
        stop.wait(0.2)
        stop.set()

    threading.Thread(target=watch, daemon=True).start()
    return stop


def test_nan_is_not_a_sample():
    body = "INC,5,0.1,inf"
    with pytest.raises(ValueError):
        parse_sentence(f"${body}*{nmea_checksum(body):02X}")
    assert math.isfinite(parse_sentence(format_sentence("INC", 5, [0.1, 0.2]))[2]["roll"])


def test_the_examples_in_docs_parse():
    """Every protocol line in docs/streams.md parses (checksums included), and the CAN example decodes."""
    from pathlib import Path
    doc = (Path(__file__).resolve().parents[1] / "docs" / "streams.md").read_text()
    lines = [ln.strip() for ln in doc.splitlines() if ln.startswith("$") and "<" not in ln]
    assert len(lines) == 3
    for line in lines:
        parse_sentence(line)
    roll, pitch, t_us = decode_inclinometer_frame(bytes.fromhex("F4 01 1E FB 40 42 0F 00"))
    assert (round(math.degrees(roll), 6), round(math.degrees(pitch), 6), t_us) == (0.5, -1.25, 1_000_000)


def test_cli_record_from_a_virtual_can_bus(tmp_path):
    """``selfcal record OUT --can CH --can-interface virtual``: frames sent by another node end up in incl0."""
    from selfcal.cli.main import main
    from selfcal.io.recording import read_recording
    channel = "selfcal_test_record"
    done = threading.Event()

    def node():  # the inclinometer: a frame every 10 ms of its clock until the recorder has what it wants
        tx = can.Bus(interface="virtual", channel=channel)
        k = 0
        try:
            while not done.is_set() and k < 2000:
                tx.send(can.Message(arbitration_id=0x181, is_extended_id=False,
                                    data=encode_inclinometer_frame(0.001 * (k % 100), -0.002, 10_000 * k)))
                k += 1
                done.wait(0.002)
        finally:
            tx.shutdown()

    th = threading.Thread(target=node, daemon=True)
    th.start()
    try:
        assert main(["record", str(tmp_path / "rec"), "--can", channel, "--can-interface", "virtual",
                     "--max-samples", "20"]) == 0
    finally:
        done.set()
        th.join(5)
    incl = read_recording(tmp_path / "rec").sensors["incl0"]
    assert incl.t_ns.size == 20 and (np.diff(incl.t_ns) == 10_000_000).all()
    assert incl.units == {"roll": "rad", "pitch": "rad"}


def test_can_clock_stepping_back_or_resetting_is_reanchored_and_counted():
    """Issue 16: a counter that steps back 1 us (or a sensor reset) is not a wrap: the host clock, which moved a
    few ms, does not show the 71.6 min a wrap would mean.  Time stays monotone and near the host's, the event is
    counted; a genuine wrap (host time moving with it) is still unwrapped."""
    source = CanInclinometerSource(bus=can.Bus(interface="virtual", channel="selfcal_test_reset"), node_id=5)
    try:
        def frame(t_us, host_s):
            return can.Message(arbitration_id=0x185, data=encode_inclinometer_frame(0.0, 0.0, t_us),
                               is_extended_id=False, timestamp=host_s)
        times = [source.handle(frame(t_us, host))[1] for t_us, host in
                 [(5_000_000, 100.000), (5_010_000, 100.010), (5_009_999, 100.020),  # 1 us back
                  (7, 100.030),  # reset to zero
                  (17, 100.040)]]
        assert source.stats.reanchored == 2
        assert np.all(np.diff(times) > 0)
        assert abs(times[-1] * 1e-9 - 100.040) < 0.02  # near the host's clock, not 4294.97 s ahead
        wrap = CanInclinometerSource(bus=source.bus, node_id=5)
        t_wrap = [wrap.handle(frame(t_us, host))[1] for t_us, host in [(2**32 - 5000, 50.0), (5000, 50.01)]]
        assert wrap.stats.reanchored == 0 and t_wrap[1] - t_wrap[0] == 10_000_000
    finally:
        source.bus.shutdown()
