"""Command line: ``selfcal <verb> ...``.  Parsing, progress and exit codes only; the work is in pipelines/."""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np
import yaml

log = logging.getLogger("selfcal")


class UsageError(Exception):
    """A mistake in the command line: reported in one line, exit code 1."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse would print the usage and exit 2; we promise one line and exit 1
        raise UsageError(f"{message} (see: {self.prog} --help)")


def _output(path) -> Path:
    """An output path whose folder exists (created if needed: `--out results/cal.yaml` just works)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def _write_yaml(path, data: dict) -> None:
    from selfcal.io.atomic import atomic_write_text
    atomic_write_text(_output(path), yaml.safe_dump(data, sort_keys=False, default_flow_style=None))
    log.info("wrote %s", path)


def _cmd_calibrate_imu(args) -> None:
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.imu_calibration import calibrate_imu
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
        _write_yaml(args.out, out)


def _cmd_calibrate_imu_pair(args) -> None:
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.imu_calibration import calibrate_imu_pair
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
        _write_yaml(args.out, cal.to_dict())


def _cmd_audit(args) -> None:
    from selfcal.io.atomic import atomic_write_text
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.audit import audit_recording
    if not args.json and not args.report:
        raise UsageError("nothing to write: give --json OUT.json and/or --report OUT.html")
    rec = read_recording(args.recording)
    sensors = [name for name in (args.imu, args.imu1) if name] or None
    run = audit_recording(rec, args.system, args.base, sensors, progress=log.info)
    for finding in run.to_json()["findings"]:
        print(f"found {finding['effect']} ({finding['target']}): RMS {finding['gain']['rms_before']:.4g} -> "
              f"{finding['gain']['rms_after']:.4g}, held-out {finding['gain']['heldout_rms_before']:.4g} -> "
              f"{finding['gain']['heldout_rms_after']:.4g}"
              + (" [ambiguous with " + ", ".join(r["effect"] for r in finding["ambiguous_with"]) + "]"
                 if finding.get("ambiguous_with") else ""))
    if not run.to_json()["findings"]:
        print("no finding: the data give no significant evidence against the base model")
    if args.json:
        atomic_write_text(_output(args.json), json.dumps(run.to_json(), indent=1, default=_plain) + "\n")
        log.info("wrote %s", args.json)
    if args.report:
        from selfcal.audit.report import write_report
        write_report(run.result, _output(args.report), run.report_extras(str(args.recording)))
        print(f"report: {args.report}")


def _plain(obj):
    """JSON for numpy scalars and arrays."""
    import numpy as np
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _cmd_smooth_ship(args) -> None:
    from selfcal.io.atomic import atomic_write_text
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.ship import smooth_ship, tum_text
    rec = read_recording(args.recording)
    est = smooth_ship(rec, online=args.online, remove_known_acceleration=not args.keep_known_acceleration,
                      imu_name=args.imu)
    print(f"{len(est.t_s)} attitudes over {est.t_s[-1] - est.t_s[0]:.0f} s in {est.seconds:.1f} s "
          f"({'iSAM2 online' if args.online else 'batch'}); final gyro bias "
          f"{np.degrees(est.gyro_bias[-1]) * 3600} deg/h")
    if args.out:
        atomic_write_text(_output(args.out), tum_text(est, int(rec.sensors[args.imu].t_ns[0])))
        print(f"trajectory: {args.out}")


def _cmd_import(args) -> None:
    from selfcal.io.importers import IMPORTERS
    from selfcal.io.recording import write_recording
    if args.kind not in IMPORTERS:
        raise UsageError(f"unknown dataset kind {args.kind!r}; known: {', '.join(sorted(IMPORTERS))}")
    rec = IMPORTERS[args.kind](Path(args.source))
    path = write_recording(rec, Path(args.out), overwrite=args.overwrite)
    print(f"wrote {path} ({', '.join(rec.sensors)})")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="selfcal", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="progress and diagnostics on stderr")
    verbs = parser.add_subparsers(dest="verb", required=True, parser_class=_Parser)

    calibrate = verbs.add_parser("calibrate", help="calibrate a sensor system from a recording")
    systems = calibrate.add_subparsers(dest="system", required=True, parser_class=_Parser)
    p = systems.add_parser("imu", help="IMU intrinsics from a multi-position recording (no external equipment)")
    p.add_argument("recording", help="recording folder (ASL layout)")
    p.add_argument("--imu", help="sensor folder to calibrate (default: every IMU)")
    p.add_argument("--gravity", type=float, help="local gravity in m s^-2 (default: sensor.yaml, else 9.80665)")
    p.add_argument("--out", help="calibration YAML to write")
    p.set_defaults(run=_cmd_calibrate_imu)

    p = systems.add_parser("imu-pair", help="rotation (time offset, lever arm) between two rigidly mounted IMUs")
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
    p.set_defaults(run=_cmd_calibrate_imu_pair)

    p = verbs.add_parser("audit", help="find what the model gets wrong in a recording, name the cause, measure the gain")
    p.add_argument("recording")
    p.add_argument("--system", required=True, choices=["imu", "imu-pair"])
    p.add_argument("--base", help="base model: imu: bias (default) or standard; imu-pair: rotation")
    p.add_argument("--imu", help="IMU to audit (imu) or reference IMU (imu-pair); default: the first")
    p.add_argument("--imu1", help="second IMU for imu-pair; default: the second")
    p.add_argument("--json", help="findings in the audit JSON contract")
    p.add_argument("--report", help="HTML report with plots")
    p.set_defaults(run=_cmd_audit)

    smooth = verbs.add_parser("smooth", help="smooth a recording offline (or replay it online with --online)")
    smoothers = smooth.add_subparsers(dest="system", required=True, parser_class=_Parser)
    p = smoothers.add_parser("ship", help="vessel attitude and gyro drift from gyro + accelerometer tilt")
    p.add_argument("recording")
    p.add_argument("--imu", default="imu0")
    p.add_argument("--online", action="store_true", help="iSAM2, keyframe by keyframe, as a live system would")
    p.add_argument("--keep-known-acceleration", action="store_true",
                   help="do not subtract surge and centripetal acceleration from speed log / GPS and yaw rate")
    p.add_argument("--out", help="TUM trajectory file (t x y z qx qy qz qw)")
    p.set_defaults(run=_cmd_smooth_ship)

    p = verbs.add_parser("import", help="convert a public dataset into a recording")
    p.add_argument("kind", help="dataset kind: imu-tk-xsens, mpu6050-tomisuarez, ansfl-quadrotor")
    p.add_argument("source", help="dataset file or folder")
    p.add_argument("out", help="recording folder to write")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(run=_cmd_import)
    return parser


def main(argv=None) -> int:
    from selfcal.errors import USER_ERRORS
    try:
        args = build_parser().parse_args(argv)
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                            format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
        args.run(args)
    except (UsageError, *USER_ERRORS) as err:
        print(f"selfcal: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("selfcal: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
