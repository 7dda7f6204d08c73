"""``selfcal calibrate imu``: IMU intrinsics from a multi-position recording."""
from __future__ import annotations

from selfcal.cli.common import UsageError, Verb, log, output, write_yaml


def calibrate_arguments(p) -> None:
    p.add_argument("recording", help="recording folder (ASL layout)")
    p.add_argument("--imu", help="sensor folder to calibrate (default: every IMU)")
    p.add_argument("--gravity", type=float, help="local gravity in m s^-2 (default: sensor.yaml, else 9.80665)")
    p.add_argument("--out", help="calibration YAML to write")
    e = p.add_argument_group("exports for Kalibr and OpenVINS (one IMU; see docs/exports.md)")
    e.add_argument("--kalibr", metavar="IMU_YAML",
                   help="Kalibr's imu.yaml: noise densities and random walks from the Allan analysis of the "
                        "longest rest (largest axis)")
    e.add_argument("--kalibr-chain", metavar="YAML",
                   help="Kalibr imu-chain with the intrinsics (model scale-misalignment: M, A, C_gyro_i, T_i_b)")
    e.add_argument("--openvins", metavar="YAML",
                   help="OpenVINS kalibr_imu_chain.yaml with the intrinsics (model kalibr: Tw, Ta, Tg, R_IMUtoGYRO, "
                        "R_IMUtoACC)")
    e.add_argument("--rostopic", help="rostopic in the exports (default: sensor.yaml's 'rostopic', else /IMU)")


def calibrate(args) -> None:
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.imu import calibrate_imu
    rec = read_recording(args.recording)
    names = [args.imu] if args.imu else rec.imu_names()
    if not names:
        raise UsageError(f"{args.recording}: no IMU sensor folder in this recording")
    exports = any((args.kalibr, args.kalibr_chain, args.openvins))
    if exports and len(names) != 1:
        raise UsageError(f"--kalibr, --kalibr-chain and --openvins describe one IMU: choose one of {names} with --imu")
    out = {}
    for name in names:
        log.info("calibrating %s ...", name)
        cal = calibrate_imu(rec, name, gravity_m_s2=args.gravity)
        print(cal.summary())
        out[name] = cal.to_dict()
    if args.out:
        write_yaml(args.out, out)
    if exports:
        write_exports(args, rec.imu(names[0], gyro_saturation_allowed=True), cal)


def write_exports(args, data, cal) -> None:
    """The Kalibr / OpenVINS files of one calibrated IMU; noise values from the Allan analysis in all of them."""
    from selfcal.io import exports as ex
    from selfcal.io.atomic import atomic_write_text
    from selfcal.pipelines.imu import kalibr_noise_values
    noise, note = kalibr_noise_values(data)
    if note:
        log.warning(note)
    meta = {**data.meta, **{k: v.value for k, v in noise.items()}}
    topic = args.rostopic or data.meta.get("rostopic") or f"/{data.name}"
    header = f"selfcal calibrate imu {args.recording} ({data.name})"
    e = cal.estimate
    if args.kalibr:
        atomic_write_text(output(args.kalibr), ex.kalibr_imu_yaml_text(topic, data.rate_hz, noise, header))
    intrinsics = ex.kalibr_intrinsics(e.accel.M, e.gyro.M, e.gyro.A)
    if args.kalibr_chain:
        chain = {"imu0": ex.kalibr_imu_entry(meta, topic, data.rate_hz, ex.homogeneous(intrinsics.C_i_S, [0, 0, 0]),
                                             intrinsics=intrinsics)}
        atomic_write_text(output(args.kalibr_chain), ex.yaml_text(chain, header + "\nKalibr imu-chain; T_i_b rotates "
                                                                "selfcal's IMU frame into Kalibr's (docs/exports.md)"))
    if args.openvins:
        chain = {"imu0": ex.openvins_imu_entry(meta, topic, data.rate_hz, intrinsics)}
        atomic_write_text(output(args.openvins), "%YAML:1.0\n" + ex.yaml_text(chain, header + "\nOpenVINS IMU "
                                                                            "intrinsics, model kalibr (docs/exports.md)"))
    for path in (args.kalibr, args.kalibr_chain, args.openvins):
        if path:
            log.info("wrote %s", path)


VERBS = (Verb("calibrate", "IMU intrinsics from a multi-position recording (no external equipment)",
              calibrate_arguments, calibrate),)
