"""Vessel attitude: the library's factor graph (batch and iSAM2) against the patent's filter (seed 003).

Per scenario (calm, heave-dominated, turning), with and without known-acceleration removal, from the same
simulated voyage: roll and pitch RMS error against the truth, the residual drift (mean error over the last
tenth), the time, and the ratio patent/graph.  Then the real logs (static MPU-6050 tilts).  A PNG shows both
methods against the truth.  Usage:

    .venv/bin/python benchmarks/ship_vs_patent.py [--duration 3600] [--plot ship.png] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from selfcal.baselines.patent_003_drift import PatentDriftFilter, cutoff_between
from selfcal.pipelines.ship import ship_inputs
from selfcal.graphs.ship import ShipGraphOptions, ShipSmoother
from selfcal.sim.ship import ShipScenario

ROOT = Path(__file__).resolve().parents[1]


def errors(t_est, roll, pitch, scenario):
    true_roll, true_pitch, _ = scenario.truth_attitude(t_est)
    e_roll, e_pitch = np.degrees(roll - true_roll), np.degrees(pitch - true_pitch)
    tail = t_est > t_est[0] + 0.9 * (t_est[-1] - t_est[0])
    return {"roll_rms_deg": float(np.sqrt(np.mean(e_roll**2))), "pitch_rms_deg": float(np.sqrt(np.mean(e_pitch**2))),
            "roll_drift_deg": float(np.mean(e_roll[tail])), "pitch_drift_deg": float(np.mean(e_pitch[tail]))}


def patent_cutoff_hz(scenario) -> float:
    """The patent's rule with the vessel's own periods (a user knows them): above the heave frequency, below
    the roll/pitch frequencies.  Where the swell is not slower than the roll (calm, turning), the rule cannot be
    met; the cutoff then sits an octave below the slowest roll/pitch period."""
    motion = scenario.motion
    roll_s = float(max(np.max(motion.roll.period_s), np.max(motion.pitch.period_s)))
    try:
        return cutoff_between(float(np.min(motion.heave.period_s)), roll_s)
    except ValueError:
        return 0.5 / roll_s


def run_scenario(kind: str, duration_s: float, remove_known: bool, seed: int = 3):
    scenario = ShipScenario(kind=kind, duration_s=duration_s, seed=seed)
    rec = scenario.perturbed_measurements(seed + 100)
    inputs = ship_inputs(rec)
    out = {}
    start = time.perf_counter()
    patent = PatentDriftFilter(patent_cutoff_hz(scenario), remove_known_acceleration=remove_known).run(
        inputs.t_s, inputs.gyro_rad_s, inputs.accel_m_s2, inputs.speed_m_s)
    out["patent"] = {**errors(inputs.t_s, patent.roll, patent.pitch, scenario),
                     "seconds": time.perf_counter() - start}
    smoother = ShipSmoother(inputs, ShipGraphOptions(remove_known_acceleration=remove_known))
    batch = smoother.batch()
    out["graph_batch"] = {**errors(batch.t_s, batch.roll, batch.pitch, scenario), "seconds": batch.seconds}
    online = smoother.online()
    out["graph_isam2"] = {**errors(online.t_s, online.roll, online.pitch, scenario), "seconds": online.seconds}
    return out, (inputs.t_s, patent, batch, online, scenario)


def plot(traces, path):
    """Roll error against the truth over the whole voyage, both methods, one panel per scenario."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=(12, 3.0 * len(traces)))
    for row, (name, (t, patent, batch, online, scenario)) in enumerate(traces.items()):
        ax = fig.add_subplot(len(traces), 1, row + 1)
        ax.plot(t, np.degrees(patent.roll - scenario.truth_attitude(t)[0]), lw=0.6, label="patent filter")
        for est, style, label in ((online, ":", "graph (iSAM2, online)"), (batch, "-", "graph (batch)")):
            ax.plot(est.t_s, np.degrees(est.roll - scenario.truth_attitude(est.t_s)[0]), style, lw=0.8, label=label)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylim(-0.6, 0.6)
        ax.set_title(f"{name}: roll error against the truth (known accelerations removed)")
        ax.set_ylabel("roll error [deg]")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=3600.0)
    parser.add_argument("--plot", default="ship_vs_patent.png")
    parser.add_argument("--json")
    args = parser.parse_args()
    results, traces = {}, {}
    for kind in ("calm", "heave", "turning"):
        for remove in (True, False):
            name = f"{kind}, known acceleration {'removed' if remove else 'kept'}"
            res, trace = run_scenario(kind, args.duration, remove)
            results[name] = res
            if remove:
                traces[kind] = trace
            p, b, o = res["patent"], res["graph_batch"], res["graph_isam2"]
            print(f"\n== {name} ({args.duration:.0f} s)")
            for label, r in (("patent", p), ("graph batch", b), ("graph iSAM2", o)):
                print(f"  {label:12s} roll RMS {r['roll_rms_deg']:.4f} deg, pitch RMS {r['pitch_rms_deg']:.4f} deg, "
                      f"drift {r['roll_drift_deg']:+.4f}/{r['pitch_drift_deg']:+.4f} deg, {r['seconds']:.1f} s")
            print(f"  patent/graph (batch) RMS ratio: roll {p['roll_rms_deg'] / b['roll_rms_deg']:.2f}, "
                  f"pitch {p['pitch_rms_deg'] / b['pitch_rms_deg']:.2f}")
    plot(traces, args.plot)
    print(f"\nplot: {args.plot}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
