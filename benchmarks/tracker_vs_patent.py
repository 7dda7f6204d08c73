"""Laser-tracker target (patent 004): the gated factor graph against the patent's SMFAFKF, same simulated runs.

Measures, side by side in one run, each accuracy figure per seed (median, 90th percentile, worst, and of the
per-seed ratio to the patent; 20 seeds by default, 3 with --quick):
* attitude and position RMSE of the gated graph (fixed-lag, online poses), the same graph without gating, the
  batch smoother, and the patent's filter as written (and without its fault detection), on fault-free and on
  fault-injected runs of the same scenario seeds;
* the gated graph's RMSE with faults / without (target <= 1.2), and the same ratio when the inclinometer's samples
  are dropped exactly over its soft faults (an oracle detector: what holding the sensor out costs by itself);
* soft-fault (inclinometer ramp / stuck) detection delay;
* inclinometer soft-fault alarms per hour on fault-free data without vibration (pure H0) against the stated
  rate, and with vibration bursts (hold-outs the vibration causes, not false alarms);
* throughput (real-time factor, wall clock and CPU time, median of 3 passes) and p99 update latency of the online
  estimator for 200 Hz IMU + 50 Hz tracker + 10 Hz inclinometer + 10 Hz camera, one thread;
* resident memory over a long fixed-lag run (3 h in the full run, 20 min in --quick), sampled along the way.

Runs last 600 s (the default fault schedule needs 10 min; 20 seeds take about an hour here); ``--duration 120``
(the --quick length) uses a 120 s schedule with every fault kind once, scaled in time for shorter runs.

Usage: ``.venv/bin/python benchmarks/tracker_vs_patent.py [--quick] [--seeds 20] [--duration 600] [--json PATH]``
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import dataclasses  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from selfcal.io.atomic import atomic_write_text  # noqa: E402
from selfcal.pipelines.tracker import OnlineTracker, noise_from_meta, patent_baseline, smooth_tracker  # noqa: E402
from selfcal.sim.tracker import TrackerScenario  # noqa: E402

import _schema  # noqa: E402  benchmarks/_schema.py: the results schema (its distribution rows)

RESULTS = Path(__file__).resolve().parent / "results"


def errors(sc: TrackerScenario, t_ns, R_est, p_est):
    t = (np.asarray(t_ns) - sc.t0_ns) * 1e-9
    R, p = sc.truth_pose(t)
    att = np.linalg.norm(Rotation.from_matrix(np.einsum("nji,njk->nik", R, R_est)).as_rotvec(), axis=1)
    return np.degrees(att), np.linalg.norm(p_est - p, axis=1) * 1e3


def rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def at_tracker_times(rec, t_ns, x, window_s=0.1):
    """``x`` at the outputs that follow a tracker sample within ``window_s`` (one keyframe): where the patent's
    filter has outputs at all (it updates and outputs only at tracker epochs, none during a beam break)."""
    tr = rec.sensors["tracker0"].t_ns
    t_ns = np.asarray(t_ns)
    i = np.searchsorted(tr, t_ns, side="right") - 1
    ok = (i >= 0) & (t_ns - tr[np.maximum(i, 0)] < window_s * 1e9)
    return x[ok]


def graph_run(sc, rec, mode="fixed-lag", gating=True):
    res = smooth_tracker(rec, mode=mode, gating=gating, covariance=False) if mode == "batch" else \
        smooth_tracker(rec, mode=mode, gating=gating)
    R = Rotation.from_quat(res.quaternion).as_matrix()
    att, pos = errors(sc, res.t_ns, R, res.position)
    return {"att_deg": rms(att), "pos_mm": rms(pos), "pos_seen_mm": rms(at_tracker_times(rec, res.t_ns, pos)),
            "decisions": res.decisions}


def without_soft_faults(sc, rec):
    """The recording with the inclinometer's samples removed over its soft faults (ramp, stuck): what an oracle
    detector would hold out, from the fault's first sample to its last."""
    inc = rec.sensors["incl0"]
    t = (inc.t_ns - sc.t0_ns) * 1e-9
    keep = np.ones(len(t), dtype=bool)
    for f in sc.faults:
        if f.sensor == "incl0" and f.kind in ("ramp", "stuck"):
            keep &= ~((t >= f.start_s) & (t < f.end_s))
    sensors = dict(rec.sensors)
    sensors["incl0"] = dataclasses.replace(inc, t_ns=inc.t_ns[keep], values={k: v[keep] for k, v in inc.values.items()})
    return dataclasses.replace(rec, sensors=sensors)


def baseline_run(sc, rec, fault_detection=True):
    res = patent_baseline(rec, use_fault_detection=fault_detection)
    att, pos = errors(sc, res.t_ns, res.R_W_B, res.p_W)
    return {"att_deg": rms(att), "pos_mm": rms(pos), "pos_seen_mm": rms(at_tracker_times(rec, res.t_ns, pos)),
            "decisions": res.decisions}


SOFT_FAULT_TESTS = ("eigen", "bias_drift", "frozen")  # the library's inclinometer soft-fault decisions


def detection_delays(sc, decisions):
    alarms = np.array(sorted((d["t_ns"] - sc.t0_ns) * 1e-9 for d in decisions
                             if d["sensor"] == "incl0" and d.get("test") in SOFT_FAULT_TESTS
                             and d["decision"] == "fault"))
    out = []
    for f in sc.faults:
        if f.sensor != "incl0" or f.kind not in ("ramp", "stuck"):
            continue
        hit = alarms[(alarms >= f.start_s) & (alarms <= f.end_s + 10.0)]
        out.append({"kind": f.kind, "start_s": f.start_s, "delay_s": float(hit[0] - f.start_s) if len(hit) else None})
    return out


def throughput(duration_s: float, seed: int = 7, passes: int = 3):
    """Real-time factor and latencies of OnlineTracker.push over a pre-generated stream (fixed-lag), ``passes``
    fresh estimators over the same stream: the median pass (other processes share the 2 cores; CPU time is less
    sensitive to them than the wall clock, not immune: cache and memory bandwidth are shared too)."""
    sc = TrackerScenario(duration_s=duration_s, seed=seed)
    events = list(sc.stream(seed=1))
    runs = []
    for _ in range(passes):
        tracker = OnlineTracker(noise_from_meta(sc._meta()), mode="fixed-lag")
        lat = np.empty(len(events))
        wall0, cpu0 = time.perf_counter(), time.process_time()
        for i, (name, t, values) in enumerate(events):
            s = time.perf_counter()
            tracker.push(name, t, values)
            lat[i] = time.perf_counter() - s
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        kf = tracker.latency_s  # a LatencyHistogram of the keyframe pushes
        runs.append({"rt_factor_wall": duration_s / wall, "rt_factor_cpu": duration_s / cpu,
                     "p99_keyframe_ms": kf.percentile_s(99) * 1e3,
                     "p99_push_ms": float(np.percentile(lat, 99) * 1e3), "max_keyframe_ms": kf.max_s * 1e3,
                     "samples": len(events)})
    out = {key: float(np.median([r[key] for r in runs])) for key in runs[0]}
    out["samples"] = len(events)
    out["passes"] = runs
    return out


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def memory_run(duration_s: float, sample_every_s: float):
    """RSS along a long fixed-lag run fed sample by sample (the simulator streams in 60 s chunks)."""
    sc = TrackerScenario(duration_s=duration_s, seed=9)
    tracker = OnlineTracker(noise_from_meta(sc._meta()), mode="fixed-lag")
    marks, next_mark = [], sample_every_s
    for name, t, values in sc.stream(seed=2):
        tracker.push(name, t, values)
        if (t - sc.t0_ns) * 1e-9 >= next_mark:
            marks.append(((t - sc.t0_ns) * 1e-9, rss_mb(),
                          int(tracker.estimator._smoother.getFactors().nrFactors())))
            next_mark += sample_every_s
    return marks


def _quick_faults(duration_s: float = 120.0):
    """A 120 s schedule with every fault kind once (the default schedule needs >= 10 min for its soft faults);
    for shorter runs its times are scaled to the duration (a spike's and a jump's length kept)."""
    from selfcal.sim.tracker import Fault
    k = min(duration_s / 120.0, 1.0)
    return [Fault("incl0", "spike", 20.0 * k, 20.0 * k + 0.05, np.radians(1.5), 0),
            Fault("tracker0", "dropout", 30.0 * k, 34.0 * k),
            Fault("tracker0", "jump", 45.0 * k, 45.0 * k + 0.06, 0.015, 0, (0.0, 0.6, 0.8)),
            Fault("incl0", "ramp", 55.0 * k, 80.0 * k, np.radians(0.01), 1), Fault("incl0", "stuck", 90.0 * k, 110.0 * k)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, help=f"scenario seeds 1, 2, ... (default {_schema.DEFAULT_SEEDS}; 3 with --quick)")
    ap.add_argument("--duration", type=float,
                    help="run length in s (default 600; 120 with --quick); below 600 s the 120 s fault schedule "
                         "(its times scaled below 120 s)")
    ap.add_argument("--json", default=str(RESULTS / "tracker_vs_patent.json"))
    args = ap.parse_args(argv)
    start = time.perf_counter()
    duration = args.duration or (120.0 if args.quick else 600.0)
    seeds = list(range(1, 1 + (args.seeds or (3 if args.quick else _schema.DEFAULT_SEEDS))))
    short = duration < 600.0  # the default schedule's soft faults need >= 10 min
    table = {}
    delays = []
    stage_seconds = {}
    for seed in seeds:
        for faults in (False, True):
            sc = TrackerScenario(duration_s=duration, seed=seed, faults=faults if not short else (
                _quick_faults(duration) if faults else False))
            rec = sc.measurements(seed=100 + seed)
            jobs = {"gated": lambda: graph_run(sc, rec), "ungated": lambda: graph_run(sc, rec, gating=False),
                    "batch": lambda: graph_run(sc, rec, mode="batch"), "patent": lambda: baseline_run(sc, rec),
                    "patent_no_fd": lambda: baseline_run(sc, rec, fault_detection=False)}
            if faults:
                jobs["oracle"] = lambda: graph_run(sc, without_soft_faults(sc, rec))
            runs = {}
            for name, job in jobs.items():
                t_run = time.perf_counter()
                runs[name] = job()
                stage_seconds[f"seed {seed} faults={faults} {name}"] = time.perf_counter() - t_run
            for name, r in runs.items():
                table.setdefault((name, faults), []).append((r["att_deg"], r["pos_mm"], r["pos_seen_mm"]))
            if not faults:  # the oracle's fault-free run is the gated graph's
                table.setdefault(("oracle", False), []).append(table[("gated", False)][-1])
            if faults:
                delays.extend(detection_delays(sc, runs["gated"]["decisions"]))
            print(f"seed {seed} faults={faults}: " + ", ".join(
                f"{n} {r['att_deg']:.4f} deg {r['pos_mm']:.3f} mm" for n, r in runs.items()), flush=True)
    per_seed = {k: np.array(v) for k, v in table.items()}  # (seeds, 3): attitude, position, position at tracker
    rows = []

    def dist(metric, unit, lib, base=None, note=""):
        rows.append(_schema.distribution(metric, unit, lib, base, note=note))

    def row(metric, unit, lib, base, better="lower", note="baseline / library; > 1 means the library is better"):
        ratio = None if base is None or lib in (None, 0) else (base / lib if better == "lower" else lib / base)
        rows.append({"metric": metric, "unit": unit, "library": lib, "baseline": base, "ratio": ratio,
                     "better": better, "note": note})

    for faults in (False, True):
        tag = "with faults" if faults else "fault-free"
        for i, (q, unit) in enumerate((("attitude RMSE", "deg"), ("position RMSE over all outputs", "mm"),
                                       ("position RMSE at tracker sample times", "mm"))):
            dist(f"{q}, {tag}: gated graph (online) vs patent 004 filter", unit, per_seed[("gated", faults)][:, i],
                 per_seed[("patent", faults)][:, i])
            dist(f"{q}, {tag}: gated graph vs patent filter without its fault detection", unit,
                 per_seed[("gated", faults)][:, i], per_seed[("patent_no_fd", faults)][:, i])
            dist(f"{q}, {tag}: gated graph vs the same graph without gating", unit,
                 per_seed[("gated", faults)][:, i], per_seed[("ungated", faults)][:, i])
            dist(f"{q}, {tag}: batch smoother (gated) vs patent filter", unit, per_seed[("batch", faults)][:, i],
                 per_seed[("patent", faults)][:, i])
    for i, (q, unit) in enumerate((("attitude", "deg"), ("position (all outputs)", "mm"),
                                   ("position at tracker sample times", "mm"))):
        dist(f"gated graph {q} RMSE with faults / fault-free (target <= 1.2)", "ratio",
             per_seed[("gated", True)][:, i] / per_seed[("gated", False)][:, i], note="library only; per seed")
    for i, (q, unit) in enumerate((("attitude", "deg"), ("position (all outputs)", "mm"),
                                   ("position at tracker sample times", "mm"))):
        dist(f"gated graph {q} RMSE with faults / fault-free, inclinometer dropped exactly over its soft faults "
             "(oracle detector)", "ratio", per_seed[("oracle", True)][:, i] / per_seed[("oracle", False)][:, i],
             note="library only; per seed; the floor that detection cannot beat: what holding the sensor out costs")
    detected = [d["delay_s"] for d in delays if d["delay_s"] is not None]
    row("inclinometer soft faults detected", "fraction", len(detected) / max(len(delays), 1), None, better="higher",
        note=f"{len(delays)} ramp/stuck faults injected")
    if detected:
        row("soft-fault detection delay, median", "s", float(np.median(detected)), None, note="library only")
        row("soft-fault detection delay, max", "s", float(np.max(detected)), None, note="library only")
        for kind in ("ramp", "stuck"):
            of_kind = [d["delay_s"] for d in delays if d["kind"] == kind and d["delay_s"] is not None]
            if of_kind:
                row(f"soft-fault detection delay, median, {kind}", "s", float(np.median(of_kind)), None,
                    note=f"library only; {len(of_kind)} detected")
    # false alarms: pure H0 (no vibration, no faults) and fault-free with vibration
    h0_s = 120.0 if args.quick else 3600.0
    false_alarms = {}
    for label, bursts, dur in (("no vibration (H0)", 0.0, h0_s / 4 if not args.quick else h0_s),
                               ("with vibration bursts", 2.0, h0_s)):
        sc = TrackerScenario(duration_s=dur, seed=21, burst_rate_per_min=bursts)
        res = smooth_tracker(sc.measurements(seed=5), mode="fixed-lag")
        held = sum(1 for d in res.decisions if d["sensor"] == "incl0" and d["decision"] == "held_out")
        rejected = sum(1 for d in res.decisions if d["sensor"] == "incl0" and d["decision"] == "reject")
        false_alarms[label] = {"duration_s": dur, "bursts": len(sc.bursts), "incl_held_out_samples": held,
                               "incl_rejected_samples": rejected}
        print(f"fault-free {label}: {dur:.0f} s, {len(sc.bursts)} bursts, {held} inclinometer samples held out, "
              f"{rejected} rejected", flush=True)
        h0_s_run = dur
        alarms = sum(1 for d in res.decisions if d["sensor"] == "incl0" and d.get("test") in SOFT_FAULT_TESTS
                     and d["decision"] == "fault")
        base = patent_baseline(sc.measurements(seed=5))
        base_alarms = sum(1 for d in base.decisions if d["test"] == "eigen" and d["decision"] == "fault")
        row(f"inclinometer soft-fault alarms per hour, fault-free, {label}; stated rate 1/h", "1/h",
            alarms * 3600.0 / h0_s_run, base_alarms * 3600.0 / h0_s_run,
            note=f"{h0_s_run:.0f} s of data, {alarms} alarms; baseline = patent's eigenvalue test with the same "
                 "Wishart threshold")
        false_alarms[label].update({"alarms": alarms, "baseline_alarms": base_alarms})
    tp = throughput(20.0 if args.quick else 120.0)
    row("real-time factor, 200 Hz IMU + 50 Hz tracker + 10 Hz incl + 10 Hz cam, wall clock", "x",
        tp["rt_factor_wall"], None, better="higher", note="library only; one thread, shared 2-core machine; median "
        "of 3 passes (" + ", ".join(f"{r['rt_factor_wall']:.1f}" for r in tp["passes"]) + ")")
    row("real-time factor, CPU time", "x", tp["rt_factor_cpu"], None, better="higher",
        note="library only; median of 3 passes (" + ", ".join(f"{r['rt_factor_cpu']:.1f}" for r in tp["passes"]) + ")")
    row("p99 keyframe update latency", "ms", tp["p99_keyframe_ms"], None, note="library only")
    row("p99 latency over all pushes", "ms", tp["p99_push_ms"], None, note="library only")
    mem_s = 120.0 if args.quick else 3 * 3600.0
    marks = memory_run(mem_s, mem_s / 6)
    row(f"RSS growth from {marks[0][0]:.0f} s to {marks[-1][0]:.0f} s (fixed-lag)", "MB", marks[-1][1] - marks[0][1],
        None, note="library only; " + "; ".join(f"{t:.0f}s {m:.0f}MB {n} factors" for t, m, n in marks))
    seconds = time.perf_counter() - start
    out = {"benchmark": "tracker_vs_patent", "system": "tracker", "quick": bool(args.quick), "seconds": seconds,
           "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "rows": rows,
           "extra": {"stage_seconds": stage_seconds, "false_alarm_runs": false_alarms, "detections": delays, "throughput": tp, "memory": marks, "seeds": seeds, "duration_s": duration}}
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(_schema.clean(out), indent=1, allow_nan=False) + "\n")
    for r in rows:
        if "distribution" in r:
            print(_schema.describe(r))
            continue
        lib = f"{r['library']:.4g}" if r["library"] is not None else "-"
        base = f"{r['baseline']:.4g}" if r["baseline"] is not None else "-"
        ratio = f"{r['ratio']:.2f}" if r["ratio"] is not None else ""
        print(f"{r['metric']:<100s} {r['unit']:>6s} {lib:>10s} {base:>10s} {ratio:>6s}")
    print(f"wrote {path} ({seconds:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
