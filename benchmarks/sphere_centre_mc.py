"""Monte Carlo of the QC sphere centres: does their scatter agree with the covariance each fit reports?

K simulated scans of the plate-with-spheres artefact (3 spheres, 0.2 mm noise, 100 deg caps; plus a
one-sided variant, 35 deg caps, where the centre comes from the known radius) go through the QC detection
and evaluation (voxel grid, normals, planes removed, DBSCAN, RANSAC, full-resolution refit).  Per sphere and run
the centre's NEES ``d^T P^-1 d`` (d: error against the truth, P: reported 3x3 covariance); the sum over
``M`` centres is chi2(3M) when the covariance is right: the 0.1 % and 99.9 % quantiles are the acceptance
bounds.  The Cramer-Rao bound of a centre is the reported covariance with the true sigma (the fit's
information matrix J^T J / sigma^2); efficiency = RMS error / sqrt(trace CRB).  Baseline: Kasa's algebraic
centre on the same points.  The centre error |d| is reported per scan (the mean over its spheres; the scan's
seed is the unit): median, 90th percentile and worst, for both fits and their per-scan ratio.  Usage:

    .venv/bin/python benchmarks/sphere_centre_mc.py [--quick] [--runs K] [--json out.json]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import stats

from selfcal.io.pointcloud import LoadedCloud, cloud_from_points
from selfcal.core.sphere import algebraic_sphere, fit_sphere, sphere_residuals_m
from selfcal.pipelines.qc.checks import run_qc
from selfcal.pipelines.qc.spec import QCSpec
from selfcal.sim.qc import PlateWithSpheres

import _schema  # benchmarks/_schema.py: the results schema every benchmark writes

SIGMA_M = 0.0002


def spec(art: PlateWithSpheres) -> QCSpec:
    return QCSpec.from_dict({
        "spheres": {"nominal_radius_m": art.radius_m, "count": 3, "ransac_threshold_m": 5 * SIGMA_M,
                    "targets": [{"name": n, "centre_m": c.tolist()} for n, c in zip(art.names, art.centres_m)],
                    "match_radius_m": 0.02},
        "planes": {"threshold_m": 5 * SIGMA_M, "min_points": 500, "evaluate": 0},
        "detection": {"voxel_m": 0.004, "normal_radius_m": 0.012, "dbscan_eps_m": 0.012}})


def campaign(runs: int, cap_deg: float, n_points: int, share) -> dict:
    art = PlateWithSpheres()
    qc_spec = spec(art)
    nees, err, err_kasa, crb_trace = [], [], [], []
    per_scan, per_scan_kasa = [], []  # mean |centre error| over the spheres found in each scan, m
    for seed in range(runs):
        first = len(err)
        pts, _ = art.scan(n_points, sigma_m=SIGMA_M, seed=1000 + seed, cap_deg=cap_deg, sphere_point_share=share)
        result = run_qc(LoadedCloud(cloud_from_points(pts), f"mc{seed}", len(pts), 0), qc_spec,
                        progress=lambda _: None)
        for s in result.spheres:
            truth = art.centres_m[art.names.index(s.name)]
            d = s.centre_fit.center_m - truth
            nees.append(float(d @ np.linalg.solve(s.centre_fit.covariance[:3, :3], d)))
            err.append(d)
            near = pts[np.abs(sphere_residuals_m(pts, s.fit.center_m, s.fit.radius_m)) <= qc_spec.spheres.gate()]
            err_kasa.append(algebraic_sphere(near)[0] - truth)
            # CRB: the same fit's information with the true noise sigma
            crb = fit_sphere(near, radius_m=art.radius_m if s.centre_fit.radius_known else None,
                             sigma_m=SIGMA_M).covariance[:3, :3]
            crb_trace.append(np.trace(crb))
        found = slice(first, len(err))
        per_scan.append(float(np.mean(np.linalg.norm(err[found], axis=1))) if len(err) > first else np.nan)
        per_scan_kasa.append(float(np.mean(np.linalg.norm(err_kasa[found], axis=1))) if len(err) > first else np.nan)
    m = len(nees)
    lo, hi = stats.chi2.ppf([0.001, 0.999], 3 * m)
    rms = float(np.sqrt(np.mean(np.sum(np.square(err), axis=1))))
    rms_kasa = float(np.sqrt(np.mean(np.sum(np.square(err_kasa), axis=1))))
    return {"cap_deg": cap_deg, "runs": runs, "centres": m, "found": m / (3 * runs), "nees_sum": float(np.sum(nees)),
            "nees_mean": float(np.mean(nees)), "chi2_lo": float(lo), "chi2_hi": float(hi),
            "consistent": bool(lo < np.sum(nees) < hi), "rms_error_m": rms, "rms_error_kasa_m": rms_kasa,
            "crb_rms_m": float(np.sqrt(np.mean(crb_trace))), "efficiency": rms / float(np.sqrt(np.mean(crb_trace))),
            "centre_error_per_scan_m": per_scan, "centre_error_per_scan_kasa_m": per_scan_kasa}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, help="scans (seeds) per campaign (default 100; 20 with --quick)")
    _schema.add_arguments(parser, "sphere_centre_mc")
    args = parser.parse_args()
    runs = args.runs or (20 if args.quick else 100)
    started = time.perf_counter()
    rows, out = [], {}
    for label, cap, share in (("100 deg caps, free radius", 100.0, None),
                              ("35 deg caps (one-sided), known radius", 35.0, 0.2)):
        r = campaign(runs, cap, 60_000, share)
        out[label] = r
        print(f"{label}: {r['centres']} centres from {runs} scans; mean NEES {r['nees_mean']:.2f} (3 expected), "
              f"sum {r['nees_sum']:.0f} in [{r['chi2_lo']:.0f}, {r['chi2_hi']:.0f}]: "
              f"{'consistent' if r['consistent'] else 'NOT consistent'}; RMS error {r['rms_error_m'] * 1e6:.2f} um "
              f"(Kasa {r['rms_error_kasa_m'] * 1e6:.2f} um), CRB {r['crb_rms_m'] * 1e6:.2f} um, "
              f"efficiency {r['efficiency']:.2f}")
        error = _schema.distribution(f"centre error per scan, {label}", "um",
                                     np.multiply(r["centre_error_per_scan_m"], 1e6),
                                     np.multiply(r["centre_error_per_scan_kasa_m"], 1e6),
                                     note="mean |centre - truth| over the scan's spheres; baseline: Kasa algebraic "
                                          "centre on the same points; per-scan ratio > 1: library better")
        print("  " + _schema.describe(error))
        rows += [error,
                 _schema.row(f"centre RMS error over the scans, {label}", "m", r["rms_error_m"], r["rms_error_kasa_m"],
                             note="baseline: Kasa algebraic centre on the same points; > 1: library better"),
                 _schema.row(f"centre RMS error / CRB, {label}", "x", r["efficiency"], None),
                 _schema.row(f"mean centre NEES, {label}", "1", r["nees_mean"], None,
                             note=f"3 expected; sum within chi2({3 * r['centres']}) 0.1-99.9 % bounds: "
                                  f"{r['consistent']}")]
    _schema.write(args.json, "sphere_centre_mc", "scan", args.quick, time.perf_counter() - started, rows, out)
    print(f"results: {args.json}")


if __name__ == "__main__":
    main()
