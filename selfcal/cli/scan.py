"""``selfcal simulate|smooth scan``: mobile stereo + inertial scan, drift corrected by sphere targets (patent 001)."""
from __future__ import annotations

from pathlib import Path

from selfcal.cli.common import UsageError, Verb, output, write_yaml

CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".pts")


def simulate_arguments(p) -> None:
    p.add_argument("--out", required=True, help="recording folder to write")
    p.add_argument("--length", type=float, default=24.0, help="scanned length, m")
    p.add_argument("--spheres", type=int, default=10, help="number of sphere targets")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--overwrite", action="store_true")


def simulate(args) -> None:
    from selfcal.sim.scan import ScanScenario, simulate_scan, write_scan_recording
    sim = simulate_scan(ScanScenario(length_m=args.length, n_spheres=args.spheres), seed=args.seed)
    write_scan_recording(sim, Path(args.out), overwrite=args.overwrite)
    print(f"wrote {args.out}: {len(sim.points_V)} clocks, {sum(len(p) for p in sim.points_V)} points, "
          f"{len(sim.sphere_centers)} spheres (reference mesh: {Path(args.out) / 'truth' / 'reference_mesh.ply'})")


def smooth_arguments(p) -> None:
    p.add_argument("recording")
    p.add_argument("--online", action="store_true", help="iSAM2, sphere by sphere, as the scan proceeds")
    p.add_argument("--out", help="corrected point cloud (.ply, .pcd); a .ply carries each point's predicted 1-sigma "
                   "(property sigma_m)")
    p.add_argument("--estimates", help="YAML with the 15 INS error terms, sphere centres and sphere distances, each "
                   "with its 1-sigma")


def smooth(args) -> None:
    import numpy as np

    from selfcal.core.progress import TerminalProgress
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.scan import smooth_scan
    if args.out and Path(args.out).suffix.lower() not in CLOUD_SUFFIXES:
        raise UsageError(f"{args.out}: the corrected scan is written as .ply, .pcd, .xyz or .pts")
    with TerminalProgress("smooth scan") as progress:
        est = smooth_scan(read_recording(args.recording), online=args.online, progress=progress)
    print(est.summary())
    if est.point_sigma_m is not None:
        q = np.percentile(est.point_sigma_m, [50, 95, 100]) * 1e3
        print(f"predicted point 1-sigma (worst direction): median {q[0]:.3g} mm, p95 {q[1]:.3g} mm, max {q[2]:.3g} mm")
    if est.distances:
        worst = max(est.distances, key=lambda d: d[3])
        print(f"predicted sphere-distance 1-sigma: up to {worst[3] * 1e3:.3g} mm (spheres {worst[0]}-{worst[1]})")
    if args.out:
        from selfcal.io.pointcloud import write_point_cloud
        ply = Path(args.out).suffix.lower() == ".ply"
        write_point_cloud(output(args.out), est.points_W,
                          attributes={"sigma_m": est.point_sigma_m} if ply and est.point_sigma_m is not None else None)
        print(f"corrected scan: {args.out}" + (" (per-point predicted 1-sigma as property sigma_m)" if ply else ""))
    if args.estimates:
        write_yaml(args.estimates, est.to_dict())


def plan_arguments(p) -> None:
    p.add_argument("--length", type=float, required=True, help="scanned length, m (a straight run)")
    p.add_argument("--speed", type=float, default=0.5, help="vehicle speed, m/s")
    p.add_argument("--tolerance", type=float, required=True,
                   help="largest sphere-distance error allowed, m (bound at --confidence)")
    p.add_argument("--confidence", type=float, default=0.95, help="two-sided confidence of the bound")
    p.add_argument("--ins", help="the INS's sensor.yaml (error_term_sigmas, pose_jitter_m, pose_jitter_rad; "
                   "default: the simulator's INS)")
    p.add_argument("--seed", type=int, default=0, help="sphere heights and ranges in the field of view")
    p.add_argument("--out", help="YAML with the plan and every layout evaluated")


def ins_model(path):
    """(prior sigmas (15), jitter sigmas (6)) from an INS sensor.yaml; UsageError if it holds no 15-term prior."""
    import numpy as np
    import yaml
    file = Path(path)
    if not file.is_file():
        raise UsageError(f"{path}: no such INS sensor.yaml")
    try:
        meta = yaml.safe_load(file.read_text()) or {}
    except yaml.YAMLError as err:
        raise UsageError(f"{path}: not valid YAML ({' '.join(str(err).split())})") from None
    sigmas = meta.get("error_term_sigmas") if isinstance(meta, dict) else None
    if sigmas is None or np.size(sigmas) != 15:
        raise UsageError(f"{path}: needs error_term_sigmas (15 values: the INS's error terms, docs/scan.md); "
                         "noise densities and random walks alone do not give the 15-term model")
    jitter = np.r_[np.full(3, float(meta.get("pose_jitter_rad", 1e-5))),
                   np.full(3, float(meta.get("pose_jitter_m", 5e-5)))]
    return np.asarray(sigmas, float), jitter


def plan(args) -> int:
    from selfcal.core.progress import TerminalProgress
    from selfcal.pipelines.scan import plan_scan
    prior, jitter = ins_model(args.ins) if args.ins else (None, None)
    with TerminalProgress("plan scan") as progress:
        result = plan_scan(args.length, args.speed, args.tolerance, prior, jitter, args.confidence, args.seed,
                           progress=progress)
    for c in result.cases:
        print(f"{c.n_spheres:3d} spheres, spacing {c.spacing_m:6.2f} m: predicted spacing RMS "
              f"{c.predicted_rms_m * 1e3:.3g} mm, worst pair {c.worst_sigma_m * 1e3:.3g} mm (1-sigma), "
              f"bound {c.bound_m * 1e3:.3g} mm -> {'meets' if c.meets else 'exceeds'} {args.tolerance * 1e3:.3g} mm")
    chosen = result.chosen
    if chosen is None:
        print(f"no layout meets {args.tolerance * 1e3:.3g} mm at {args.confidence:.0%}: this INS cannot be corrected "
              "to the tolerance by spheres alone over this path")
    else:
        print(f"largest sphere spacing: {chosen.spacing_m:.2f} m ({chosen.n_spheres} spheres over {args.length:g} m)")
    if args.out:
        write_yaml(args.out, result.to_dict())
    return 0 if chosen is not None else 3


VERBS = (
    Verb("simulate", "mobile stereo line-scan + INS through a tunnel with spheres (patent 001)",
         simulate_arguments, simulate),
    Verb("smooth", "mobile stereo scan: INS drift corrected by sphere targets (patent 001)", smooth_arguments, smooth),
    Verb("plan", "mobile scan: the largest sphere spacing that meets a tolerance, for an INS and a path",
         plan_arguments, plan, epilog="exit status: 0 a spacing meets the tolerance, 3 none does, 1 error"),
)
