"""``selfcal calibrate imu-pair``: rotation (clock offset, lever arm) between two rigidly mounted IMUs."""
from __future__ import annotations

import argparse

from selfcal.cli.common import UsageError, Verb, write_yaml


def calibrate_arguments(p) -> None:
    p.add_argument("recording")
    p.add_argument("--imu0", help="reference IMU (default: first)")
    p.add_argument("--imu1", help="second IMU (default: second)")
    p.add_argument("--lever-arm", action=argparse.BooleanOptionalAction, default=None,
                   help="estimate the lever arm (default: where the data determine it)")
    p.add_argument("--time-offset", action=argparse.BooleanOptionalAction, default=None,
                   help="estimate the clock offset (default: where the data determine it)")
    p.add_argument("--gains", action=argparse.BooleanOptionalAction, default=False,
                   help="also estimate imu1's scale and non-orthogonality relative to imu0 (for IMUs whose "
                        "intrinsics were not calibrated first)")
    p.add_argument("--lowpass-hz", type=float, default=5.0,
                   help="zero-phase low-pass applied to both IMUs before the dynamic pairs, Hz (0: none)")
    p.add_argument("--out", help="calibration YAML to write")


def calibrate(args) -> None:
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.imu_pair import calibrate_imu_pair
    rec = read_recording(args.recording)
    names = rec.imu_names()
    imu0 = args.imu0 or (names[0] if names else None)
    imu1 = args.imu1 or (names[1] if len(names) > 1 else None)
    if imu0 is None or imu1 is None:
        raise UsageError(f"{args.recording}: needs two IMU sensor folders, found {names}")
    cal = calibrate_imu_pair(rec, imu0, imu1, lever_arm=args.lever_arm, time_offset=args.time_offset,
                             lowpass_hz=args.lowpass_hz or None, gains=args.gains)
    print(cal.summary())
    if args.out:
        write_yaml(args.out, cal.to_dict())


VERBS = (Verb("calibrate", "rotation (time offset, lever arm) between two rigidly mounted IMUs",
              calibrate_arguments, calibrate),)
