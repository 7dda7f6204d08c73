"""CAN logs (.asc, .blf, candump .log) and DBC decoding: ``selfcal track/record --can-log FILE [--dbc --dbc-map]``.

The logs are written by python-can's own writers from a simulated tracker run whose truth is known; the frames are
the live bus's (the TPDO1 encoder of the live-bus tests).  A log replayed through the command line must give what
the live (virtual-bus) path gives on the same frames: the same samples, so the same poses, byte for byte.
"""
import math

import can
import numpy as np
import pytest
import yaml

from selfcal.cli.main import main
from selfcal.core.inertial import STANDARD_GRAVITY_M_S2
from selfcal.io.canlog import CanLogSource
from selfcal.io.dbc import DbcDecoder, load_dbc
from selfcal.io.recorder import Recorder
from selfcal.io.recording import read_recording, write_recording
from selfcal.io.streams import CAN_ANGLE_LSB_RAD, CanInclinometerSource, encode_inclinometer_frame
from selfcal.sim.tracker import TrackerScenario

WRITERS = {".asc": can.ASCWriter, ".blf": can.BLFWriter, ".log": can.CanutilsLogWriter}
NODE = 1
# frames on the bus that are not the inclinometer's: NMT heartbeat, another node's TPDO1, a 29-bit ID, a SYNC
FOREIGN = [(0x701, False, bytes([5])), (0x182, False, bytes(8)), (0x18FF0010, True, bytes(8)), (0x080, False, b"")]

# The fixed TPDO1 layout of docs/streams.md, as a DBC says it (0x7FFF named: no valid reading)
TPDO_DBC = """VERSION ""

BS_:

BU_: INCL

BO_ 385 INCL_TPDO1: 8 INCL
 SG_ INCL_Roll : 0|16@1- (0.001,0) [-32.767|32.767] "deg" Vector__XXX
 SG_ INCL_Pitch : 16|16@1- (0.001,0) [-32.767|32.767] "deg" Vector__XXX
 SG_ INCL_Time : 32|32@1+ (1,0) [0|4294967295] "us" Vector__XXX

BO_ 1793 INCL_Heartbeat: 1 INCL
 SG_ INCL_State : 0|8@1+ (1,0) [0|255] "" Vector__XXX

VAL_ 385 INCL_Roll 32767 "NoValidReading" ;
VAL_ 385 INCL_Pitch 32767 "NoValidReading" ;
"""
TPDO_MAP = {"incl0": {"roll": "INCL_Roll", "pitch": "INCL_Pitch"}}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A 3 s simulated tracker run: the whole recording, the same without incl0, and incl0 as bus frames."""
    folder = tmp_path_factory.mktemp("canlog")
    rec = TrackerScenario(duration_s=3.0, seed=1).measurements(seed=1)
    write_recording(rec, folder / "full")
    rest = read_recording(folder / "full")
    del rest.sensors["incl0"]
    write_recording(rest, folder / "rest")
    incl = rec.sensors["incl0"]
    t0 = int(incl.t_ns[0])
    frames = []
    for k, (t, roll, pitch) in enumerate(zip(incl.t_ns.tolist(), incl.values["roll"], incl.values["pitch"])):
        # host receive time = the sim's time (the run starts on a whole second: exact in every log format)
        frames.append(can.Message(arbitration_id=0x180 + NODE, is_extended_id=False, timestamp=t * 1e-9,
                                  data=encode_inclinometer_frame(roll, pitch, (t - t0) // 1000)))
        arb, ext, data = FOREIGN[k % len(FOREIGN)]
        frames.append(can.Message(arbitration_id=arb, is_extended_id=ext, data=data, timestamp=(t + 1_000_000) * 1e-9))
    # one frame flagged invalid (0x7FFF): malformed, counted, skipped
    frames.insert(7, can.Message(arbitration_id=0x180 + NODE, is_extended_id=False, timestamp=frames[6].timestamp,
                                 data=b"\xff\x7f" + bytes(6)))
    return {"folder": folder, "rec": rec, "frames": frames, "n_incl": incl.t_ns.size}


def write_log(path, frames):
    writer = WRITERS[path.suffix](str(path))
    for msg in frames:
        writer.on_message_received(msg)
    writer.stop()
    return path


def virtual_bus_samples(frames, channel):
    """The live path: the frames sent on a python-can virtual bus (sender's times kept), read by the live source."""
    tx = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    rx = can.Bus(interface="virtual", channel=channel)
    source = CanInclinometerSource(bus=rx, node_id=NODE, sensor="incl0")
    try:
        for msg in frames:
            tx.send(msg)
        samples = []
        while (msg := rx.recv(timeout=0.5)) is not None:
            sample = source.handle(msg)
            if sample is not None:
                samples.append(sample)
        return samples, source.stats
    finally:
        tx.shutdown()
        rx.shutdown()


@pytest.fixture(scope="module")
def live_poses(run):
    """``selfcal track`` on the recording whose incl0 is what the live bus gave: the reference poses."""
    folder = run["folder"]
    samples, stats = virtual_bus_samples(run["frames"], "selfcal_test_canlog")
    assert len(samples) == run["n_incl"] and stats.malformed == 1 and stats.ignored == len(run["frames"]) - 1 - \
        run["n_incl"]
    live = folder / "live"
    write_recording(read_recording(folder / "rest"), live)
    with Recorder(live) as recorder:
        for sample in samples:
            assert recorder.write(*sample)
    assert main(["track", "--replay", str(live), "--sensors-from", str(folder / "full"),
                 "--out-tum", str(folder / "live.tum")]) == 0
    return samples, (folder / "live.tum").read_text()


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".log"])
def test_cli_track_from_a_can_log_equals_the_live_bus_path(run, live_poses, suffix, tmp_path, capsys):
    """Same frames, same samples (time and value, exactly), same poses byte for byte; foreign IDs counted."""
    samples, reference = live_poses
    log = write_log(tmp_path / f"run{suffix}", run["frames"])
    assert list(CanLogSource(log, node_id=NODE).samples()) == samples
    capsys.readouterr()
    assert main(["track", "--replay", str(run["folder"] / "rest"), "--can-log", str(log),
                 "--sensors-from", str(run["folder"] / "full"), "--out-tum", str(tmp_path / "log.tum")]) == 0
    assert (tmp_path / "log.tum").read_text() == reference and reference.count("\n") > 10
    n_foreign = len(run["frames"]) - 1 - run["n_incl"]
    assert (f"CAN log {log}: {len(run['frames'])} frames: {run['n_incl']} decoded into {run['n_incl']} samples, "
            f"{n_foreign} skipped (IDs not decoded), 1 malformed skipped") in capsys.readouterr().out


def test_dbc_of_the_tpdo_layout_decodes_what_the_fixed_decoder_does(run, tmp_path):
    """A DBC describing TPDO1 (deg, converted to rad): frames encoded by cantools are the fixed encoder's bytes,
    and decoding gives the fixed decoder's samples: the same times, the same angles (to the float rounding of
    counts * 0.001 * pi/180 taken in another order: a few ulp), the same counts of skipped frames."""
    (tmp_path / "tpdo.dbc").write_text(TPDO_DBC)
    db = load_dbc(tmp_path / "tpdo.dbc")
    message = db.get_message_by_name("INCL_TPDO1")
    for counts in [(500, -1250, 1_000_000), (-32766, 32766, 2**32 - 1), (1, -1, 0)]:
        roll, pitch, t_us = counts
        encoded = message.encode({"INCL_Roll": roll * 0.001, "INCL_Pitch": pitch * 0.001, "INCL_Time": t_us})
        assert encoded == encode_inclinometer_frame(roll * CAN_ANGLE_LSB_RAD, pitch * CAN_ANGLE_LSB_RAD, t_us)
    fixed = CanInclinometerSource(bus=object(), node_id=NODE)
    dbc = DbcDecoder(db, TPDO_MAP)
    want = [s for s in map(fixed.handle, run["frames"]) if s is not None]
    got = [s for msg in run["frames"] for s in dbc.decode(msg)]
    assert len(got) == len(want) == run["n_incl"]
    assert [(name, t) for name, t, _ in got] == [(name, t) for name, t, _ in want]
    for (_, _, v), (_, _, w) in zip(got, want):
        assert list(v) == ["roll", "pitch"]
        np.testing.assert_allclose([v["roll"], v["pitch"]], [w["roll"], w["pitch"]], rtol=1e-14, atol=0)
    assert (dbc.stats.ignored, dbc.stats.malformed) == (fixed.stats.ignored, fixed.stats.malformed) \
        == (len(run["frames"]) - 1 - run["n_incl"], 1)


# A whole tracker run on CAN through a DBC, in the units such DBCs use (deg/s, g, mm, deg, px); the IMU's rates
# and accelerations come in two frames, the tracker position (21 bits per axis, 0.1 mm) in an extended-ID frame
RUN_DBC = """VERSION ""

BS_:

BU_: IMU TRK INCL CAM

BO_ 256 IMU_Rates: 6 IMU
 SG_ RateX : 0|16@1- (0.001,0) [-32.768|32.767] "deg/s" Vector__XXX
 SG_ RateY : 16|16@1- (0.001,0) [-32.768|32.767] "deg/s" Vector__XXX
 SG_ RateZ : 32|16@1- (0.001,0) [-32.768|32.767] "deg/s" Vector__XXX

BO_ 257 IMU_Accels: 6 IMU
 SG_ AccX : 0|16@1- (0.0001,0) [-3.2768|3.2767] "g" Vector__XXX
 SG_ AccY : 16|16@1- (0.0001,0) [-3.2768|3.2767] "g" Vector__XXX
 SG_ AccZ : 32|16@1- (0.0001,0) [-3.2768|3.2767] "g" Vector__XXX

BO_ 2147484160 TRK_Position: 8 TRK
 SG_ PosX : 0|21@1- (0.1,0) [-104857.6|104857.5] "mm" Vector__XXX
 SG_ PosY : 21|21@1- (0.1,0) [-104857.6|104857.5] "mm" Vector__XXX
 SG_ PosZ : 42|21@1- (0.1,0) [-104857.6|104857.5] "mm" Vector__XXX

BO_ 385 INCL_TPDO1: 8 INCL
 SG_ Roll : 0|16@1- (0.001,0) [-32.767|32.767] "deg" Vector__XXX
 SG_ Pitch : 16|16@1- (0.001,0) [-32.767|32.767] "deg" Vector__XXX

BO_ 768 CAM_Spot: 8 CAM
 SG_ SpotU : 0|32@1- (0.001,0) [-2147483.648|2147483.647] "px" Vector__XXX
 SG_ SpotV : 32|32@1- (0.001,0) [-2147483.648|2147483.647] "" Vector__XXX
"""
RUN_MAP = {"imu0": {"w_RS_S_x": "RateX", "w_RS_S_y": "RateY", "w_RS_S_z": "RateZ",
                    "a_RS_S_x": "AccX", "a_RS_S_y": "AccY", "a_RS_S_z": "AccZ"},
           "tracker0": {"x": "PosX", "y": "PosY", "z": "PosZ"},
           "incl0": {"roll": "Roll", "pitch": "Pitch"},
           "cam0": {"u": "SpotU", "v": "SpotV"}}
# column -> (DBC signal scale in its unit, factor from that unit to the column's): half an LSB is the bound
LSB = {**{c: (0.001, math.pi / 180) for c in ("w_RS_S_x", "w_RS_S_y", "w_RS_S_z")},
       **{c: (0.0001, STANDARD_GRAVITY_M_S2) for c in ("a_RS_S_x", "a_RS_S_y", "a_RS_S_z")},
       **{c: (0.1, 1e-3) for c in ("x", "y", "z")}, "roll": (0.001, math.pi / 180),
       "pitch": (0.001, math.pi / 180), "u": (0.001, 1.0), "v": (0.001, 1.0)}


def dbc_frames(db, rec):
    """Every sample of ``rec`` as the frames of RUN_DBC (values in the DBC's units), in (time, sensor) order,
    with a frame the DBC does not know after each tracker frame."""
    messages = {"imu0": ["IMU_Rates", "IMU_Accels"], "tracker0": ["TRK_Position"], "incl0": ["INCL_TPDO1"],
                "cam0": ["CAM_Spot"]}
    events = []
    for sensor, names in messages.items():
        s = rec.sensors[sensor]
        for k, t in enumerate(s.t_ns.tolist()):
            for name in names:
                m = db.get_message_by_name(name)
                column = {sig: col for col, sig in RUN_MAP[sensor].items()}
                values = {sig.name: s.values[column[sig.name]][k] / LSB[column[sig.name]][1] for sig in m.signals}
                events.append((t, sensor, can.Message(arbitration_id=m.frame_id, is_extended_id=m.is_extended_frame,
                                                      data=m.encode(values), timestamp=t * 1e-9)))
            if sensor == "tracker0":
                events.append((t, sensor, can.Message(arbitration_id=0x123, data=bytes(4), timestamp=t * 1e-9)))
    events.sort(key=lambda e: (e[0], e[1]))
    return [msg for _, _, msg in events]


def test_cli_record_and_track_a_can_log_through_a_dbc(run, tmp_path, capsys):
    """``record --can-log --dbc``: every sample within half an LSB of the simulated values, in the recording's
    units (deg/s, g, mm, deg converted); ``track`` on the log gives the poses of ``track`` on that recording."""
    (tmp_path / "run.dbc").write_text(RUN_DBC)
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(RUN_MAP, sort_keys=False))
    rec = run["rec"]
    frames = dbc_frames(load_dbc(tmp_path / "run.dbc"), rec)
    log = write_log(tmp_path / "run.blf", frames)
    dbc = ["--can-log", str(log), "--dbc", str(tmp_path / "run.dbc"), "--dbc-map", str(tmp_path / "map.yaml")]
    assert main(["record", str(tmp_path / "out"), *dbc]) == 0
    n_trk = rec.sensors["tracker0"].t_ns.size
    n_samples = sum(s.t_ns.size for s in rec.sensors.values())
    assert (f"{len(frames)} frames: {len(frames) - n_trk} decoded into {n_samples} samples, {n_trk} skipped "
            f"(IDs not decoded), 0 malformed skipped") in capsys.readouterr().out
    got = read_recording(tmp_path / "out")
    assert sorted(got.sensors) == sorted(RUN_MAP)
    for name, s in got.sensors.items():
        truth = rec.sensors[name]
        np.testing.assert_array_equal(s.t_ns, truth.t_ns)
        assert list(s.values) == list(RUN_MAP[name])
        for column, values in s.values.items():
            scale, factor = LSB[column]
            bound = scale / 2 * factor * (1 + 1e-9)  # half an LSB (+ the float rounding of the conversions)
            assert np.max(np.abs(values - truth.values[column])) <= bound, (name, column)
    sensors_from = ["--sensors-from", str(run["folder"] / "full")]
    assert main(["track", *dbc, *sensors_from, "--out-tum", str(tmp_path / "log.tum")]) == 0
    assert main(["track", "--replay", str(tmp_path / "out"), *sensors_from, "--out-tum", str(tmp_path / "rec.tum")]) == 0
    assert (tmp_path / "log.tum").read_text() == (tmp_path / "rec.tum").read_text()
    assert (tmp_path / "log.tum").read_text().count("\n") > 10


def test_dbc_sample_split_over_frames_needs_every_frame(tmp_path):
    """A lost accelerometer frame: the partial IMU sample is dropped and counted, the next one comes whole."""
    (tmp_path / "run.dbc").write_text(RUN_DBC)
    db = load_dbc(tmp_path / "run.dbc")
    decoder = DbcDecoder(db, {"imu0": RUN_MAP["imu0"]})
    rates, accels = db.get_message_by_name("IMU_Rates"), db.get_message_by_name("IMU_Accels")

    def frame(m, values, t):
        return can.Message(arbitration_id=m.frame_id, is_extended_id=False, data=m.encode(values), timestamp=t)

    r = {"RateX": 1.0, "RateY": 2.0, "RateZ": 3.0}
    a = {"AccX": 0.0, "AccY": 0.0, "AccZ": 1.0}
    out = [s for msg in [frame(rates, r, 10.0), frame(rates, r, 10.005), frame(accels, a, 10.005)]
           for s in decoder.decode(msg)]
    assert decoder.stats.malformed == 1 and len(out) == 1
    name, t_ns, values = out[0]
    assert name == "imu0" and t_ns == 10_005_000_000
    assert values["a_RS_S_z"] == pytest.approx(STANDARD_GRAVITY_M_S2, rel=1e-12)
    assert values["w_RS_S_y"] == pytest.approx(math.radians(2.0), rel=1e-12)


# --------------------------------------------------------------------------------------------- one-line errors

def one_line_error(capsys, argv, *fragments):
    capsys.readouterr()
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in err, err


def test_can_log_errors_are_one_line(tmp_path, capsys):
    out = ["--out-tum", str(tmp_path / "p.tum")]
    one_line_error(capsys, ["track", "--can-log", str(tmp_path / "missing.blf"), *out], "missing.blf", "no such")
    (tmp_path / "run.trc").write_text("")
    one_line_error(capsys, ["track", "--can-log", str(tmp_path / "run.trc"), *out], "unknown CAN log suffix '.trc'",
                   ".asc", ".blf", ".log")
    (tmp_path / "bad.blf").write_bytes(b"not a BLF file at all" * 10)
    one_line_error(capsys, ["record", str(tmp_path / "rec"), "--can-log", str(tmp_path / "bad.blf")],
                   "bad.blf", "not a readable")
    one_line_error(capsys, ["track", "--can-log", str(tmp_path / "bad.blf"), "--serial", "loop://", *out],
                   "cannot be merged with live")


def test_dbc_errors_are_one_line(tmp_path, capsys):
    log = write_log(tmp_path / "run.log", [can.Message(arbitration_id=0x181, data=bytes(8), timestamp=1.0)])
    (tmp_path / "good.dbc").write_text(TPDO_DBC)
    (tmp_path / "bad.dbc").write_text("BO_ this is not a DBC\n")

    def track(dbc, mapping):
        path = tmp_path / "map.yaml"
        path.write_text(yaml.safe_dump(mapping, sort_keys=False))
        return ["track", "--can-log", str(log), "--dbc", str(tmp_path / dbc), "--dbc-map", str(path),
                "--out-tum", str(tmp_path / "p.tum")]

    one_line_error(capsys, track("bad.dbc", TPDO_MAP), "bad.dbc", "not a DBC")
    one_line_error(capsys, track("nope.dbc", TPDO_MAP), "nope.dbc", "no such DBC file")
    one_line_error(capsys, track("good.dbc", {"incl0": {"roll": "INCL_Rol", "pitch": "INCL_Pitch"}}),
                   "incl0 roll -> INCL_Rol: no such signal", "did you mean INCL_Roll")
    one_line_error(capsys, track("good.dbc", {"incl0": {"roll": "INCL_Roll"}}), "incl0 maps roll",
                   "all the columns of one kind")
    one_line_error(capsys, track("good.dbc", {"imu0": {"w_RS_S_x": "INCL_Roll", "w_RS_S_y": "INCL_Pitch",
                                                       "w_RS_S_z": "INCL_Roll", "a_RS_S_x": "INCL_Time",
                                                       "a_RS_S_y": "INCL_Roll", "a_RS_S_z": "INCL_Roll"}}),
                   "DBC unit 'deg' cannot be read as w_RS_S_x [rad s^-1]")
    one_line_error(capsys, ["track", "--can-log", str(log), "--dbc", str(tmp_path / "good.dbc"),
                            "--out-tum", str(tmp_path / "p.tum")], "--dbc FILE and --dbc-map MAP.yaml go together")


def test_cli_record_from_a_live_bus_through_a_dbc(tmp_path):
    """``record --can CH --dbc --dbc-map``: the live bus decoded through the DBC (deg -> rad), foreign IDs ignored."""
    import threading
    (tmp_path / "tpdo.dbc").write_text(TPDO_DBC)
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(TPDO_MAP, sort_keys=False))
    message = load_dbc(tmp_path / "tpdo.dbc").get_message_by_name("INCL_TPDO1")
    channel = "selfcal_test_dbc_live"
    done = threading.Event()

    def node():  # the inclinometer, and a heartbeat, until the recorder has what it wants
        tx = can.Bus(interface="virtual", channel=channel)
        k = 0
        try:
            while not done.is_set() and k < 2000:
                tx.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=message.encode(
                    {"INCL_Roll": 0.5, "INCL_Pitch": -1.25, "INCL_Time": 1000 * k})))
                tx.send(can.Message(arbitration_id=0x701, is_extended_id=False, data=bytes([5])))
                k += 1
                done.wait(0.002)
        finally:
            tx.shutdown()

    th = threading.Thread(target=node, daemon=True)
    th.start()
    try:
        assert main(["record", str(tmp_path / "rec"), "--can", channel, "--can-interface", "virtual",
                     "--dbc", str(tmp_path / "tpdo.dbc"), "--dbc-map", str(tmp_path / "map.yaml"),
                     "--max-samples", "10"]) == 0
    finally:
        done.set()
        th.join(5)
    incl = read_recording(tmp_path / "rec").sensors["incl0"]
    assert incl.t_ns.size == 10 and incl.units == {"roll": "rad", "pitch": "rad"}
    np.testing.assert_allclose(incl.values["roll"], math.radians(0.5), rtol=1e-14)
    np.testing.assert_allclose(incl.values["pitch"], math.radians(-1.25), rtol=1e-14)


def test_realtime_paces_a_log_by_its_timestamps():
    """``--realtime --speed 2``: samples 0.5 s apart in the log come 0.25 s apart on the (fake) wall clock."""
    from selfcal.io.canlog import paced
    now = [0.0]
    released = []

    def sleep(s):
        now[0] += s

    samples = [("incl0", 1_700_000_000_000_000_000 + k * 500_000_000, {}) for k in range(4)]
    for sample in paced(samples, speed=2.0, clock=lambda: now[0], sleep=sleep):
        released.append(now[0])
    assert released == [0.0, 0.25, 0.5, 0.75]
