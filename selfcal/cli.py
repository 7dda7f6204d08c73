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
        _write_yaml(args.out, out)


def _cmd_calibrate_imu_pair(args) -> None:
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


def _cmd_smooth_scan(args) -> None:
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.scan import smooth_scan
    if args.out and Path(args.out).suffix.lower() not in (".ply", ".pcd", ".xyz", ".pts"):
        raise UsageError(f"{args.out}: the corrected scan is written as .ply, .pcd, .xyz or .pts")
    est = smooth_scan(read_recording(args.recording), online=args.online)
    print(est.summary())
    if args.out:
        from selfcal.io.pointcloud import write_point_cloud
        write_point_cloud(_output(args.out), est.points_W)
        print(f"corrected scan: {args.out}")
    if args.estimates:
        _write_yaml(args.estimates, est.to_dict())


def _cmd_smooth_tracker(args) -> None:
    from selfcal.io.atomic import atomic_write_text
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.tracker import smooth_tracker
    result = smooth_tracker(read_recording(args.recording), mode=args.mode, gating=not args.no_gating)
    c = result.counts
    print(f"{len(result.t_ns)} poses in {result.seconds:.1f} s ({args.mode}); measurements accepted {c['accepted']}, "
          f"rejected {c['rejected']}, held out {c['held_out']}, removed after a soft-fault alarm {c['removed']}")
    atomic_write_text(_output(args.out), result.tum_text())
    print(f"trajectory: {args.out}")
    if args.log:
        atomic_write_text(_output(args.log), result.decisions_jsonl())
        print(f"decisions: {args.log}")


def _cmd_simulate_tracker(args) -> None:
    from selfcal.sim.tracker import TrackerScenario
    sc = TrackerScenario(duration_s=args.duration, seed=args.seed, faults=args.faults,
                         advance_mm_s=args.advance_mm_s, burst_rate_per_min=args.bursts_per_min)
    sc.write(args.out, seed=args.noise_seed, overwrite=args.overwrite)
    print(f"wrote {args.out}: {args.duration:.0f} s, {len(sc.bursts)} vibration bursts, {len(sc.faults)} injected "
          f"faults (truth/truth.yaml, truth/poses.tum)")


def _cmd_simulate_scan(args) -> None:
    from selfcal.sim.scan import ScanScenario, simulate_scan, write_scan_recording
    sim = simulate_scan(ScanScenario(length_m=args.length, n_spheres=args.spheres), seed=args.seed)
    write_scan_recording(sim, Path(args.out), overwrite=args.overwrite)
    print(f"wrote {args.out}: {len(sim.points_V)} clocks, {sum(len(p) for p in sim.points_V)} points, "
          f"{len(sim.sphere_centers)} spheres (reference mesh: {Path(args.out) / 'truth' / 'reference_mesh.ply'})")


def _cmd_simulate_encoder(args) -> None:
    from selfcal.pipelines.encoder import simulate_encoder
    options = {"n_positions": args.positions, "n_diodes": args.diodes, "l": args.code_bits,
               "cells_per_image": args.cells_per_image, "n_arrays": args.arrays, "noise_sigma": args.noise,
               "harmonic_rad": args.graduation_harmonic, "random_rad": args.graduation_random,
               "eccentricity": tuple(args.eccentricity), "prnu_sigma": args.prnu,
               "temperature_scale_per_degC": args.temperature_scale,
               "temperature_range_degC": args.temperature_range,
               "temperature_profile": args.temperature_profile, "a0_per_degC": args.a0_per_degc,
               "aperture_per_degC": args.aperture_per_degc, "intensity_per_degC": args.light_per_degc,
               "frame_period_s": args.frame_period}
    result = simulate_encoder(args.out, seed=args.seed, overwrite=args.overwrite,
                              reference_every=args.reference_every, reference_sigma_rad=args.reference_sigma,
                              **options)
    print(result.summary())


def _cmd_calibrate_encoder(args) -> None:
    from selfcal.io.atomic import atomic_write_bytes
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.encoder import calibrate_encoder
    cal = calibrate_encoder(read_recording(args.recording), use_reference=not args.no_reference)
    print(cal.summary())
    if args.out:
        out = _output(args.out)
        cov_path = out.with_suffix(".cov.npy")
        atomic_write_bytes(cov_path, cal.covariance_bytes())
        _write_yaml(out, cal.to_dict(cov_path.name))
        print(f"calibration: {out} (joint covariance: {cov_path})")


def _cmd_measure_encoder(args) -> None:
    from selfcal.io.encoder import EncoderRecordingError, write_angles_csv
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.encoder import measure_encoder
    try:
        calibration = yaml.safe_load(Path(args.calibration).read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        raise EncoderRecordingError(f"{args.calibration}: invalid YAML ({err})") from None
    if not isinstance(calibration, dict) or calibration.get("system") != "encoder":
        raise EncoderRecordingError(f"{args.calibration}: not an encoder calibration (system: encoder)")
    covariance = None
    if calibration.get("covariance_file"):
        cov_path = Path(args.calibration).parent / calibration["covariance_file"]
        if cov_path.is_file():
            covariance = np.load(cov_path, allow_pickle=False)
        else:
            log.warning("%s not found: sigmas without the calibration's own uncertainty", cov_path)
    if args.out_calibration and not args.track_drift:
        raise EncoderRecordingError("--out-calibration needs --track-drift (only a durable run updates it)")
    result = measure_encoder(read_recording(args.recording), calibration, covariance, array=args.array,
                             track_drift=args.track_drift)
    print(result.summary())
    if args.out:
        write_angles_csv(_output(args.out), result.t_ns, result.beta_rad, result.sigma_rad, result.flags,
                         result.drift_columns)
        print(f"angles: {args.out}")
    if args.out_calibration:
        import io
        from selfcal.io.atomic import atomic_write_bytes
        out = _output(args.out_calibration)
        cov_path = out.with_suffix(".cov.npy")
        buf = io.BytesIO()
        np.save(buf, result.updated_covariance, allow_pickle=False)
        atomic_write_bytes(cov_path, buf.getvalue())
        _write_yaml(out, {**result.updated_calibration, "covariance_file": cov_path.name})
        print(f"updated calibration: {out} (joint covariance: {cov_path})")


def _cmd_import(args) -> None:
    from selfcal.io.importers import IMPORTERS
    from selfcal.io.recording import write_recording
    if args.kind not in IMPORTERS:
        raise UsageError(f"unknown dataset kind {args.kind!r}; known: {', '.join(sorted(IMPORTERS))}")
    rec = IMPORTERS[args.kind](Path(args.source))
    path = write_recording(rec, Path(args.out), overwrite=args.overwrite)
    print(f"wrote {path} ({', '.join(rec.sensors)})")


QC_EXIT_CODES = {"pass": 0, "reported": 0, "fail": 3, "incomplete": 4}  # 1 is an error, 2 a usage error


def _cmd_qc(args) -> int:
    from selfcal.io.atomic import atomic_write_text
    from selfcal.io.pointcloud import read_point_cloud, read_triangle_mesh
    from selfcal.pipelines.qc.checks import run_qc
    from selfcal.pipelines.qc.report import write_reports
    from selfcal.pipelines.qc.spec import QCSpec
    if not (args.report or args.markdown or args.json):
        raise UsageError("nothing to write: give --report OUT.html, --markdown OUT.md and/or --json OUT.json")
    spec = QCSpec.from_yaml(args.spec) if args.spec else QCSpec()
    mesh = read_triangle_mesh(args.reference) if args.reference else None
    loaded = read_point_cloud(args.scan, drop_nonfinite=True)
    result = run_qc(loaded, spec, mesh, args.reference, progress=log.info)
    for check in result.checks:
        value = "-" if check.value is None else (f"{check.value:.4g}" if check.unit == "fraction"
                                                 else f"{check.value * 1e3:.4g} mm")
        print(f"{check.name}: {value} [{check.status}]" + (f" ({check.note})" if check.value is None else ""))
    for warning in result.warnings:
        print(f"warning: {warning}")
    print(f"verdict: {result.verdict} ({result.seconds['total']:.1f} s)")
    written = write_reports(result, html_path=_output(args.report) if args.report else None,
                            markdown_path=_output(args.markdown) if args.markdown else None,
                            png_path=_output(args.png) if args.png else None)
    if args.json:
        written["json"] = atomic_write_text(_output(args.json),
                                            json.dumps(result.to_json(), indent=1, default=_plain) + "\n")
    for kind, path in written.items():
        print(f"{kind}: {path}")
    return QC_EXIT_CODES[result.verdict]  # a CI job fails on a failed part without parsing the report


def _cmd_fleet(args) -> None:
    import time

    from selfcal.pipelines.fleet import run_fleet, write_fleet_report, write_table
    if not args.verbose:  # dask logs every scheduler and worker start at INFO; the progress line says enough
        import distributed  # noqa: F401  (it sets its loggers' levels when imported: quiet them after that)
        logging.getLogger("distributed").setLevel(logging.WARNING)
    options = {"system": args.system, "imu": args.imu, "imu1": args.imu1}
    for item in args.option or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--option {item!r}: expected KEY=VALUE")
        options[key.strip().replace("-", "_")] = yaml.safe_load(value)
    if not args.out.lower().endswith((".csv", ".parquet")):
        raise UsageError(f"--out {args.out}: the table is TABLE.csv or TABLE.parquet (both are written)")
    start = time.perf_counter()
    failed = 0
    tty = sys.stderr.isatty()

    def progress(done, total, row):  # one status line, redrawn in place on a terminal
        nonlocal failed
        failed += not row.get("ok")
        width = 30
        bar = "#" * (width * done // total) + "-" * (width - width * done // total)
        line = (f"fleet [{bar}] {done}/{total} done, {failed} failed, {time.perf_counter() - start:.0f} s"
                + ("" if row.get("ok") else f" ({row.get('name', '?')}: {row.get('error')})"))
        print(("\r" + line[:150].ljust(150)) if tty else line, end="" if tty and done < total else "\n",
              file=sys.stderr, flush=True)

    result = run_fleet(args.source, args.task, options, scheduler=args.scheduler, workers=args.workers,
                       progress=progress)
    paths = write_table(result.table, _output(args.out))
    print(f"{len(result.table)} recordings, {result.n_failed} failed, {result.seconds:.1f} s on "
          f"{result.workers} worker(s); table: {', '.join(map(str, paths))}")
    if args.report:
        print(f"report: {write_fleet_report(result, _output(args.report))}")


def _open_stream_from_args(args, max_samples=None):
    from selfcal.io.streams import open_stream
    if not (args.serial or args.can or args.replay):
        raise UsageError("no source: give --serial PORT[:BAUD][,TYPE=sensor...], --can CHANNEL and/or --replay REC")
    return open_stream(serial=args.serial, can_channel=args.can, can_interface=args.can_interface,
                       can_node=args.can_node, can_sensor=args.can_sensor, replay_path=args.replay,
                       realtime=args.realtime, speed=args.speed, max_samples=max_samples)


def _print_stream_stats(stream) -> None:
    for s in stream.stats():
        if s.malformed or s.late or s.ignored:
            print(f"{s.name}: {s.samples} samples, {s.malformed} malformed skipped, {s.late} late dropped, "
                  f"{s.ignored} foreign frames ignored")


def _cmd_record(args) -> None:
    from selfcal.io.recorder import record_stream
    stream = _open_stream_from_args(args)
    try:
        counts = record_stream(stream.samples, Path(args.out), duration_s=args.duration, max_samples=args.max_samples)
    finally:
        stream.close()
    for name, c in counts.items():
        print(f"{name}: {c['written']} samples written" + (f", {c['dropped']} dropped" if c["dropped"] else "")
              + (f", cut a partial line of {c['repaired_bytes']} bytes" if c["repaired_bytes"] else ""))
    _print_stream_stats(stream)


def _cmd_track(args) -> None:
    from selfcal.pipelines.track import make_estimator, run_track, sensor_meta
    if not args.out_tum and not args.out_jsonl:
        raise UsageError("nothing to write: give --out-tum POSES.tum and/or --out-jsonl POSES.jsonl")
    meta_from = args.sensors_from or args.replay
    estimator = make_estimator(args.system, sensor_meta(meta_from) if meta_from else {})
    stream = _open_stream_from_args(args, max_samples=args.max_samples)
    try:
        result = run_track(stream.samples, estimator, out_tum=args.out_tum, out_jsonl=args.out_jsonl,
                           append=args.append)
    finally:
        stream.close()
    print(result.summary())
    _print_stream_stats(stream)


def _cmd_calibrate_stationing(args) -> None:
    from selfcal.pipelines.stationing import calibrate_stationing, heldout_stationing
    cal = calibrate_stationing(args.datasets, urdf=args.urdf)
    print(cal.summary())
    out = cal.to_dict()
    if args.heldout:
        out["heldout"] = {}
        for path in args.heldout:
            h = heldout_stationing(cal.calibration, path, urdf=args.urdf)
            out["heldout"][h.name] = h.to_dict()
            print(f"held out {h.name}: evaluation points predicted from stationing points, RMS "
                  f"{np.round(h.rms_m * 1e3, 2).tolist()} mm (3D {np.linalg.norm(h.rms_m) * 1e3:.2f}); rigid "
                  f"stations with the URDF lever arm: {np.linalg.norm(h.baseline_rms_m) * 1e3:.2f} mm")
    if args.out:
        _write_yaml(args.out, out)


def _add_stream_options(p) -> None:
    p.add_argument("--serial", action="append", metavar="PORT[:BAUD][,TYPE=sensor...]",
                   help="serial port speaking the line protocol of docs/streams.md (repeatable); e.g. "
                        "/dev/ttyUSB0:115200,IMU=imu0,TRK=tracker0 (default mapping IMU=imu0,INC=incl0,"
                        "TRK=tracker0,CAM=cam0)")
    p.add_argument("--can", metavar="CHANNEL", help="CAN channel of a CANopen-style inclinometer (e.g. can0)")
    p.add_argument("--can-interface", default="socketcan", help="python-can interface: socketcan (default), "
                                                                 "virtual, ...")
    p.add_argument("--can-node", type=int, default=1, help="CANopen node id (TPDO1 COB-ID 0x180+node), default 1")
    p.add_argument("--can-sensor", default="incl0", help="sensor name of the CAN inclinometer (default incl0)")
    p.add_argument("--replay", metavar="REC", help="replay a recording (as fast as possible unless --realtime)")
    p.add_argument("--realtime", action="store_true", help="replay at the recording's own pace")
    p.add_argument("--speed", type=float, default=1.0, help="with --realtime: playback speed factor")
    p.add_argument("--max-samples", type=int, help="stop after this many samples")


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

    p = systems.add_parser("stationing", help="prism lever arm, column bend and tilt-accelerometer mountings of a "
                                              "mobile manipulator from total-station stationing datasets")
    p.add_argument("datasets", nargs="+", help="dataset YAML file(s) (Hilti stationing format), fitted jointly")
    p.add_argument("--urdf", help="robot URDF (default: trailblazer.urdf next to the first dataset)")
    p.add_argument("--heldout", nargs="+", metavar="DATASET.yaml",
                   help="apply the calibration to these files: station from the stationing points, predict the "
                        "evaluation points, report the RMS against the total station")
    p.add_argument("--out", help="calibration YAML to write")
    p.set_defaults(run=_cmd_calibrate_stationing)

    p = systems.add_parser("encoder", help="optical angle encoder self-calibration from its own diode-array frames")
    p.add_argument("recording", help="recording folder with array0/frames.npy (and optional reference/)")
    p.add_argument("--out", help="calibration YAML to write (joint covariance next to it as .cov.npy)")
    p.add_argument("--no-reference", action="store_true", help="ignore reference/ (pure self-calibration)")
    p.set_defaults(run=_cmd_calibrate_encoder)

    p = verbs.add_parser("audit", help="find what the model gets wrong in a recording, name the cause, measure the gain")
    p.add_argument("recording")
    p.add_argument("--system", required=True, choices=["imu", "imu-pair", "encoder", "scan", "ship", "tracker"])
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
    p = smoothers.add_parser("scan", help="mobile stereo scan: INS drift corrected by sphere targets (patent 001)")
    p.add_argument("recording")
    p.add_argument("--online", action="store_true", help="iSAM2, sphere by sphere, as the scan proceeds")
    p.add_argument("--out", help="corrected point cloud (.ply, .pcd)")
    p.add_argument("--estimates", help="YAML with the 15 INS error terms and sphere centres, each with its 1-sigma")
    p.set_defaults(run=_cmd_smooth_scan)
    p = smoothers.add_parser("tracker", help="laser tracker + inclinometer + beam camera + IMU, fault-gated (patent 004)")
    p.add_argument("recording")
    p.add_argument("--mode", choices=["batch", "isam2", "fixed-lag"], default="batch",
                   help="batch: LM over all keyframes after the online gating pass; isam2 / fixed-lag: online poses")
    p.add_argument("--no-gating", action="store_true", help="no chi-square gate, no soft-fault detector")
    p.add_argument("--out", required=True, help="TUM trajectory file (t x y z qx qy qz qw) of the IMU body frame")
    p.add_argument("--log", help="JSON lines: every gating decision with its statistic and threshold")
    p.set_defaults(run=_cmd_smooth_tracker)

    p = verbs.add_parser("import", help="convert a public dataset into a recording")
    p.add_argument("kind", help="dataset kind: imu-tk-xsens, mpu6050-tomisuarez, ansfl-quadrotor")
    p.add_argument("source", help="dataset file or folder")
    p.add_argument("out", help="recording folder to write")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(run=_cmd_import)

    simulate = verbs.add_parser("simulate", help="write a simulated recording (ground truth in truth/)")
    _simulators = simulate.add_subparsers(dest="system", required=True, parser_class=_Parser)
    p = _simulators.add_parser("scan", help="mobile stereo line-scan + INS through a tunnel with spheres (patent 001)")
    p.add_argument("--out", required=True, help="recording folder to write")
    p.add_argument("--length", type=float, default=24.0, help="scanned length, m")
    p.add_argument("--spheres", type=int, default=10, help="number of sphere targets")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(run=_cmd_simulate_scan)
    p = _simulators.add_parser("encoder", help="self-calibrating optical angle encoder (patent 000)")
    p.add_argument("--out", required=True, help="recording folder to write")
    p.add_argument("--positions", type=int, default=240, help="disk positions N (default 240)")
    p.add_argument("--diodes", type=int, default=1024, help="diodes per array n (default 1024)")
    p.add_argument("--code-bits", type=int, default=10, help="m-sequence bits l, m = 2^l - 1 cells (default 10)")
    p.add_argument("--cells-per-image", type=float, default=51.0,
                   help="code cells imaged on the array (default 51: each cell in ~12 frames, as the patent asks)")
    p.add_argument("--arrays", type=int, default=1, help="diode arrays on the disk (default 1)")
    p.add_argument("--noise", type=float, default=2.0, help="diode noise, counts (default 2)")
    p.add_argument("--graduation-harmonic", type=float, default=2e-6, help="amplitude of each low harmonic "
                   "of the graduation error, rad")
    p.add_argument("--graduation-random", type=float, default=1e-6, help="random per-edge graduation error, rad")
    p.add_argument("--eccentricity", type=float, nargs=2, default=(0.0, 0.0), metavar=("EX", "EY"),
                   help="code centre offset from the axis, code radii")
    p.add_argument("--prnu", type=float, default=0.0, help="per-diode gain non-uniformity, 1 sigma (relative)")
    p.add_argument("--temperature-scale", type=float, default=0.0, help="dp/p per degC")
    p.add_argument("--temperature-range", type=float, default=0.0, help="temperature swing, degC")
    p.add_argument("--temperature-profile", choices=["centred", "ramp"], default="centred",
                   help="temperature about 25 degC (centred) or rising from 25 degC (ramp: a run after a calibration)")
    p.add_argument("--a0-per-degc", type=float, default=0.0, help="dark level drift, counts per degC")
    p.add_argument("--aperture-per-degc", type=float, default=0.0, help="relative aperture (blur) drift per degC")
    p.add_argument("--light-per-degc", type=float, default=0.0, help="relative light level drift per degC")
    p.add_argument("--frame-period", type=float, default=1.0, help="time between frames, s (default 1)")
    p.add_argument("--reference-every", type=int, default=0, help="write reference/ angles for every k-th position")
    p.add_argument("--reference-sigma", type=float, default=1e-6, help="reference angle noise, rad")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(run=_cmd_simulate_encoder)
    p = _simulators.add_parser("tracker", help="TBM laser-tracker target with vibration bursts and faults (patent 004)")
    p.add_argument("--out", required=True, help="recording folder to write")
    p.add_argument("--duration", type=float, default=600.0, help="run length, s")
    p.add_argument("--faults", action="store_true", help="inject the default fault schedule (truth/ logs it)")
    p.add_argument("--advance-mm-s", type=float, default=1.0, help="advance speed, mm/s")
    p.add_argument("--bursts-per-min", type=float, default=2.0, help="mean vibration bursts per minute")
    p.add_argument("--seed", type=int, default=0, help="scenario seed (motion, bursts, biases, faults)")
    p.add_argument("--noise-seed", type=int, default=1, help="white-noise seed")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(run=_cmd_simulate_tracker)

    measure = verbs.add_parser("measure", help="measure with a calibrated instrument")
    _measurers = measure.add_subparsers(dest="system", required=True, parser_class=_Parser)
    p = _measurers.add_parser("encoder", help="ML angle (and 1-sigma) of every frame with an encoder calibration")
    p.add_argument("recording", help="recording folder with array0/frames.npy")
    p.add_argument("--calibration", required=True, help="calibration YAML of `selfcal calibrate encoder`")
    p.add_argument("--array", default="array0", help="array to read (default array0)")
    p.add_argument("--out", help="angles CSV (timestamp, angle, sigma, valid, flag)")
    p.add_argument("--track-drift", action="store_true",
                   help="durable self-calibration: iSAM2 follows the drifting geometry, aperture and dark level "
                        "from the frames (extra columns in --out), starting from the calibration as a prior")
    p.add_argument("--out-calibration", help="with --track-drift: write the updated calibration YAML (+ .cov.npy)")
    p.set_defaults(run=_cmd_measure_encoder)

    p = verbs.add_parser("record", help="record live streams (serial, CAN) into a recording folder, append-safe")
    p.add_argument("out", help="recording folder (created, or appended to: never overwritten)")
    _add_stream_options(p)
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    p.set_defaults(run=_cmd_record)

    p = verbs.add_parser("track", help="online pose estimation from live streams or a replayed recording")
    _add_stream_options(p)
    p.add_argument("--system", default="tracker", help="online estimator (default: tracker)")
    p.add_argument("--out-tum", help="poses, TUM format (t x y z qx qy qz qw), appended line by line")
    p.add_argument("--out-jsonl", help="one JSON object per pose: covariance and fault flags included")
    p.add_argument("--append", action="store_true", help="continue existing output files")
    p.add_argument("--sensors-from", metavar="REC", help="recording whose sensor.yaml files configure the "
                                                         "estimator (default: the --replay recording)")
    p.set_defaults(run=_cmd_track)

    p = verbs.add_parser("qc", help="quality control of a scan (VDI/VDE 2634-2 figures, deviation from a reference)",
                          epilog="exit status: 0 pass (or figures only), 3 fail, 4 incomplete (a toleranced check could not be made), 1 error")
    p.add_argument("scan", help="point cloud: .ply, .pcd, .xyz (or .xyz.gz / .txt columns x y z), metres")
    p.add_argument("--reference", help="reference mesh of the object in the scan's frame (.ply, .stl, .obj, ...)")
    p.add_argument("--spec", help="QC spec YAML: tolerances and detection settings (see docs/qc.md)")
    p.add_argument("--report", help="HTML report to write (deviation image embedded)")
    p.add_argument("--markdown", help="Markdown report to write (deviation image next to it as .png)")
    p.add_argument("--json", help="all figures and checks as JSON")
    p.add_argument("--png", help="deviation image to write (default: next to the Markdown report)")
    p.set_defaults(run=_cmd_qc)

    p = verbs.add_parser("fleet", help="run one task per recording (a production line, a test campaign) on dask")
    p.add_argument("source", help="folder of recordings, or a manifest (.yaml/.csv; see docs/fleet.md)")
    p.add_argument("--task", required=True,
                   help="calibrate-imu, calibrate-imu-pair, calibrate-encoder, audit, or any task a system registered")
    p.add_argument("--out", required=True, help="result table TABLE.csv or TABLE.parquet (both are written)")
    p.add_argument("--report", help="short report: .html (plots embedded) or .md")
    p.add_argument("--scheduler", help="address of a running dask scheduler (default: a local cluster)")
    p.add_argument("--workers", type=int, help="worker processes of the local cluster (default 2)")
    p.add_argument("--system", help="audit: the system (imu or imu-pair)")
    p.add_argument("--imu", help="IMU to use (calibrate-imu, audit; default: the first)")
    p.add_argument("--imu1", help="second IMU (audit imu-pair; default: the second)")
    p.add_argument("--option", action="append", metavar="KEY=VALUE",
                   help="any further task option for every recording (repeatable; value read as YAML)")
    p.set_defaults(run=_cmd_fleet)
    return parser


def main(argv=None) -> int:
    from selfcal.core.errors import USER_ERRORS
    try:
        args = build_parser().parse_args(argv)
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                            format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
        code = args.run(args)
    except (UsageError, *USER_ERRORS) as err:
        print(f"selfcal: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("selfcal: interrupted", file=sys.stderr)
        return 130
    return code or 0


if __name__ == "__main__":
    sys.exit(main())
