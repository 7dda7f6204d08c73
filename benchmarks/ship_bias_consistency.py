"""Ship gyro bias: is the batch smoother's reported sigma honest on turning voyages?  (issue 16, item 6)

Per seed (20 by default), a turning voyage (``ShipScenario(kind="turning")``, speed log on, default lever arm,
10 deg/h bias walking 10 deg/h/sqrt(h)): the batch smoother's final gyro bias segment and its marginal
covariance, against the truth averaged over that segment.  Per component: median / p90 / worst error, NEES mean
with its 95 % chi-square interval (a consistent estimator's 1-dof NEES mean over N seeds lies in
``[chi2_N(0.025), chi2_N(0.975)] / N``), coverage of the 95 % bounds (+-1.96 sigma), and how often the
component is flagged "not determined" (sigma above ``BIAS_SIGMA_BOUND_DEG_H``; the heading axis always).  Side by side: the patent's
filter, whose bias is the slope of its PI correction over the last 30 % of the voyage (roll and pitch; it has no
heading correction, so no z estimate: its z error is the true z).  Usage:

    .venv/bin/python benchmarks/ship_bias_consistency.py [--quick] [--seeds 20] [--duration 120]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.stats import chi2

from selfcal.baselines.ship import PatentDriftFilter, vessel_cutoff_hz
from selfcal.graphs.ship import ShipSmoother
from selfcal.pipelines.ship import BIAS_SIGMA_BOUND_DEG_H, DEG_H, UNVOUCHED_AXES, ship_inputs
from selfcal.sim.ship import ShipScenario

import _schema  # benchmarks/_schema.py: the results schema every benchmark writes

PATENT_SLOPE_FRACTION = 0.3  # the patent's bias: the PI correction's slope over this last part of the voyage


def final_segment_truth(scenario: ShipScenario, t_s: np.ndarray, segment_s: float) -> np.ndarray:
    """The true bias averaged over the smoother's final bias segment (deg/h, (3,))."""
    start = t_s[0] + segment_s * np.floor((t_s[-1] - t_s[0]) / segment_s)
    return scenario.truth_gyro_bias(np.linspace(start, t_s[-1], 200)).mean(axis=0) / DEG_H


def patent_bias_deg_h(scenario: ShipScenario, inputs) -> np.ndarray:
    """(x, y, nan): the drift rate the patent's PI loop compensates at the end of the voyage, deg/h.  The adder
    makes angle = gyro angle + u, so a bias b ramps u at -b (roll, pitch axes; small angles)."""
    motion = scenario.motion
    cutoff = vessel_cutoff_hz(motion.heave.period_s, np.concatenate([motion.roll.period_s, motion.pitch.period_s]))
    result = PatentDriftFilter(cutoff, remove_known_acceleration=True).run(
        inputs.t_s, inputs.gyro_rad_s, inputs.accel_m_s2, inputs.speed_m_s)
    tail = inputs.t_s >= inputs.t_s[-1] - PATENT_SLOPE_FRACTION * (inputs.t_s[-1] - inputs.t_s[0])
    slopes = np.polyfit(inputs.t_s[tail], result.correction[tail, :2], 1)[0]
    return np.array([-slopes[0] / DEG_H, -slopes[1] / DEG_H, np.nan])


def run_seed(seed: int, duration_s: float) -> dict:
    scenario = ShipScenario(kind="turning", duration_s=duration_s, seed=seed)
    inputs = ship_inputs(scenario.perturbed_measurements(seed + 100))
    smoother = ShipSmoother(inputs)
    estimate = smoother.batch()
    truth = final_segment_truth(scenario, estimate.t_s, smoother.options.bias_segment_s)
    value = estimate.gyro_bias[-1] / DEG_H
    covariance = estimate.gyro_bias_covariance / DEG_H**2
    error = value - truth
    patent = patent_bias_deg_h(scenario, inputs)
    return {"seed": seed, "truth_deg_h": truth.tolist(), "graph_deg_h": value.tolist(),
            "graph_sigma_deg_h": np.sqrt(np.diag(covariance)).tolist(), "graph_error_deg_h": error.tolist(),
            "nees3": float(error @ np.linalg.solve(covariance, error)),
            "patent_deg_h": [None if np.isnan(p) else float(p) for p in patent],
            "patent_error_deg_h": [float(abs(truth[i])) if np.isnan(p) else float(p - truth[i])
                                   for i, p in enumerate(patent)],
            "seconds": estimate.seconds}


def summary(seeds: list[dict]) -> dict:
    n = len(seeds)
    err = np.array([s["graph_error_deg_h"] for s in seeds])
    sig = np.array([s["graph_sigma_deg_h"] for s in seeds])
    pat = np.abs(np.array([s["patent_error_deg_h"] for s in seeds]))
    z = err / sig
    nees_interval = [chi2.ppf(0.025, n) / n, chi2.ppf(0.975, n) / n]
    out = {"n_seeds": n, "nees_1dof_interval_95": nees_interval,
           "nees_3dof_mean": float(np.mean([s["nees3"] for s in seeds])),
           "nees_3dof_interval_95": [chi2.ppf(0.025, 3 * n) / n, chi2.ppf(0.975, 3 * n) / n], "components": {}}
    for i, axis in enumerate("xyz"):
        a = np.abs(err[:, i])
        nees = float(np.mean(z[:, i] ** 2))
        out["components"][axis] = {
            "graph_abs_error_deg_h": {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)),
                                      "worst": float(a.max())},
            "graph_sigma_median_deg_h": float(np.median(sig[:, i])),
            "nees_mean": nees, "nees_consistent": bool(nees_interval[0] <= nees <= nees_interval[1]),
            "coverage_95": float(np.mean(np.abs(z[:, i]) <= 1.96)),
            "flagged_undetermined": 1.0 if axis in UNVOUCHED_AXES else float(np.mean(sig[:, i] > BIAS_SIGMA_BOUND_DEG_H)),
            "patent_abs_error_deg_h": {"median": float(np.median(pat[:, i])), "p90": float(np.percentile(pat[:, i], 90)),
                                       "worst": float(pat[:, i].max())},
        }
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=None, help="number of seeds (default 20; 5 with --quick)")
    parser.add_argument("--duration", type=float, default=None, help="voyage length, s (default 120; 60 with --quick)")
    _schema.add_arguments(parser, "ship_bias_consistency")
    args = parser.parse_args()
    n_seeds = args.seeds or (5 if args.quick else 20)
    duration = args.duration or (60.0 if args.quick else 120.0)
    started = time.perf_counter()
    seeds = []
    for seed in range(n_seeds):
        s = run_seed(seed, duration)
        seeds.append(s)
        print(f"seed {seed:2d}: truth {np.round(s['truth_deg_h'], 1)}, graph {np.round(s['graph_deg_h'], 1)} +- "
              f"{np.round(s['graph_sigma_deg_h'], 1)}, patent x y {np.round(s['patent_deg_h'][:2], 1)} deg/h; "
              f"NEES(3) {s['nees3']:.2f}", flush=True)
    result = summary(seeds)
    lo, hi = result["nees_1dof_interval_95"]
    print(f"\n{n_seeds} turning voyages of {duration:.0f} s; NEES mean 95 % interval (1 dof) [{lo:.2f}, {hi:.2f}]; "
          f"3-dof NEES mean {result['nees_3dof_mean']:.2f} in [{result['nees_3dof_interval_95'][0]:.2f}, "
          f"{result['nees_3dof_interval_95'][1]:.2f}]")
    rows = []
    for axis, c in result["components"].items():
        g, p = c["graph_abs_error_deg_h"], c["patent_abs_error_deg_h"]
        print(f"  {axis}: graph |error| median {g['median']:.2f} p90 {g['p90']:.2f} worst {g['worst']:.2f} deg/h, "
              f"sigma median {c['graph_sigma_median_deg_h']:.2f}, NEES {c['nees_mean']:.2f} "
              f"({'in' if c['nees_consistent'] else 'OUTSIDE'} the interval), 95 % coverage {c['coverage_95']:.0%}, "
              f"flagged not determined {c['flagged_undetermined']:.0%}; patent |error| median {p['median']:.2f} "
              f"p90 {p['p90']:.2f} worst {p['worst']:.2f}" + (" (no z estimate: |true z|)" if axis == "z" else ""))
        rows += [_schema.row(f"gyro bias {axis} |error| median, turning {duration:.0f} s (batch)", "deg/h",
                             g["median"], p["median"]),
                 _schema.row(f"gyro bias {axis} |error| p90, turning {duration:.0f} s (batch)", "deg/h",
                             g["p90"], p["p90"]),
                 _schema.row(f"gyro bias {axis} NEES mean (consistent: {lo:.2f}-{hi:.2f})", "1", c["nees_mean"],
                             note="1-dof NEES mean over the seeds; no baseline (the patent reports no sigma)"),
                 _schema.row(f"gyro bias {axis} coverage of the 95 % bounds", "fraction", c["coverage_95"],
                             better="higher", note="no baseline")]
    _schema.write(args.json, "ship_bias_consistency", "ship", args.quick, time.perf_counter() - started, rows,
                  {"duration_s": duration, "summary": result, "seeds": seeds})
    print(f"results: {args.json}")


if __name__ == "__main__":
    main()
