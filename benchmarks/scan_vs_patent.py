"""Mobile scan (patent 001): the joint factor graph against the patent's two-stage procedure, same runs.

Per seeded run (a simulated tunnel scan with sphere targets, INS error terms drawn from the INS prior): the
sphere-spacing error of every sphere pair, measured by fitting each sphere (known radius) in the cloud itself,
for the inertial-only scan, the joint graph (batch LM and iSAM2), and the patent's two stages (stage-2 weights:
the stage-1 information with the centres marginalised, the stronger reading; and the literal reading, every
optimal pose a full measurement); the time of each estimator; the NEES of the error terms.  Each scan's
sphere-spacing RMS is one seed's figure: median, 90th percentile and worst over the seeds, with the per-seed ratio.  Then a Monte
Carlo of the sphere centres against their reported covariance (chi-square bounds).  Usage:

    .venv/bin/python benchmarks/scan_vs_patent.py [--quick] [--runs N] [--json out.json]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import stats

from selfcal.baselines.scan import patent_two_stage
from selfcal.graphs import scan as gs
from selfcal.io.recording import read_recording
from selfcal.models import scan as ms
from selfcal.core.sphere import fit_sphere
from selfcal.pipelines.scan import read_scan, scan_problem
from selfcal.sim.scan import ScanScenario, simulate_scan, write_scan_recording

import _schema  # benchmarks/_schema.py: the results schema every benchmark writes


def spacing_errors(problem, R, r, true_centers):
    """Pairwise centre-distance errors (m), each sphere fitted (known radius) to its set-B points placed by the
    clock poses (R, r) of an estimator: the same points for every estimator, wherever it puts them."""
    centers = []
    for j in range(len(problem.centers0)):
        obs = [o for o in problem.observations if o.sphere == j]
        pts = np.concatenate([ms.world_points(R[o.clock], r[o.clock], problem.imu_R_vision, problem.imu_t_vision,
                                              o.vision_p) for o in obs])
        centers.append(fit_sphere(pts, radius_m=problem.radius_m).center_m)
    centers = np.array(centers)
    i, j = np.triu_indices(len(true_centers), 1)
    return np.linalg.norm(centers[i] - centers[j], axis=1) - np.linalg.norm(true_centers[i] - true_centers[j], axis=1)


def one_run(seed: int, scenario: ScanScenario, folder: Path) -> dict:
    sim = simulate_scan(scenario, seed=seed)
    rec = read_recording(write_scan_recording(sim, folder / f"rec{seed}"))
    data = read_scan(rec)
    t = time.perf_counter()
    problem = scan_problem(data)
    detect_s = time.perf_counter() - t
    if len(problem.centers0) != len(sim.sphere_centers):
        return {"seed": seed, "skipped": f"{len(problem.centers0)} of {len(sim.sphere_centers)} spheres detected"}
    truth = sim.sphere_centers
    out = {"seed": seed, "detect_s": detect_s}
    R0, r0 = gs.corrected_clock_poses(problem, gs.ScanSolution(np.zeros(15), None, None, None))
    out["inertial"] = spacing_errors(problem, R0, r0, truth)
    for name, solver in (("graph", gs.solve_batch), ("online", gs.solve_online)):
        t = time.perf_counter()
        sol = solver(problem)
        out[f"{name}_s"] = time.perf_counter() - t
        R, r = gs.corrected_clock_poses(problem, sol)
        out[name] = spacing_errors(problem, R, r, truth)
        if name == "graph":
            e = sol.theta - sim.error_terms
            out["theta_nees"] = float(e @ np.linalg.solve(sol.theta_cov, e))
            out["center_nees"] = [float((c - tc) @ np.linalg.solve(C, c - tc))
                                  for c, C, tc in zip(sol.centers, sol.centers_cov, truth)]
    clocks = problem.b_clocks()
    row = {m: i for i, m in enumerate(clocks)}
    Rb, rb, Phi, _ = gs.clock_inputs(problem, clocks)
    obs = [(row[o.clock], o.sphere, o.vision_p) for o in problem.observations]
    for name, weighting in (("patent", "information"), ("patent_literal", "pose_sigmas")):
        t = time.perf_counter()
        pat = patent_two_stage(Rb, rb, Phi[:, :, :15], obs, problem.imu_R_vision, problem.imu_t_vision,
                               problem.centers0, problem.radius_m, problem.prior_sigmas, problem.jitter_sigmas,
                               weighting=weighting)
        out[f"{name}_s"] = time.perf_counter() - t
        R, r = gs.corrected_clock_poses(problem, gs.ScanSolution(pat.theta, None, None, None))
        out[name] = spacing_errors(problem, R, r, truth)
    out["points"] = int(sum(len(p) for p in sim.points_V))
    return out


def rms(x):
    x = np.concatenate([np.atleast_1d(v) for v in x])
    return float(np.sqrt(np.mean(x**2)))


def centre_mc(runs: int, folder: Path) -> dict:
    nees = []
    for seed in range(1000, 1000 + runs):
        sim = simulate_scan(ScanScenario(length_m=6.0, n_spheres=3, pixel_step=8), seed=seed)
        problem = scan_problem(read_scan(read_recording(write_scan_recording(sim, folder / f"mc{seed}"))))
        if len(problem.centers0) != len(sim.sphere_centers):
            continue
        sol = gs.solve_batch(problem)
        nees += [float((c - tc) @ np.linalg.solve(C, c - tc))
                 for c, C, tc in zip(sol.centers, sol.centers_cov, sim.sphere_centers)]
    n = len(nees)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], 3 * n) / n
    return {"centres": n, "mean_nees": float(np.mean(nees)), "bounds_99.9": [float(lo), float(hi)],
            "consistent": bool(lo < np.mean(nees) < hi)}


def plot(results, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4))
    labels = [("inertial", "inertial only"), ("patent_literal", "patent, literal"), ("patent", "patent, informed"),
              ("graph", "joint graph (LM)"), ("online", "joint graph (iSAM2)")]
    for k, (key, label) in enumerate(labels):
        vals = [rms([r[key]]) * 1e3 for r in results]
        ax.scatter(np.full(len(vals), k), vals, label=label)
    ax.set_yscale("log")
    ax.set_xticks(range(len(labels)), [l for _, l in labels], rotation=15)
    ax.set_ylabel("sphere-spacing RMS error per run (mm)")
    ax.set_title("Mobile scan: sphere spacing after INS drift correction")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int,
                        help=f"scans (seeds) per estimator (default {_schema.DEFAULT_SEEDS}; --quick 3)")
    parser.add_argument("--plot", default=str(_schema.RESULTS / "scan_vs_patent.png"))
    _schema.add_arguments(parser, "scan_vs_patent")
    args = parser.parse_args()
    started = time.perf_counter()
    runs = args.runs or (3 if args.quick else _schema.DEFAULT_SEEDS)
    scenario = ScanScenario(length_m=10.0, n_spheres=5) if args.quick else ScanScenario()
    with tempfile.TemporaryDirectory() as tmp:
        results = [one_run(seed, scenario, Path(tmp)) for seed in range(runs)]
        skipped = [r for r in results if "skipped" in r]
        results = [r for r in results if "skipped" not in r]
        mc = centre_mc(4 if args.quick else 30, Path(tmp))
    ins, gr, on, pa, pl = (rms([r[k] for r in results]) for k in ("inertial", "graph", "online", "patent",
                                                                   "patent_literal"))
    t_g, t_o, t_p = (float(np.mean([r[k] for r in results])) for k in ("graph_s", "online_s", "patent_s"))
    theta_nees = float(np.mean([r["theta_nees"] for r in results]))
    per_seed = {k: [rms([r[k]]) * 1e3 for r in results] for k in ("inertial", "graph", "online", "patent",
                                                                   "patent_literal")}
    max_per_seed = {k: [float(np.abs(r[k]).max()) * 1e3 for r in results] for k in ("graph", "inertial")}
    rows = [
        _schema.distribution("sphere-spacing RMS per scan, joint graph vs inertial-only", "mm", per_seed["graph"],
                             per_seed["inertial"], note="baseline = the uncorrected INS scan; target ratio >= 10"),
        _schema.distribution("sphere-spacing RMS per scan, joint graph vs patent two-stage (informed weights)", "mm",
                             per_seed["graph"], per_seed["patent"]),
        _schema.distribution("sphere-spacing RMS per scan, joint graph vs patent two-stage (literal)", "mm",
                             per_seed["graph"], per_seed["patent_literal"]),
        _schema.distribution("sphere-spacing RMS per scan, iSAM2 online vs patent (informed)", "mm",
                             per_seed["online"], per_seed["patent"]),
        _schema.distribution("max sphere-spacing error per scan, joint graph vs inertial-only", "mm",
                             max_per_seed["graph"], max_per_seed["inertial"]),
        _schema.row("sphere-spacing RMS over all scans, joint graph vs patent two-stage (informed weights)", "mm",
                    gr * 1e3, pa * 1e3),
        _schema.row("estimation time per scan, joint graph (LM) vs patent (informed)", "s", t_g, t_p),
        _schema.row("estimation time per scan, iSAM2 (all spheres) vs patent (informed)", "s", t_o, t_p),
        _schema.row("error-term NEES (15 dof when honest), joint graph", "1", theta_nees),
        _schema.row("sphere-centre NEES mean (3 when honest), joint graph", "1", mc["mean_nees"],
                    note=f"{mc['centres']} centres; 99.9 % chi2 bounds {mc['bounds_99.9']}"),
    ]
    if not args.quick:
        plot(results, args.plot)
    extra = {"runs": len(results), "skipped": skipped, "scenario_length_m": scenario.length_m,
             "spheres_per_scan": scenario.n_spheres, "points_per_scan": [r["points"] for r in results],
             "centre_monte_carlo": mc, "detect_s_mean": float(np.mean([r["detect_s"] for r in results])),
             "seeds": [r["seed"] for r in results], "per_run_spacing_rms_mm": per_seed}
    _schema.write(args.json, "scan_vs_patent", "scan", args.quick, time.perf_counter() - started, rows, extra)
    for r in rows:
        if "distribution" in r:
            print(_schema.describe(r))
            continue
        ratio = f"{r['ratio']:.3g}" if r["ratio"] is not None else "-"
        base = f"{r['baseline']:.4g}" if r["baseline"] is not None else "-"
        print(f"{r['metric']:75s} {r['library']:.4g} vs {base} {r['unit']} (ratio {ratio})")
    print(f"centre Monte Carlo: {mc}")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
