"""``selfcal calibrate imu-pair``: rotation (clock offset, lever arm) between two rigidly mounted IMUs."""
from __future__ import annotations

import argparse

from selfcal.cli.common import UsageError, Verb, output, write_yaml


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
    p.add_argument("--kalibr", metavar="YAML",
                   help="Kalibr imu-chain of the two IMUs (imu1: T_i_b, time_offset; see docs/exports.md)")


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
    if args.kalibr:
        write_kalibr_chain(args, rec.imu(imu0), rec.imu(imu1), cal)


def write_kalibr_chain(args, data0, data1, cal) -> None:
    """Kalibr's imu-chain (model ``calibrated``): imu0 the reference, imu1 with T_i_b and time_offset."""
    from selfcal.io import exports as ex
    from selfcal.io.atomic import atomic_write_text
    e = cal.estimate
    header = f"selfcal calibrate imu-pair {args.recording} ({data0.name}, {data1.name}): Kalibr imu-chain"
    if e.gains:
        header += "\nimu1's relative gains (--gains) are not in this file: Kalibr's model 'calibrated' has none"
    chain = {"imu0": ex.kalibr_imu_entry(data0.meta, data0.meta.get("rostopic", f"/{data0.name}"), data0.rate_hz),
             "imu1": ex.kalibr_imu_entry(data1.meta, data1.meta.get("rostopic", f"/{data1.name}"), data1.rate_hz,
                                         ex.kalibr_pair_T_i_b(e.R_imu0_imu1, e.lever_arm_m), e.time_offset_s or 0.0)}
    atomic_write_text(output(args.kalibr), ex.yaml_text(chain, header))


VERBS = (Verb("calibrate", "rotation (time offset, lever arm) between two rigidly mounted IMUs",
              calibrate_arguments, calibrate),)
