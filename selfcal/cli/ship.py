"""``selfcal smooth ship``: vessel attitude and gyro drift from gyro + accelerometer tilt (patent 003)."""
from __future__ import annotations

from selfcal.cli.common import UsageError, Verb, output, write_yaml


def smooth_arguments(p) -> None:
    p.add_argument("recording")
    p.add_argument("--imu", default="imu0")
    p.add_argument("--online", action="store_true", help="iSAM2, keyframe by keyframe, as a live system would")
    p.add_argument("--keep-known-acceleration", action="store_true",
                   help="do not subtract surge and centripetal acceleration from speed log / GPS and yaw rate")
    p.add_argument("--out", help="TUM trajectory file (t x y z qx qy qz qw)")
    p.add_argument("--bias-out", help="YAML: the final gyro bias per axis with its 1-sigma, flagged when the voyage "
                                      "does not determine it")
    p.add_argument("--bias-sigma-bound", type=float, default=None, metavar="DEG_H",
                   help="a bias component whose 1-sigma exceeds this is reported as not determined (default 5)")


def smooth(args) -> None:
    if args.bias_sigma_bound is not None and not args.bias_sigma_bound > 0:
        raise UsageError(f"--bias-sigma-bound must be a positive number of deg/h, not {args.bias_sigma_bound}")
    from selfcal.core.progress import TerminalProgress
    from selfcal.io.atomic import atomic_write_text
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.ship import gyro_bias_lines, gyro_bias_report, smooth_ship, tum_text
    with TerminalProgress("smooth ship") as progress:
        progress("read the recording")
        rec = read_recording(args.recording)
        est = smooth_ship(rec, online=args.online, remove_known_acceleration=not args.keep_known_acceleration,
                          imu_name=args.imu, progress=progress)
    report = gyro_bias_report(est, args.bias_sigma_bound)
    print(f"{len(est.t_s)} attitudes over {est.t_s[-1] - est.t_s[0]:.0f} s in {est.seconds:.1f} s "
          f"({'iSAM2 online' if args.online else 'batch'}); final gyro bias:")
    print("\n".join(gyro_bias_lines(report)))
    if args.bias_out:
        write_yaml(args.bias_out, {"gyro_bias": report})
        print(f"gyro bias: {args.bias_out}")
    if args.out:
        atomic_write_text(output(args.out), tum_text(est, int(rec.sensors[args.imu].t_ns[0])))
        print(f"trajectory: {args.out}")


VERBS = (Verb("smooth", "vessel attitude and gyro drift from gyro + accelerometer tilt", smooth_arguments, smooth),)
