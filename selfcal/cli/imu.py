"""``selfcal calibrate imu``: IMU intrinsics from a multi-position recording."""
from __future__ import annotations

from selfcal.cli.common import UsageError, Verb, log, write_yaml


def calibrate_arguments(p) -> None:
    p.add_argument("recording", help="recording folder (ASL layout)")
    p.add_argument("--imu", help="sensor folder to calibrate (default: every IMU)")
    p.add_argument("--gravity", type=float, help="local gravity in m s^-2 (default: sensor.yaml, else 9.80665)")
    p.add_argument("--out", help="calibration YAML to write")


def calibrate(args) -> None:
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.imu import calibrate_imu
    rec = read_recording(args.recording)
    names = [args.imu] if args.imu else rec.imu_names()
    if not names:
        raise UsageError(f"{args.recording}: no IMU sensor folder in this recording")
    out = {}
    for name in names:
        log.info("calibrating %s ...", name)
        cal = calibrate_imu(rec, name, gravity_m_s2=args.gravity)
        print(cal.summary())
        out[name] = cal.to_dict()
    if args.out:
        write_yaml(args.out, out)


VERBS = (Verb("calibrate", "IMU intrinsics from a multi-position recording (no external equipment)",
              calibrate_arguments, calibrate),)
