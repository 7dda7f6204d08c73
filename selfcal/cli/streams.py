"""``selfcal record`` and ``selfcal track``: live streams (serial, CAN), a replayed recording or CAN log
(docs/streams.md)."""
from __future__ import annotations

import sys
from pathlib import Path

from selfcal import registry
from selfcal.cli.common import UsageError, Verb, positive_float


def stream_arguments(p) -> None:
    """The sources a live command reads from (repeatable serial ports, one CAN channel, or a replay)."""
    sources = p.add_argument_group("sources")
    sources.add_argument("--serial", action="append", metavar="PORT[:BAUD][,TYPE=sensor...]",
                         help="serial port speaking the line protocol of docs/streams.md (repeatable); e.g. "
                              "/dev/ttyUSB0:115200,IMU=imu0,TRK=tracker0 (default mapping IMU=imu0,INC=incl0,"
                              "TRK=tracker0,CAM=cam0)")
    sources.add_argument("--can", metavar="CHANNEL", help="CAN channel of a CANopen-style inclinometer (e.g. can0)")
    sources.add_argument("--can-interface", default="socketcan", help="python-can interface: socketcan (default), "
                                                                       "virtual, ...")
    sources.add_argument("--can-node", type=int, default=1,
                         help="CANopen node id (TPDO1 COB-ID 0x180+node), default 1")
    sources.add_argument("--can-sensor", default="incl0", help="sensor name of the CAN inclinometer (default incl0)")
    sources.add_argument("--replay", metavar="REC", help="replay a recording (as fast as possible unless --realtime)")
    sources.add_argument("--can-log", metavar="FILE", help="replay a CAN log: .asc, .blf (Vector) or .log (candump "
                                                          "-L), as fast as possible unless --realtime; alone or "
                                                          "with --replay")
    sources.add_argument("--dbc", metavar="FILE", help="decode the CAN frames (--can or --can-log) through this DBC "
                                                      "instead of the fixed inclinometer TPDO1; needs --dbc-map")
    sources.add_argument("--dbc-map", metavar="MAP.yaml", help="which DBC signal is which column: "
                                                              "'sensor: {column: signal}' (docs/streams.md)")
    sources.add_argument("--realtime", action="store_true", help="replay at the recording's (or log's) own pace")
    sources.add_argument("--speed", type=positive_float, default=1.0, help="with --realtime: playback speed factor")
    sources.add_argument("--max-samples", type=int, help="stop after this many samples")


def open_stream(args, max_samples=None, recording=None):
    """The sources of the command line merged; ``recording``: the --replay recording when already read."""
    from selfcal.io.streams import open_stream as open_sources
    if not (args.serial or args.can or args.replay or args.can_log):
        raise UsageError("no source: give --serial PORT[:BAUD][,TYPE=sensor...], --can CHANNEL, --replay REC "
                         "and/or --can-log FILE")
    if (args.dbc is None) != (args.dbc_map is None):
        raise UsageError("--dbc FILE and --dbc-map MAP.yaml go together (the map says which signal is which column)")
    if args.dbc and not (args.can or args.can_log):
        raise UsageError("--dbc decodes CAN frames: give --can CHANNEL or --can-log FILE")
    return open_sources(serial=args.serial, can_channel=args.can, can_interface=args.can_interface,
                        can_node=args.can_node, can_sensor=args.can_sensor, replay_path=args.replay,
                        replay_recording=recording,
                        realtime=args.realtime, speed=args.speed, max_samples=max_samples, can_log=args.can_log,
                        dbc=args.dbc, dbc_map=args.dbc_map)


def print_stream_stats(stream) -> None:
    for source in stream.sources:
        if hasattr(source, "summary"):  # a CAN log: frames read, decoded and skipped, always said
            print(source.summary())
            continue
        s = source.stats
        if s.malformed or s.late or s.ignored or s.reanchored:
            print(f"{s.name}: {s.samples} samples, {s.malformed} malformed skipped, {s.late} late dropped, "
                  f"{s.ignored} foreign frames ignored, {s.reanchored} clock re-anchorings")


def record_arguments(p) -> None:
    p.add_argument("out", help="recording folder (created, or appended to: never overwritten)")
    stream_arguments(p)
    p.add_argument("--duration", type=positive_float, help="stop after this many seconds (default: until Ctrl-C)")


def record(args) -> None:
    from selfcal.io.recorder import record_stream
    stream = open_stream(args)
    try:
        counts = record_stream(stream.samples, Path(args.out), duration_s=args.duration, max_samples=args.max_samples,
                               stop=stream.stop)
    finally:
        stream.close()
    for name, c in counts.items():
        print(f"{name}: {c['written']} samples written" + (f", {c['dropped']} dropped" if c["dropped"] else "")
              + (f", cut a partial line of {c['repaired_bytes']} bytes" if c["repaired_bytes"] else ""))
    print_stream_stats(stream)


def track_arguments(p) -> None:
    stream_arguments(p)
    # not `choices`: an unknown name is refused by pipelines.track.make_estimator, which names the known ones
    p.add_argument("--system", default="tracker",
                   help=f"online estimator, one of {', '.join(registry.names('online'))} (default: tracker)")
    outputs = p.add_argument_group("outputs")
    outputs.add_argument("--out-tum", help="poses, TUM format (t x y z qx qy qz qw), appended line by line")
    outputs.add_argument("--out-jsonl", help="one JSON object per pose: covariance and fault flags included")
    outputs.add_argument("--append", action="store_true", help="continue existing output files after the last "
                                                                    "pose already in them")
    p.add_argument("--sensors-from", metavar="REC", help="recording whose sensor.yaml files configure the "
                                                         "estimator (default: the --replay recording)")


def track(args) -> None:
    from selfcal.pipelines.track import check_replay, make_estimator, run_track, sensor_meta
    if not args.out_tum and not args.out_jsonl:
        raise UsageError("nothing to write: give --out-tum POSES.tum and/or --out-jsonl POSES.jsonl")
    if args.replay and not (args.serial or args.can or args.can_log):  # the recording is the whole input
        recording = check_replay(args.system, args.replay)
    else:
        recording = None
    meta_from = args.sensors_from or args.replay
    estimator = make_estimator(args.system, sensor_meta(meta_from) if meta_from else {})
    stream = open_stream(args, max_samples=args.max_samples, recording=recording)
    try:
        result = run_track(stream.samples, estimator, out_tum=args.out_tum, out_jsonl=args.out_jsonl,
                           append=args.append)
    finally:
        stream.close()
    if result.outputs == 0 and not args.append:  # nothing estimated: no empty file that looks like a result
        from pathlib import Path

        from selfcal.pipelines.track import TrackError
        for out in (args.out_tum, args.out_jsonl):
            if out and Path(out).is_file() and Path(out).stat().st_size == 0:
                Path(out).unlink()
        raise TrackError(f"no pose from {result.samples} samples: the sensors never gave the estimator enough to "
                         "start (too short, or a sensor missing)")
    try:
        getattr(estimator, "check", lambda: None)()  # can the run be vouched for, now that it is whole
    except Exception:
        if args.replay and not args.append:  # a recording's replay is refused whole, as its batch path would be
            from pathlib import Path
            for out in (args.out_tum, args.out_jsonl):
                if out:
                    Path(out).unlink(missing_ok=True)
        raise
    if result.skipped:  # --append resumed after the poses already written
        print("--append: " + ", ".join(f"{n} poses already in {path} (at or before its last pose) skipped"
                                       for path, n in result.skipped.items()), file=sys.stderr)
    print(result.summary())
    print_stream_stats(stream)


VERBS = (
    Verb("record", "record live streams (serial, CAN) into a recording folder, append-safe", record_arguments, record),
    Verb("track", "online pose estimation from live streams or a replayed recording", track_arguments, track),
)
