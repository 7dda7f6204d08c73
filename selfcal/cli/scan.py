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


VERBS = (
    Verb("simulate", "mobile stereo line-scan + INS through a tunnel with spheres (patent 001)",
         simulate_arguments, simulate),
    Verb("smooth", "mobile stereo scan: INS drift corrected by sphere targets (patent 001)", smooth_arguments, smooth),
)
