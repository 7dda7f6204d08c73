"""Mobile scan (patent 001): sphere spacing with and without frame-registration factors, same seeds, one run.

Per seed (the default 24 m / 10-sphere scan of ``scan_prediction.py``, INS error terms drawn from the prior): the
batch graph solved on the spheres alone, then with :func:`selfcal.pipelines.scan.register_frames` (profile pairs
registered by point-to-plane ICP) as :func:`selfcal.factors.scan.registration_theta_factor`.  Both: the
sphere-spacing RMS against the truth, the 95 % coverage and mean z^2 of every distance error over its predicted
sigma, the consecutive-distance NEES, the error-term NEES, seconds.  With registration also: the registration
NEES of each pair at the true poses (is the ICP covariance honest?).  Usage:

    .venv/bin/python benchmarks/scan_registration.py [--quick] [--seeds N] [--workers 1] [--json out.json]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from multiprocessing import Pool

import gtsam
import numpy as np
from scipy import stats

from selfcal.graphs import scan as gs
from selfcal.models import scan as ms
from selfcal.pipelines.scan import register_frames, scan_problem, solve_scan
from selfcal.sim.scan import ScanScenario

import _schema  # benchmarks/_schema.py: the results schema every benchmark writes
from scan_prediction import scan_data, spacing_figures

SCENARIO = ScanScenario()
QUICK = ScanScenario(length_m=10.0, n_spheres=5, pixel_step=8)


def registration_nees(registrations, sim, jitter_sigmas) -> list[float]:
    """Each pair's chi-square at the true relative pose (``dof`` = rows of its square-root information)."""
    out = []
    for g in registrations:
        Ra, ra, Rb, rb = sim.true_R[g.clock_a], sim.true_r[g.clock_a], sim.true_R[g.clock_b], sim.true_r[g.clock_b]
        true = gtsam.Pose3(gtsam.Rot3(Ra.T @ Rb), Ra.T @ (rb - ra))
        e = g.sqrt_information @ gtsam.Pose3.Logmap(true.between(gtsam.Pose3(g.a_T_b)))
        C = np.eye(len(e)) + g.sqrt_information @ ms.relative_jitter_covariance(g.a_T_b, jitter_sigmas) \
            @ g.sqrt_information.T
        out.append((float(e @ np.linalg.solve(C, e)), len(e)))
    return out


def information_bound(scenario: ScanScenario, layouts: int) -> dict:
    """What ideal registration could give at most: the planner's linear covariance analysis (no data) with
    relative-pose information between poses 1 s apart added on chosen directions of the INS error state
    (10 urad, 20 um per pair: far better than the ICP pairs measure), predicted spacing RMS per case."""
    from selfcal.core.solve import dense_jacobian
    from selfcal.pipelines.scan import planned_problem
    prior = np.asarray(scenario.error_sigmas, float)
    jitter = np.r_[np.full(3, scenario.ins_jitter_rad), np.full(3, scenario.ins_jitter_m)]
    rows = {"psi_x": (0, 1e-5), "psi_y": (1, 1e-5), "psi_z": (2, 1e-5), "dr_x": (6, 2e-5), "dr_y": (7, 2e-5),
            "dr_z": (8, 2e-5)}
    cases = {"spheres only": [], "across the track (psi_x, dr_y, dr_z)": ["psi_x", "dr_y", "dr_z"],
             "all but along the track": ["psi_x", "psi_y", "psi_z", "dr_y", "dr_z"],
             "along the track only (dr_x)": ["dr_x"], "full 6 dof": list(rows)}
    out = {name: [] for name in cases}
    for seed in range(layouts):
        problem = planned_problem(scenario, prior, jitter, seed=seed)
        S = len(problem.centers0)
        values = gtsam.Values()
        values.insert(gs.THETA, np.zeros(15))
        for j, c in enumerate(problem.centers0):
            values.insert(gs.O_KEY(j), np.asarray(c, float))
        A, _, offsets = dense_jacobian(gs.build_collapsed(problem)[0], values)
        keys = [gs.THETA] + [gs.O_KEY(j) for j in range(S)]
        A = A[:, np.concatenate([np.arange(offsets[k], offsets[k] + values.atVector(k).size) for k in keys])]
        Phi = problem.sensitivity.at(np.arange(problem.clock_t_s[0], problem.clock_t_s[-1], 1.0))[:, :, :15] * prior
        pairs = np.array(np.triu_indices(S, 1)).T
        for name, directions in cases.items():
            H = A.T @ A
            for d in directions:
                row, sigma = rows[d]
                D = np.diff(Phi[:, row, :], axis=0)  # relative: consecutive poses 1 s apart
                H[:15, :15] += D.T @ D / sigma**2
            _, s = ms.distance_sigmas(problem.centers0, np.linalg.inv(H)[15:, 15:], pairs)
            out[name].append(float(np.sqrt(np.mean(s**2))))
    return {name: float(np.sqrt(np.mean(np.square(v)))) * 1e3 for name, v in out.items()}


def one_seed(task) -> dict:
    scenario, seed = task
    from selfcal.sim.scan import simulate_scan
    sim = simulate_scan(scenario, seed=seed)
    data = scan_data(sim)
    problem = scan_problem(data)
    if len(problem.centers0) != len(sim.sphere_centers):
        return {"seed": seed, "skipped": f"{len(problem.centers0)} of {len(sim.sphere_centers)} spheres found"}
    out = {"seed": seed}
    t0 = time.perf_counter()
    _, sol, theta = solve_scan(data, problem)
    out["spheres"] = {**spacing_figures(sol, sim.sphere_centers), "seconds": time.perf_counter() - t0,
                      "theta_nees": float((theta - sim.error_terms) @ np.linalg.solve(sol.theta_cov,
                                                                                        theta - sim.error_terms))}
    t0 = time.perf_counter()
    registrations = register_frames(data, problem)
    t_icp = time.perf_counter() - t0
    _, sol_r, theta_r = solve_scan(data, replace(problem, registrations=registrations), gs.ScanModel(registration=True))
    e = theta_r - sim.error_terms
    chi = registration_nees(registrations, sim, data.jitter_sigmas)
    out["registration"] = {**spacing_figures(sol_r, sim.sphere_centers), "seconds": time.perf_counter() - t0,
                           "icp_seconds": t_icp, "pairs": len(registrations),
                           "seen_directions": float(np.mean([c[1] for c in chi])) if chi else 0.0,
                           "pair_nees_sum": float(sum(c[0] for c in chi)), "pair_dof": int(sum(c[1] for c in chi)),
                           "theta_nees": float(e @ np.linalg.solve(sol_r.theta_cov, e))}
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, help="scans (default 20; --quick 2)")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--first-seed", type=int, default=100)
    parser.add_argument("--bound-layouts", type=int, default=3, help="layouts for the ideal-registration bound")
    _schema.add_arguments(parser, "scan_registration")
    args = parser.parse_args()
    started = time.perf_counter()
    scenario = QUICK if args.quick else SCENARIO
    seeds = args.seeds or (2 if args.quick else 20)
    runs = []
    with Pool(args.workers) as pool:
        tasks = [(scenario, s) for s in range(args.first_seed, args.first_seed + seeds)]
        for r in pool.imap_unordered(one_seed, tasks):
            runs.append(r)
            if "skipped" in r:
                print(f"seed {r['seed']}: skipped ({r['skipped']})", flush=True)
                continue
            print(f"seed {r['seed']}: spacing RMS {r['spheres']['spacing_rms_m'] * 1e3:.3f} mm spheres only, "
                  f"{r['registration']['spacing_rms_m'] * 1e3:.3f} mm with {r['registration']['pairs']} registrations",
                  flush=True)
    ok = sorted((r for r in runs if "skipped" not in r), key=lambda r: r["seed"])
    rows, extra = [], {"seeds": [r["seed"] for r in ok], "skipped": [r for r in runs if "skipped" in r]}
    per = lambda arm, key: [r[arm][key] for r in ok]  # noqa: E731
    rows.append(_schema.distribution("scan: sphere-spacing RMS per scan, spheres + registration (baseline: spheres "
                                     "only)", "mm", np.array(per("registration", "spacing_rms_m")) * 1e3,
                                     np.array(per("spheres", "spacing_rms_m")) * 1e3))
    rows.append(_schema.distribution("scan: solve seconds per scan, spheres + registration incl. ICP (baseline: "
                                     "spheres only)", "s", per("registration", "seconds"), per("spheres", "seconds")))
    for arm in ("spheres", "registration"):
        z = np.concatenate([r[arm]["z"] for r in ok])
        nees, dof = sum(per(arm, "nees_consecutive")), sum(per(arm, "dof_consecutive"))
        lo, hi = stats.chi2.ppf([0.0005, 0.9995], dof)
        rows.append(_schema.row(f"scan ({arm}): coverage of the 95 % bounds of the sphere-distance errors", "fraction",
                                float(np.mean(np.abs(z) < 1.96)), better="higher",
                                note=f"{len(z)} distances; 0.95 when honest"))
        rows.append(_schema.row(f"scan ({arm}): consecutive-distance NEES / dof", "1", nees / dof,
                                note=f"chi2 with {dof} dof: 99.9 % bounds {lo / dof:.3f}-{hi / dof:.3f}"))
        extra[arm] = {"mean_z2": float(np.mean(z**2)), "theta_nees_mean": float(np.mean(per(arm, "theta_nees"))),
                      "predicted_rms_mm_median": float(np.median(per(arm, "predicted_rms_m"))) * 1e3}
    pair_nees, pair_dof = sum(per("registration", "pair_nees_sum")), sum(per("registration", "pair_dof"))
    rows.append(_schema.row("scan: registration NEES / dof of the ICP pairs at the true relative poses", "1",
                            pair_nees / pair_dof, note=f"{pair_dof} dof; 1 when the ICP information is honest"))
    extra["registration"].update({"pairs_per_scan": float(np.mean(per("registration", "pairs"))),
                                  "seen_directions_per_pair": float(np.mean(per("registration", "seen_directions"))),
                                  "icp_seconds_per_scan": float(np.mean(per("registration", "icp_seconds")))})
    layouts = 1 if args.quick else args.bound_layouts
    bound = information_bound(scenario, layouts)
    for name, v in bound.items():
        rows.append(_schema.row(f"scan: planner-predicted spacing RMS with ideal registration, {name}", "mm", v,
                                bound["spheres only"], note=f"{layouts} layouts; baseline: spheres only"))
    extra["ideal_registration_bound_mm"] = bound
    extra["per_seed"] = [{k: ({kk: vv for kk, vv in v.items() if kk != "z"} if isinstance(v, dict) else v)
                          for k, v in r.items()} for r in runs]
    _schema.write(args.json, "scan_registration", "scan", args.quick, time.perf_counter() - started, rows, extra)
    for r in rows:
        print(_schema.describe(r) if "distribution" in r else f"{r['metric']}: {r['library']:.4g} {r['unit']} "
              f"({r['note']})")
    print({k: extra[k] for k in ("spheres", "registration")})
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
