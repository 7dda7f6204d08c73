"""``selfcal simulate|calibrate|measure encoder``: the self-calibrating optical angle encoder (patent 000)."""
from __future__ import annotations

from pathlib import Path

from selfcal.cli.common import Verb, log, output, write_yaml


def simulate_arguments(p) -> None:
    p.add_argument("--out", required=True, help="recording folder to write")
    disk = p.add_argument_group("disk and array")
    disk.add_argument("--positions", type=int, default=240, help="disk positions N (default 240)")
    disk.add_argument("--diodes", type=int, default=1024, help="diodes per array n (default 1024)")
    disk.add_argument("--code-bits", type=int, default=10, help="m-sequence bits l, m = 2^l - 1 cells (default 10)")
    disk.add_argument("--cells-per-image", type=float, default=51.0,
                      help="code cells imaged on the array (default 51: each cell in ~12 frames, as the patent asks)")
    disk.add_argument("--arrays", type=int, default=1, help="diode arrays on the disk (default 1)")
    disk.add_argument("--noise", type=float, default=2.0, help="diode noise, counts (default 2)")
    errors = p.add_argument_group("hidden errors")
    errors.add_argument("--graduation-harmonic", type=float, default=2e-6, help="amplitude of each low harmonic "
                        "of the graduation error, rad")
    errors.add_argument("--graduation-random", type=float, default=1e-6, help="random per-edge graduation error, rad")
    errors.add_argument("--eccentricity", type=float, nargs=2, default=(0.0, 0.0), metavar=("EX", "EY"),
                        help="code centre offset from the axis, code radii")
    errors.add_argument("--prnu", type=float, default=0.0, help="per-diode gain non-uniformity, 1 sigma (relative)")
    drift = p.add_argument_group("temperature drift")
    drift.add_argument("--temperature-scale", type=float, default=0.0, help="dp/p per degC")
    drift.add_argument("--temperature-range", type=float, default=0.0, help="temperature swing, degC")
    drift.add_argument("--temperature-profile", choices=["centred", "ramp"], default="centred",
                       help="temperature about 25 degC (centred) or rising from 25 degC (ramp: a run after a "
                            "calibration)")
    drift.add_argument("--a0-per-degc", type=float, default=0.0, help="dark level drift, counts per degC")
    drift.add_argument("--aperture-per-degc", type=float, default=0.0, help="relative aperture (blur) drift per degC")
    drift.add_argument("--light-per-degc", type=float, default=0.0, help="relative light level drift per degC")
    drift.add_argument("--frame-period", type=float, default=1.0, help="time between frames, s (default 1)")
    reference = p.add_argument_group("reference angles")
    reference.add_argument("--reference-every", type=int, default=0,
                           help="write reference/ angles for every k-th position")
    reference.add_argument("--reference-sigma", type=float, default=1e-6, help="reference angle noise, rad")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--overwrite", action="store_true")


def simulate(args) -> None:
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


def calibrate_arguments(p) -> None:
    p.add_argument("recording", help="recording folder with array0/frames.npy (and optional reference/)")
    p.add_argument("--out", help="calibration YAML to write (joint covariance next to it as .cov.npy)")
    p.add_argument("--no-reference", action="store_true", help="ignore reference/ (pure self-calibration)")


def calibrate(args) -> None:
    from selfcal.core.progress import TerminalProgress
    from selfcal.io.atomic import atomic_write_bytes
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.encoder import calibrate_encoder
    with TerminalProgress("calibrate encoder") as progress:
        cal = calibrate_encoder(read_recording(args.recording), use_reference=not args.no_reference,
                                progress=progress)
    print(cal.summary())
    if args.out:
        out = output(args.out)
        cov_path = out.with_suffix(".cov.npy")
        atomic_write_bytes(cov_path, cal.covariance_bytes())
        write_yaml(out, cal.to_dict(cov_path.name))
        print(f"calibration: {out} (joint covariance: {cov_path})")


def measure_arguments(p) -> None:
    p.add_argument("recording", help="recording folder with array0/frames.npy")
    p.add_argument("--calibration", required=True, help="calibration YAML of `selfcal calibrate encoder`")
    p.add_argument("--array", default="array0", help="array to read (default array0)")
    p.add_argument("--out", help="angles CSV (timestamp, angle, sigma, valid, flag)")
    p.add_argument("--track-drift", action="store_true",
                   help="durable self-calibration: iSAM2 follows the drifting geometry, aperture and dark level "
                        "from the frames (extra columns in --out), starting from the calibration as a prior")
    p.add_argument("--out-calibration", help="with --track-drift: write the updated calibration YAML (+ .cov.npy)")


def _read_calibration(path) -> tuple[dict, object]:
    """The calibration YAML of ``selfcal calibrate encoder`` and its joint covariance (None if not found)."""
    import numpy as np
    import yaml

    from selfcal.io.encoder import EncoderRecordingError
    try:
        calibration = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        raise EncoderRecordingError(f"{path}: invalid YAML ({err})") from None
    if not isinstance(calibration, dict) or calibration.get("system") != "encoder":
        raise EncoderRecordingError(f"{path}: not an encoder calibration (system: encoder)")
    covariance = None
    if calibration.get("covariance_file"):
        cov_path = Path(path).parent / calibration["covariance_file"]
        if cov_path.is_file():
            try:
                covariance = np.load(cov_path, allow_pickle=False)
            except (ValueError, OSError, EOFError) as err:  # truncated: the run that wrote it was killed, disk full
                raise EncoderRecordingError(f"{cov_path}: not a readable covariance ({' '.join(str(err).split())})"
                                            ) from None
            if covariance.ndim != 2 or covariance.shape[0] != covariance.shape[1] or not np.isfinite(covariance).all():
                raise EncoderRecordingError(f"{cov_path}: expected a finite square covariance, got shape "
                                            f"{covariance.shape}")
        else:
            log.warning("%s not found: sigmas without the calibration's own uncertainty", cov_path)
    return calibration, covariance


def measure(args) -> None:
    from selfcal.core.progress import TerminalProgress
    from selfcal.io.encoder import EncoderRecordingError, write_angles_csv
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.encoder import measure_encoder
    calibration, covariance = _read_calibration(args.calibration)
    if args.out_calibration and not args.track_drift:
        raise EncoderRecordingError("--out-calibration needs --track-drift (only a durable run updates it)")
    with TerminalProgress("measure encoder") as progress:
        progress("read the recording")
        result = measure_encoder(read_recording(args.recording), calibration, covariance, array=args.array,
                                 track_drift=args.track_drift, progress=progress)
    print(result.summary())
    if args.out:
        write_angles_csv(output(args.out), result.t_ns, result.beta_rad, result.sigma_rad, result.flags,
                         result.drift_columns)
        print(f"angles: {args.out}")
    if args.out_calibration:
        import io

        import numpy as np

        from selfcal.io.atomic import atomic_write_bytes
        out = output(args.out_calibration)
        cov_path = out.with_suffix(".cov.npy")
        buf = io.BytesIO()
        np.save(buf, result.updated_covariance, allow_pickle=False)
        atomic_write_bytes(cov_path, buf.getvalue())
        write_yaml(out, {**result.updated_calibration, "covariance_file": cov_path.name})
        print(f"updated calibration: {out} (joint covariance: {cov_path})")


VERBS = (
    Verb("simulate", "self-calibrating optical angle encoder (patent 000)", simulate_arguments, simulate),
    Verb("calibrate", "optical angle encoder self-calibration from its own diode-array frames",
         calibrate_arguments, calibrate),
    Verb("measure", "ML angle (and 1-sigma) of every frame with an encoder calibration", measure_arguments, measure),
)
